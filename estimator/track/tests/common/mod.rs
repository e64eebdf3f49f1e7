//! A synthetic stereo scene for the tracker's tests and bench (the simulator is not a
//! dependency of this crate): a small instrument model, cameras looking at its tip, and images
//! with the instrument's silhouette drawn dark on a noisy light background.
#![allow(dead_code, clippy::unwrap_used, clippy::expect_used, reason = "test helpers")]

use estimator::calib::Intrinsics;
use estimator::kinematics::{Achilles, AchillesConfig};
use nalgebra::{Isometry3, Point3, Translation3, UnitQuaternion, Vector3};
use track::{FrameInput, Part, PartMesh, Particle, StereoCameras, ToolGeometry, ToolModel};

pub const W: usize = 640;
pub const H: usize = 480;

fn cylinder(z0: f32, z1: f32, r: f32, seg: u32) -> (Vec<[f32; 3]>, Vec<[u32; 3]>) {
    let mut p = Vec::new();
    let mut t = Vec::new();
    for z in [z0, z1] {
        for k in 0..seg {
            let a = std::f32::consts::TAU * k as f32 / seg as f32;
            p.push([r * a.cos(), r * a.sin(), z]);
        }
    }
    for k in 0..seg {
        let k1 = (k + 1) % seg;
        t.push([k, k1, seg + k1]);
        t.push([k, seg + k1, seg + k]);
    }
    // Caps (fans about the first vertex of each ring).
    for k in 1..seg - 1 {
        t.push([0, k + 1, k]);
        t.push([seg, seg + k, seg + k + 1]);
    }
    (p, t)
}

fn jaw(side: f32) -> (Vec<[f32; 3]>, Vec<[u32; 3]>) {
    let (w0, t0, l) = (0.003f32, 0.0034f32, 0.018f32);
    let x = |v: f32| side * v;
    let mut c = vec![
        [0.0, -w0, 0.0],
        [x(t0), -w0, 0.0],
        [x(t0), w0, 0.0],
        [0.0, w0, 0.0],
        [0.0, -w0 * 0.4, l],
        [x(t0 * 0.4), -w0 * 0.4, l],
        [x(t0 * 0.4), w0 * 0.4, l],
        [0.0, w0 * 0.4, l],
    ];
    if side < 0.0 {
        c.swap(1, 3);
        c.swap(5, 7);
    }
    let faces: [[u32; 4]; 6] = [[0, 3, 2, 1], [4, 5, 6, 7], [0, 1, 5, 4], [1, 2, 6, 5], [2, 3, 7, 6], [3, 0, 4, 7]];
    let t = faces.iter().flat_map(|f| [[f[0], f[1], f[2]], [f[0], f[2], f[3]]]).collect();
    (c, t)
}

pub fn model() -> ToolModel {
    let arm = Achilles::new(&AchillesConfig::default()).unwrap();
    let (sp, st) = cylinder(-0.1, 0.0, 0.004, 16);
    let (wp, wt) = cylinder(0.0, 0.01, 0.00375, 16);
    let (j1p, j1t) = jaw(1.0);
    let (j2p, j2t) = jaw(-1.0);
    let meshes = [
        PartMesh { part: Part::Shaft, positions: sp, triangles: st },
        PartMesh { part: Part::Wrist, positions: wp, triangles: wt },
        PartMesh { part: Part::Jaw1, positions: j1p, triangles: j1t },
        PartMesh { part: Part::Jaw2, positions: j2p, triangles: j2t },
    ];
    let g =
        ToolGeometry { instrument_length_m: 0.3, wrist_length_m: 0.01, shaft_radius_m: 0.004, shaft_modelled_m: 0.1 };
    ToolModel::new(arm, g, &meshes).unwrap()
}

pub fn intrinsics() -> Intrinsics {
    Intrinsics {
        fx: 400.0,
        fy: 400.0,
        cx: 319.5,
        cy: 239.5,
        skew: 0.0,
        width: W as u32,
        height: H as u32,
        distortion: [-0.08, 0.01, 0.0, 0.0, 0.0],
    }
}

/// Joints of frame `k` of a slow motion (radians).
pub fn joints(k: usize) -> [f64; 6] {
    let t = k as f64 * 0.1;
    [0.05 * t.sin(), 0.9 + 0.03 * t.cos(), 1.2 + 0.02 * t, 0.1, 0.2 + 0.05 * t.sin(), 0.3]
}

