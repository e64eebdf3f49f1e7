//! Single images as files: one PNG read as 8-bit RGB, one RGB buffer written as PNG (for the
//! tools that look at stills: `comanip-calib detect` and its overlays). Feature `camera`.
//!
//! Pixels: row-major, 3 bytes per pixel (sRGB), no padding; grey and RGBA images are expanded
//! to RGB (alpha dropped); 16-bit images are refused.

use std::path::{Path, PathBuf};

/// An 8-bit RGB image read from a file.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct RgbImage {
    /// Width, pixels.
    pub width: usize,
    /// Height, pixels.
    pub height: usize,
    /// `3 · width · height` bytes, row-major RGB.
    pub rgb: Vec<u8>,
}

/// Why an image could not be read.
#[derive(Debug, thiserror::Error)]
pub enum ReadImageError {
    /// The file cannot be opened or decoded.
    #[error("cannot decode {path}: {source}")]
    Decode {
        /// The file.
        path: PathBuf,
        /// The decoder's reason.
        source: image::ImageError,
    },
    /// Not an 8-bit grey, grey-alpha, RGB or RGBA image.
    #[error("{path}: colour type {color:?} is not 8-bit grey, RGB or RGBA")]
    ColorType {
        /// The file.
        path: PathBuf,
        /// Its colour type.
        color: image::ColorType,
    },
}

/// Why an image could not be written.
#[derive(Debug, thiserror::Error)]
pub enum WriteImageError {
    /// The buffer is not `3 · width · height` bytes, or a side is zero or too large.
    #[error("{len} bytes are not a {width}x{height} RGB image")]
    Size {
        /// Width, pixels.
        width: usize,
        /// Height, pixels.
        height: usize,
        /// Bytes given.
        len: usize,
    },
    /// The encoder or the file system refused.
    #[error("cannot write {path}: {source}")]
    Encode {
        /// The file.
        path: PathBuf,
        /// The encoder's reason.
        source: image::ImageError,
    },
}

/// Reads an image file (PNG, or any format the `image` crate was built with) as 8-bit RGB.
pub fn read_rgb(path: &Path) -> Result<RgbImage, ReadImageError> {
    let decode = |source| ReadImageError::Decode { path: path.to_owned(), source };
    let img = image::ImageReader::open(path)
        .map_err(|e| decode(image::ImageError::IoError(e)))?
        .with_guessed_format()
        .map_err(|e| decode(image::ImageError::IoError(e)))?
        .decode()
        .map_err(decode)?;
    let rgb = match img {
        image::DynamicImage::ImageLuma8(_)
        | image::DynamicImage::ImageLumaA8(_)
        | image::DynamicImage::ImageRgb8(_)
        | image::DynamicImage::ImageRgba8(_) => img.to_rgb8(),
        other => return Err(ReadImageError::ColorType { path: path.to_owned(), color: other.color() }),
    };
    let (width, height) = (rgb.width() as usize, rgb.height() as usize);
    Ok(RgbImage { width, height, rgb: rgb.into_raw() })
}

/// Writes a `width × height` RGB buffer as a PNG file.
pub fn write_rgb_png(path: &Path, width: usize, height: usize, rgb: &[u8]) -> Result<(), WriteImageError> {
    let size = WriteImageError::Size { width, height, len: rgb.len() };
    let (Ok(w), Ok(h)) = (u32::try_from(width), u32::try_from(height)) else { return Err(size) };
    if width == 0 || height == 0 || width.checked_mul(height).and_then(|n| n.checked_mul(3)) != Some(rgb.len()) {
        return Err(size);
    }
    image::save_buffer(path, rgb, w, h, image::ExtendedColorType::Rgb8)
        .map_err(|source| WriteImageError::Encode { path: path.to_owned(), source })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trip_and_refusals() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("a.png");
        let px: Vec<u8> = (0..2 * 3 * 3).map(|i| (i * 13) as u8).collect();
        write_rgb_png(&p, 3, 2, &px).unwrap();
        let back = read_rgb(&p).unwrap();
        assert_eq!((back.width, back.height), (3, 2));
        assert_eq!(back.rgb, px);
        assert!(matches!(write_rgb_png(&p, 3, 2, &px[1..]), Err(WriteImageError::Size { .. })));
        assert!(matches!(write_rgb_png(&p, 0, 2, &[]), Err(WriteImageError::Size { .. })));
        std::fs::write(dir.path().join("bad.png"), b"not a png").unwrap();
        assert!(matches!(read_rgb(&dir.path().join("bad.png")), Err(ReadImageError::Decode { .. })));
        assert!(matches!(read_rgb(&dir.path().join("missing.png")), Err(ReadImageError::Decode { .. })));
    }
}
