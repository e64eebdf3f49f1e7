//! Tests of the renderer as a whole: determinism, the analytic ground truth against the
//! rendered masks, stereo geometry, degenerate inputs.

use estimator::calib::camera::IntrinsicsError;
use nalgebra::{Isometry3, Point3, Quaternion, Translation3, UnitQuaternion, Vector2, Vector3};

use super::config::{ConfigError, EndoscopeConfig, RealismConfig};
use super::mesh::{InstrumentGeometry, InstrumentMesh};
use super::render::{NewRendererError, RenderError, StereoFrame, StereoRenderer, label};
use super::scene::{DemoMotion, SceneState};
use super::truth::InstrumentTruth;

/// A small, fast configuration (160×120, small texture).
fn small(realism: RealismConfig, distorted: bool) -> EndoscopeConfig {
    let mut c = EndoscopeConfig::default();
    c.camera.intrinsics.width = 160;
    c.camera.intrinsics.height = 120;
    c.camera.intrinsics.fx = 100.0;
    c.camera.intrinsics.fy = 100.0;
    c.camera.intrinsics.cx = 79.5;
    c.camera.intrinsics.cy = 59.5;
    if !distorted {
        c.camera.intrinsics.distortion = [0.0; 5];
    }
    c.tissue.texture_px = 128;
    c.tissue.grid = 24;
    c.realism = realism;
    c
}

/// Full-size configuration without blur/noise, for the geometric checks.
fn full(distorted: bool) -> EndoscopeConfig {
    let mut c = EndoscopeConfig::default();
    if !distorted {
        c.camera.intrinsics.distortion = [0.0; 5];
    }
    c.tissue.texture_px = 256;
    c.realism = RealismConfig { tissue_texture: true, specular: true, ..RealismConfig::none() };
    c
}

fn renderer(cfg: EndoscopeConfig) -> StereoRenderer {
    StereoRenderer::new(cfg.clone(), cfg.instrument.mesh().unwrap()).unwrap()
}

fn demo(t_ns: u64) -> SceneState {
    DemoMotion::default().state_at(t_ns)
}

#[test]
fn same_seed_same_bytes_other_seed_other_noise() {
    let cfg = small(RealismConfig::default(), true);
    let mut a = renderer(cfg.clone());
    let mut b = renderer(cfg.clone());
    let fa = a.render(1_000_000_000, &demo).unwrap();
    let fb = b.render(1_000_000_000, &demo).unwrap();
    assert_eq!(fa.images, fb.images);
    assert_eq!(fa.truth, fb.truth);
    // Rendering again with the same renderer (reused buffers) gives the same bytes.
    let fa2 = a.render(1_000_000_000, &demo).unwrap();
    assert_eq!(fa.images, fa2.images);
    // Another seed: other noise (and another tissue texture), same ground truth.
    let mut c = renderer(EndoscopeConfig { seed: 2, ..cfg.clone() });
    let fc = c.render(1_000_000_000, &demo).unwrap();
    assert_ne!(fa.images[0].rgb, fc.images[0].rgb);
    assert_eq!(fa.truth, fc.truth);
    // Same seed, noise only differs between eyes and frames: with the texture off and the
    // noise on, two renders of a static scene at different times differ.
    let st = demo(0);
    let mut cfg_n = small(RealismConfig::none(), false);
    cfg_n.realism.noise.enabled = true;
    let mut d = renderer(cfg_n);
    let d1 = d.render(0, &|_| st).unwrap();
    let d2 = d.render(33_000_000, &|_| st).unwrap();
    assert_ne!(d1.images[0].rgb, d2.images[0].rgb);
    assert_eq!(d1.images[0].labels, d2.images[0].labels);
    // Without noise the same static scene gives the same bytes at any time.
    let mut e = renderer(small(RealismConfig::none(), false));
    assert_eq!(e.render(0, &|_| st).unwrap().images, e.render(33_000_000, &|_| st).unwrap().images);
}