/// Cameras 9 cm from the tip of `joints(0)`, looking at it from the side of the shaft.
pub fn cameras(model: &ToolModel) -> StereoCameras {
    let tip = model.tip_in_base(&joints(0)).unwrap();
    let axis = tip.rotation * Vector3::z();
    let side = axis.cross(&Vector3::new(0.3, 0.2, 1.0)).normalize();
    let eye = tip.translation.vector + side * 0.09 - axis * 0.03;
    let target = tip.translation.vector - axis * 0.02;
    // Camera frame: z toward the target, y down-ish.
    let z = (target - eye).normalize();
    let x = z.cross(&axis).normalize();
    let y = z.cross(&x);
    let r = nalgebra::Rotation3::from_matrix_unchecked(nalgebra::Matrix3::from_columns(&[x, y, z]));
    let cam_in_base = Isometry3::from_parts(Translation3::from(eye), UnitQuaternion::from_rotation_matrix(&r));
    StereoCameras {
        intrinsics: [intrinsics(); 2],
        left_from_base: cam_in_base.inverse(),
        right_from_left: Isometry3::translation(-0.005, 0.0, 0.0),
    }
}

/// The images of `truth` (left, right): the silhouette drawn 2 px wide, dark, on noise.
pub fn images(model: &ToolModel, cams: &StereoCameras, truth: &Particle, seed: u32) -> [Vec<u8>; 2] {
    let mut out = [vec![0u8; W * H * 3], vec![0u8; W * H * 3]];
    let mut pts = Vec::new();
    for (e, img) in out.iter_mut().enumerate() {
        let mut s = seed.wrapping_mul(747_796_405).wrapping_add(e as u32 + 1);
        for px in img.chunks_exact_mut(3) {
            s ^= s << 13;
            s ^= s >> 17;
            s ^= s << 5;
            let v = 170 + (s % 24) as u8;
            px.copy_from_slice(&[v, v.saturating_sub(40), v.saturating_sub(50)]);
        }
        track::measure::silhouette_px(model, cams, truth, e, &mut pts);
        for p in &pts {
            for dy in 0..2 {
                for dx in 0..2 {
                    let (x, y) = (p[0].round() as i64 + dx, p[1].round() as i64 + dy);
                    if x >= 0 && y >= 0 && (x as usize) < W && (y as usize) < H {
                        let i = (y as usize * W + x as usize) * 3;
                        img[i..i + 3].copy_from_slice(&[40, 40, 45]);
                    }
                }
            }
        }
    }
    out
}

pub fn input<'a>(cams: &StereoCameras, k: usize, imgs: &'a [Vec<u8>; 2]) -> FrameInput<'a> {
    FrameInput {
        encoder_rad: joints(k),
        cameras: *cams,
        rgb: [&imgs[0], &imgs[1]],
        time_ns: Some(k as u64 * 100_000_000),
    }
}

/// A joint offset that moves the tip by a few millimetres.
pub fn offset(q: &[f64; 6]) -> [f64; 6] {
    let mut o = *q;
    o[0] += 0.006;
    o[1] -= 0.004;
    o[4] += 0.01;
    o
}

pub fn tip_error_mm(model: &ToolModel, q: &[f64; 6], truth: &[f64; 6]) -> f64 {
    let a = model.tip_in_base(q).unwrap().translation.vector;
    let b = model.tip_in_base(truth).unwrap().translation.vector;
    (a - b).norm() * 1e3
}

pub fn point(model: &ToolModel, q: &[f64; 6]) -> Point3<f64> {
    Point3::from(model.tip_in_base(q).unwrap().translation.vector)
}

/// The pose index of frame `n`: back and forth over `joints(0..=8)` (the instrument stays in
/// view however many frames are counted).
pub fn pose_of_frame(n: usize) -> usize {
    let k = n % 16;
    if k <= 8 { k } else { 16 - k }
}

/// The rendered stereo pair of each pose `joints(0..=8)` (jaw 0.2 rad), in order.
pub fn pose_images(model: &ToolModel, cams: &StereoCameras) -> Vec<[Vec<u8>; 2]> {
    (0..=8)
        .map(|k| images(model, cams, &Particle { joints: joints(k), jaw_rad: 0.2, camera_delta: [0.0; 6] }, k as u32))
        .collect()
}

/// Frame `n` of the back-and-forth sequence over `pose_images` ([`pose_of_frame`]): the
/// pose's encoders and pair, 100 ms apart.
pub fn back_and_forth<'a>(cams: &StereoCameras, images: &'a [[Vec<u8>; 2]], n: usize) -> FrameInput<'a> {
    let f = &images[pose_of_frame(n)];
    FrameInput {
        encoder_rad: joints(pose_of_frame(n)),
        cameras: *cams,
        rgb: [&f[0], &f[1]],
        time_ns: Some(n as u64 * 100_000_000),
    }
}
