//! Camera images (PNG, JPEG) in and PNG out, with errors that name the file.

use std::path::Path;

use image::{ImageFormat, ImageReader, RgbImage};

use crate::atomic::write_atomic_with;
use crate::{Error, Result};

fn image_error(path: &Path, e: image::ImageError) -> Error {
    match e {
        image::ImageError::IoError(io) => Error::io(path, io),
        other => Error::format(path, format!("cannot decode image: {other}")),
    }
}

/// Read a PNG or JPEG camera image as 8-bit RGB (format detected from the content). A truncated or
/// corrupt file is an error naming the file.
pub fn read_rgb_image(path: &Path) -> Result<RgbImage> {
    let reader = ImageReader::open(path)
        .map_err(|e| Error::io(path, e))?
        .with_guessed_format()
        .map_err(|e| Error::io(path, e))?;
    if reader.format().is_none() {
        return Err(Error::format(
            path,
            "not a PNG or JPEG image (unrecognised content)",
        ));
    }
    let img = reader.decode().map_err(|e| image_error(path, e))?;
    Ok(img.into_rgb8())
}

/// Width and height of an image from its header only (cheap; the pixels are not decoded).
pub fn image_dimensions(path: &Path) -> Result<(u32, u32)> {
    let reader = ImageReader::open(path)
        .map_err(|e| Error::io(path, e))?
        .with_guessed_format()
        .map_err(|e| Error::io(path, e))?;
    if reader.format().is_none() {
        return Err(Error::format(
            path,
            "not a PNG or JPEG image (unrecognised content)",
        ));
    }
    reader.into_dimensions().map_err(|e| image_error(path, e))
}

/// Encode an RGB image as PNG bytes.
pub fn encode_png(img: &RgbImage) -> Result<Vec<u8>> {
    let mut buf = std::io::Cursor::new(Vec::new());
    img.write_to(&mut buf, ImageFormat::Png)
        .map_err(|e| Error::Invalid {
            what: "image".into(),
            message: format!("PNG encoding failed: {e}"),
        })?;
    Ok(buf.into_inner())
}

/// Write an RGB image as PNG, atomically (temp file + rename).
pub fn write_png(path: &Path, img: &RgbImage) -> Result<()> {
    let bytes = encode_png(img)?;
    write_atomic_with(path, |w| std::io::Write::write_all(w, &bytes))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn png_round_trip_and_truncation() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("a.png");
        let img = RgbImage::from_fn(37, 11, |x, y| image::Rgb([x as u8, y as u8, (x * y) as u8]));
        write_png(&p, &img).unwrap();
        assert_eq!(read_rgb_image(&p).unwrap(), img);
        assert_eq!(image_dimensions(&p).unwrap(), (37, 11));

        let bytes = std::fs::read(&p).unwrap();
        let cut = dir.path().join("cut.png");
        std::fs::write(&cut, &bytes[..bytes.len() / 2]).unwrap();
        let e = read_rgb_image(&cut).unwrap_err().to_string();
        assert!(e.contains("cut.png"), "{e}");

        let junk = dir.path().join("junk.png");
        std::fs::write(&junk, b"definitely not an image").unwrap();
        let e = read_rgb_image(&junk).unwrap_err().to_string();
        assert!(e.contains("junk.png") && e.contains("decode"), "{e}");
        let e = read_rgb_image(&dir.path().join("missing.png"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("missing.png"), "{e}");
    }
}
