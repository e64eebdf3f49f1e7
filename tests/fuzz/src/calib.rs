//! The calibration files: dataset, truth, result and shaft-lines JSON, the intrinsics YAML
//! (OpenCV or ROS) and the stereo camera_info pair.

use hw_io::calib_files::{
    parse_dataset, parse_intrinsics_yaml, parse_lines, parse_result, parse_stereo_camera_info, parse_truth,
};

/// `data` as each calibration JSON file; a typed error or a value, never a panic.
pub fn json(data: &[u8]) {
    let Ok(text) = std::str::from_utf8(data) else { return };
    let _ = parse_dataset(text);
    let _ = parse_truth(text);
    let _ = parse_result(text);
    let _ = parse_lines(text);
}

/// `data` as an intrinsics YAML file, and (split at the first NUL byte, or twice the same
/// text) as a left/right camera_info pair. Accepted intrinsics are valid.
pub fn yaml(data: &[u8]) {
    let Ok(text) = std::str::from_utf8(data) else { return };
    if let Ok(k) = parse_intrinsics_yaml(text) {
        assert!(k.validate().is_ok(), "accepted intrinsics are invalid: {k:?}");
    }
    let (left, right) = text.split_once('\0').unwrap_or((text, text));
    if let Ok(stereo) = parse_stereo_camera_info(left, right) {
        assert!(stereo.baseline_m().is_finite(), "non-finite baseline: {stereo:?}");
    }
}