#[test]
fn cached_tissue_gives_the_same_bytes_as_a_fresh_render() {
    // The endoscope held still for a few frames while the instruments move, then moved, then
    // still again: a renderer that keeps its tissue between frames renders every frame
    // exactly as a fresh renderer does (second instrument and smoke on: every path).
    let mut realism = RealismConfig { second_instrument: true, ..RealismConfig::default() };
    realism.smoke.enabled = true;
    for distorted in [true, false] {
        let cfg = small(realism, distorted);
        let held = demo(0).ecm_joints;
        let scene = |t: u64| {
            let mut s = demo(t);
            if !(700_000_000..900_000_000).contains(&t) {
                s.ecm_joints = held;
            }
            s
        };
        let mut kept = renderer(cfg.clone());
        let times: Vec<u64> = (0..8u64).map(|i| 400_000_000 + i * 100_000_000).collect();
        for &t in &times {
            let f = kept.render(t, &scene).unwrap();
            let fresh = renderer(cfg.clone()).render(t, &scene).unwrap();
            assert_eq!(f, fresh, "t {t} distorted {distorted}");
        }
        // 8 frames, the endoscope moving for 2 of them (t = 0.7 s and 0.8 s) and back: 4 draws.
        assert_eq!(kept.tissue_draws(), [4, 4], "distorted {distorted}");
    }
}

fn label_at(f: &StereoFrame, eye: usize, p: [f64; 2]) -> Option<u8> {
    let img = &f.images[eye];
    let (x, y) = (p[0].round(), p[1].round());
    if x < 0.0 || y < 0.0 || x >= img.width as f64 || y >= img.height as f64 {
        return None;
    }
    Some(img.labels[y as usize * img.width as usize + x as usize])
}

fn times() -> impl Iterator<Item = u64> {
    (0..8u64).map(|i| 400_000_000 + i * 730_000_000)
}

#[test]
fn tip_pixel_lies_inside_the_mask() {
    for distorted in [false, true] {
        let mut r = renderer(full(distorted));
        let mut checked = 0;
        for t in times() {
            let f = r.render(t, &demo).unwrap();
            for eye in 0..2 {
                let inst = &f.truth[eye].instruments[0];
                if let Some(tip) = inst.tip_px {
                    assert_eq!(label_at(&f, eye, tip), Some(label::INSTRUMENT), "t {t} eye {eye} tip {tip:?}");
                    checked += 1;
                }
            }
        }
        assert!(checked >= 12, "only {checked} tips in view");
    }
}

/// Camera-frame geometry of the shaft from the ground truth: distal end A, direction d.
fn shaft_axis(inst: &InstrumentTruth) -> (Vector3<f64>, Vector3<f64>) {
    let [w, x, y, z] = inst.pose_in_camera.quaternion_wxyz;
    let q = UnitQuaternion::from_quaternion(Quaternion::new(w, x, y, z));
    (Vector3::from(inst.pose_in_camera.translation_m), q * Vector3::z())
}

