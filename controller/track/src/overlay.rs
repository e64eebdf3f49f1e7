//! Overlays: both eyes side by side (`DIR/overlay_NNNNNN.png`), the best hypothesis's
//! silhouette in green, the particle cloud's tips in cyan, the kinematics-only tip in red.

use std::path::Path;

use nalgebra::Point3;
use track::{Particle, StereoCameras, TrackedPose, Tracker};

use crate::input::Sequence;
use crate::run::RunError;

fn put(img: &mut [u8], w: usize, h: usize, x: f64, y: f64, rgb: [u8; 3], r: i64) {
    if !(x.is_finite() && y.is_finite()) {
        return;
    }
    let (cx, cy) = (x.round() as i64, y.round() as i64);
    for dy in -r..=r {
        for dx in -r..=r {
            let (px, py) = (cx + dx, cy + dy);
            if px >= 0 && py >= 0 && (px as usize) < w && (py as usize) < h {
                let i = (py as usize * w + px as usize) * 3;
                img[i..i + 3].copy_from_slice(&rgb);
            }
        }
    }
}

/// Writes frame `index`'s overlay into `dir`.
#[allow(clippy::too_many_arguments)]
pub fn write(
    dir: &Path,
    index: usize,
    _seq: &Sequence,
    tracker: &Tracker,
    cams: &StereoCameras,
    pose: Option<&TrackedPose>,
    images: [&hw_io::camera::png::RgbImage; 2],
    sil: &mut Vec<[f64; 2]>,
) -> Result<(), RunError> {
    let (w, h) = (images[0].width, images[0].height);
    let mut out = vec![0u8; 2 * w * h * 3];
    for (e, img) in images.iter().enumerate() {
        let mut eye = img.rgb.clone();
        let k = &cams.intrinsics[e];
        for p in tracker.particles() {
            let Some(tip) = tracker.model().tip_in_base(&p.joints) else { continue };
            let t_c_b = cams.eyes_from_base(&p.camera_delta)[e];
            let q = t_c_b * Point3::from(tip.translation.vector);
            if q.z > 1e-3 {
                let px = k.project(&q.coords);
                put(&mut eye, w, h, px.x, px.y, [0, 230, 255], 0);
            }
        }
        if let Some(p) = pose {
            let best = Particle { joints: p.joints_rad, jaw_rad: p.jaw_rad, camera_delta: p.camera_delta };
            track::measure::silhouette_px(tracker.model(), cams, &best, e, sil);
            for s in sil.iter() {
                put(&mut eye, w, h, s[0], s[1], [40, 255, 40], 0);
            }
        }
        for y in 0..h {
            let src = &eye[y * w * 3..(y + 1) * w * 3];
            let dst = (y * 2 * w + e * w) * 3;
            out[dst..dst + w * 3].copy_from_slice(src);
        }
    }
    let path = dir.join(format!("overlay_{index:06}.png"));
    hw_io::camera::png::write_rgb_png(&path, 2 * w, h, &out)
        .map_err(|e| RunError::Write { path: path.clone(), message: e.to_string() })
}