/// Checks, around points of each analytic contour, that every pixel centre at least 1 px
/// inside the contour is labelled as the instrument and every one at least 1 px outside is
/// not. Returns the number of points checked.
fn check_contours(r: &StereoRenderer, f: &StereoFrame, eye: usize) -> usize {
    let cfg = r.config();
    let k = cfg.camera.intrinsics;
    let g = &cfg.instrument;
    let inst = &f.truth[eye].instruments[0];
    let Some(contours) = &inst.contours else { return 0 };
    let (a, d) = shaft_axis(inst);
    let radius = g.shaft_radius_m();
    let img = &f.images[eye];
    let (w, h) = (img.width as i64, img.height as i64);
    // Far enough from the distal end that neither wrist nor jaws reach the contour in the
    // image (the demo motion keeps the wrist within ±0.45 rad, the jaws within 0.5 rad).
    let margin = 4.0 * radius;
    let mut checked = 0;
    for (ci, c) in contours.iter().enumerate() {
        let n = Vector3::from(c.plane_normal);
        let other = &contours[1 - ci].line_ideal;
        for i in 0..200 {
            let s = -margin - 0.5e-3 * i as f64;
            let p = a - n * radius + d * s;
            if p.z < 0.01 {
                continue;
            }
            let px = k.project(&p);
            let inward = k.project(&(p + n * 1e-5)) - px;
            let Some(u) = inward.try_normalize(1e-12) else { continue };
            let tangent = Vector2::new(-u.y, u.x);
            if px.x < 5.0 || px.y < 5.0 || px.x > (w - 6) as f64 || px.y > (h - 6) as f64 {
                continue;
            }
            // The shaft's width there (undistorted pixels) must leave room for the check.
            let ideal = k.k() * (p / p.z);
            if other[0] * ideal.x + other[1] * ideal.y + other[2] < 8.0 {
                continue;
            }
            checked += 1;
            let (cx, cy) = (px.x.round() as i64, px.y.round() as i64);
            for y in cy - 3..=cy + 3 {
                for x in cx - 3..=cx + 3 {
                    let q = Vector2::new(x as f64, y as f64) - px;
                    let (delta, along) = (q.dot(&u), q.dot(&tangent));
                    if along.abs() > 3.0 || delta.abs() > 3.0 {
                        continue;
                    }
                    let l = img.labels[(y * w + x) as usize];
                    if delta >= 1.0 {
                        assert_eq!(
                            l,
                            label::INSTRUMENT,
                            "eye {eye} contour {ci} s {s:.3}: pixel ({x}, {y}) {delta:.2} px inside"
                        );
                    } else if delta <= -1.0 {
                        assert_eq!(
                            l,
                            label::BACKGROUND,
                            "eye {eye} contour {ci} s {s:.3}: pixel ({x}, {y}) {delta:.2} px outside"
                        );
                    }
                }
            }
        }
    }
    checked
}

#[test]
fn analytic_contours_lie_within_a_pixel_of_the_mask_boundary() {
    for distorted in [false, true] {
        let mut r = renderer(full(distorted));
        let mut checked = 0;
        for t in times() {
            let f = r.render(t, &demo).unwrap();
            for eye in 0..2 {
                checked += check_contours(&r, &f, eye);
            }
        }
        assert!(checked > 150, "distorted {distorted}: only {checked} contour points checked");
    }
}

#[test]
fn projected_axis_lies_between_the_contours_and_inside_the_mask() {
    let mut r = renderer(full(true));
    let k = r.config().camera.intrinsics;
    let mut checked = 0;
    let mut asymmetric = 0;
    for t in times() {
        let f = r.render(t, &demo).unwrap();
        for eye in 0..2 {
            let inst = &f.truth[eye].instruments[0];
            let (Some(cs), Some(axis)) = (&inst.contours, &inst.axis) else { continue };
            let Some(seg) = axis.segment_ideal_px else { continue };
            for i in 1..20 {
                let t = i as f64 / 20.0;
                let u = [seg[0][0] + (seg[1][0] - seg[0][0]) * t, seg[0][1] + (seg[1][1] - seg[0][1]) * t];
                let d0 = cs[0].line_ideal[0] * u[0] + cs[0].line_ideal[1] * u[1] + cs[0].line_ideal[2];
                let d1 = cs[1].line_ideal[0] * u[0] + cs[1].line_ideal[1] * u[1] + cs[1].line_ideal[2];
                assert!(d0 > 0.0 && d1 > 0.0, "axis point {u:?} not between the contours: {d0} {d1}");
                if (d0 - d1).abs() > 0.05 {
                    asymmetric += 1; // perspective: the axis is not the midline
                }
                // On the axis' polyline (distorted), away from the ends: inside the mask.
                checked += 1;
            }
            for p in &axis.polyline_px[2..axis.polyline_px.len() - 2] {
                let l = label_at(&f, eye, *p);
                assert!(l.is_none() || l == Some(label::INSTRUMENT), "axis pixel {p:?} labelled {l:?}");
            }
            // The polyline's points are distorted images of the ideal segment.
            let ideal0 = k.undistort_px(&Vector2::from(axis.polyline_px[0]));
            assert!((ideal0 - Vector2::from(seg[0])).norm() < 1e-6);
        }
    }
    assert!(checked > 100 && asymmetric > 0, "checked {checked}, asymmetric {asymmetric}");
}

#[test]
fn stereo_disparity_has_the_expected_sign_and_magnitude() {
    let mut cfg = full(false);
    cfg.camera.baseline_m = 0.005;
    let r = renderer(cfg.clone());
    let q = [0.05, -0.03, 0.06, 0.2];
    let [left, right] = r.eye_poses(&q);
    // The right eye is the left moved by the baseline along the left's x.
    let rel = left.inverse() * right;
    assert!((rel.translation.vector - Vector3::new(0.005, 0.0, 0.0)).norm() < 1e-12);
    assert!(rel.rotation.angle() < 1e-12);
    let fx = cfg.camera.intrinsics.fx;
    for z in [0.04, 0.08, 0.15] {
        let p_c = Vector3::new(0.006, -0.004, z);
        let p_e = (left * Point3::from(p_c)).coords;
        let ul = r.project_world(&left, &p_e).unwrap();
        let ur = r.project_world(&right, &p_e).unwrap();
        let disparity = ul.x - ur.x;
        assert!((disparity - fx * 0.005 / z).abs() < 1e-9, "z {z}: {disparity}");
        assert!((ul.y - ur.y).abs() < 1e-9);
    }
    // With distortion, the undistorted pixels keep the relation; the rendered tips agree.
    let mut rd = renderer(full(true));
    let f = rd.render(1_500_000_000, &demo).unwrap();
    let k = full(true).camera.intrinsics;
    let (tl, tr) = (&f.truth[0].instruments[0], &f.truth[1].instruments[0]);
    let (Some(pl), Some(pr)) = (tl.tip_px, tr.tip_px) else { panic!("tip out of view") };
    let (il, ir) = (k.undistort_px(&Vector2::from(pl)), k.undistort_px(&Vector2::from(pr)));
    let z = tl.tip_camera_m[2];
    assert!((il.x - ir.x - k.fx * 0.005 / z).abs() < 1e-6, "{} vs {}", il.x - ir.x, k.fx * 0.005 / z);
    assert!((tr.tip_camera_m[2] - z).abs() < 1e-12);
    let _ = rd.render(1_600_000_000, &demo).unwrap();
}

#[test]
fn degenerate_inputs_give_typed_errors_not_panics() {
    let mesh = InstrumentGeometry::default().mesh().unwrap();
    let mut zero = EndoscopeConfig::default();
    zero.camera.intrinsics.width = 0;
    assert!(matches!(
        StereoRenderer::new(zero, mesh.clone()),
        Err(NewRendererError::Config(ConfigError::Intrinsics(IntrinsicsError::Size { .. })))
    ));
    let mut nan = EndoscopeConfig::default();
    nan.camera.intrinsics.fx = f64::NAN;
    assert!(matches!(StereoRenderer::new(nan, mesh.clone()), Err(NewRendererError::Config(_))));
    let mut huge = EndoscopeConfig::default();
    huge.camera.intrinsics.width = 100_000;
    assert!(matches!(
        StereoRenderer::new(huge, mesh.clone()),
        Err(NewRendererError::Config(ConfigError::TooLarge { .. }))
    ));
    let mut even = EndoscopeConfig::default();
    even.realism.motion_blur.samples = 4;
    assert!(matches!(
        StereoRenderer::new(even, mesh.clone()),
        Err(NewRendererError::Config(ConfigError::Range { .. }))
    ));
    let mut folded = EndoscopeConfig::default();
    folded.camera.intrinsics.distortion = [-3.0, 0.0, 0.0, 0.0, 0.0];
    assert!(matches!(
        StereoRenderer::new(folded, mesh.clone()),
        Err(NewRendererError::Config(ConfigError::Distortion))
    ));
    let mut baseline = EndoscopeConfig::default();
    baseline.camera.baseline_m = f64::INFINITY;
    assert!(StereoRenderer::new(baseline, mesh.clone()).is_err());
    let mut geometry = EndoscopeConfig::default();
    geometry.instrument.shaft_diameter_m = -1.0;
    assert!(matches!(
        StereoRenderer::new(geometry, mesh.clone()),
        Err(NewRendererError::Config(ConfigError::Geometry(_)))
    ));
    assert!(matches!(
        StereoRenderer::new(EndoscopeConfig::default(), InstrumentMesh { parts: vec![] }),
        Err(NewRendererError::Mesh)
    ));
    // Zero exposure is fine: no blur.
    let mut cfg = small(RealismConfig::default(), true);
    cfg.timing.exposure_s = 0.0;
    let mut r = renderer(cfg);
    r.render(0, &demo).unwrap();
    // NaN poses and joints: typed errors.
    let mut s = demo(0);
    s.instrument.pose_world.translation.vector.x = f64::NAN;
    assert!(matches!(r.render(0, &|_| s), Err(RenderError::NotFinite { .. })));
    let mut s = demo(0);
    s.ecm_joints[2] = f64::INFINITY;
    assert!(matches!(r.render(0, &|_| s), Err(RenderError::NotFinite { .. })));
    let mut s = demo(0);
    s.instrument.jaw_rad[1] = f64::NAN;
    assert!(matches!(r.render(0, &|_| s), Err(RenderError::NotFinite { .. })));
    // Odd but finite scenes render: the camera inside the shaft, the instrument behind the
    // camera, the instrument through the camera plane.
    for pose in [
        Isometry3::from_parts(Translation3::new(0.0, 0.0, 0.1), UnitQuaternion::identity()),
        Isometry3::from_parts(Translation3::new(0.0, 0.0, -0.2), UnitQuaternion::identity()),
        Isometry3::from_parts(
            Translation3::new(0.01, 0.0, 0.07),
            UnitQuaternion::from_axis_angle(&Vector3::y_axis(), 1.2),
        ),
    ] {
        let mut s = demo(0);
        s.instrument.pose_world = pose;
        s.ecm_joints = [0.0, 0.0, 0.0, 0.0];
        let f = r.render(0, &|_| s).unwrap();
        assert_eq!(f.images[0].rgb.len(), 160 * 120 * 3);
        for eye in &f.truth {
            assert!(eye.instruments[0].tip_camera_m.iter().all(|v| v.is_finite()));
        }
    }
}

#[test]
fn realism_options_change_the_image_and_second_instrument_occludes() {
    let base = small(RealismConfig::none(), true);
    let mut r0 = renderer(base.clone());
    let mut options: Vec<(&str, RealismConfig)> = Vec::new();
    let none = RealismConfig::none();
    options.push(("specular", RealismConfig { specular: true, ..none }));
    options.push(("texture", RealismConfig { tissue_texture: true, ..none }));
    let mut v = none;
    v.vignetting.enabled = true;
    options.push(("vignetting", v));
    let mut d = none;
    d.defocus.enabled = true;
    options.push(("defocus", d));
    let mut n = none;
    n.noise.enabled = true;
    options.push(("noise", n));
    let mut s = none;
    s.smoke.enabled = true;
    options.push(("smoke", s));
    let mut m = none;
    m.motion_blur.enabled = true;
    options.push(("motion blur", m));
    // A moving instrument (motion blur needs motion); the plain frame is rendered once.
    let moving = |t| DemoMotion { speed: 6.0, ..Default::default() }.state_at(t);
    let plain = renderer(base.clone()).render(2_000_000_000, &moving).unwrap();
    for (name, realism) in options {
        let mut r = renderer(EndoscopeConfig { realism, ..base.clone() });
        let f = r.render(2_000_000_000, &moving).unwrap();
        assert_ne!(f.images[0].rgb, plain.images[0].rgb, "{name} changed nothing");
        assert_eq!(f.images[0].labels, plain.images[0].labels, "{name} changed the mask");
    }
    // The second instrument: label 2 appears, the truth lists it, and it hides some pixels
    // of the first at some time of the demo motion.
    let mut two = renderer(EndoscopeConfig { realism: RealismConfig { second_instrument: true, ..none }, ..base });
    let mut occluded = false;
    for i in 0..40u64 {
        let t = i * 250_000_000;
        let f2 = two.render(t, &demo).unwrap();
        let f1 = r0.render(t, &demo).unwrap();
        assert_eq!(f2.truth[0].instruments.len(), 2);
        let hidden = f1.images[0].labels.iter().zip(&f2.images[0].labels).filter(|(a, b)| **a == 1 && **b == 2).count();
        occluded |= hidden > 20;
    }
    assert!(occluded, "the second instrument never passes in front of the first");
}

#[test]
fn occluder_hides_the_instrument_and_the_truth_counts_it() {
    use super::render::Occluder;
    use crate::world::occluder_for;
    let cfg = small(RealismConfig::none(), true);
    let mut r = renderer(cfg);
    let t = 1_000_000_000;
    let st = demo(t);
    let clear = r.render(t, &|_| st).unwrap();
    for eye in 0..2 {
        let v = clear.truth[eye].visibility;
        assert!(v.unoccluded_px > 50, "the instrument in view: {v:?}");
        assert_eq!(v.visible_px, v.unoccluded_px, "nothing in front");
    }
    let tip_px = |f: &StereoFrame| {
        let p = f.truth[0].instruments[0].tip_px.unwrap();
        let w = f.images[0].width as usize;
        f.images[0].labels[p[1].round() as usize * w + p[0].round() as usize]
    };
    assert_eq!(tip_px(&clear), label::INSTRUMENT);
    // All of it hidden: almost nothing visible in either eye, the same unoccluded count.
    r.set_occluder(occluder_for(&r, &st, 1.0, false));
    assert!(r.occluder().is_some());
    let hidden = r.render(t, &|_| st).unwrap();
    for eye in 0..2 {
        let v = hidden.truth[eye].visibility;
        assert_eq!(v.unoccluded_px, clear.truth[eye].visibility.unoccluded_px);
        assert!(v.fraction().unwrap() < 0.02, "eye {eye}: {v:?}");
        assert!(hidden.images[eye].labels.contains(&label::OCCLUDER));
    }
    // Half, tip end first: the tip hidden; half, shaft end first: the tip in view.
    for (shaft_end, tip_label) in [(false, label::OCCLUDER), (true, label::INSTRUMENT)] {
        r.set_occluder(occluder_for(&r, &st, 0.5, shaft_end));
        let half = r.render(t, &|_| st).unwrap();
        let f = half.truth[0].visibility.fraction().unwrap();
        assert!((0.25..0.8).contains(&f), "shaft end {shaft_end}: left visible fraction {f}");
        assert_eq!(tip_px(&half), tip_label, "shaft end {shaft_end}");
    }
    // Taken away: the same bytes as before it came (the kept tissue put back).
    r.set_occluder(None);
    assert_eq!(r.render(t, &|_| st).unwrap().images, clear.images);
    // A non-finite or degenerate plate is refused.
    let mut bad = occluder_for(&r, &st, 1.0, false).unwrap();
    bad.half_size_m[0] = f64::NAN;
    r.set_occluder(Some(bad));
    assert!(matches!(r.render(t, &|_| st), Err(RenderError::NotFinite { .. })));
    let mut bad = Occluder { half_size_m: [0.0, 0.01], ..bad };
    bad.pose_world = Isometry3::identity();
    r.set_occluder(Some(bad));
    assert!(r.render(t, &|_| st).is_err());
}

#[test]
fn occlusion_windows_parse_or_are_refused() {
    use crate::world::OcclusionWindow;
    let w: OcclusionWindow = "3:1:0.5".parse().unwrap();
    assert_eq!((w.start_s, w.duration_s, w.fraction, w.from_shaft_end), (3.0, 1.0, 0.5, false));
    assert!(w.contains(3.0) && w.contains(3.99) && !w.contains(4.0) && !w.contains(2.9));
    let w: OcclusionWindow = "8:1.5:1:shaft".parse().unwrap();
    assert!(w.from_shaft_end && w.fraction == 1.0);
    assert!(!"8:1:1:tip".parse::<OcclusionWindow>().unwrap().from_shaft_end);
    for bad in ["3:1", "3:1:1.5", "3:1:0", "a:1:0.5", "3:-1:0.5", "3:1:0.5:side", "NaN:1:0.5", ""] {
        assert!(bad.parse::<OcclusionWindow>().is_err(), "{bad:?}");
    }
}
