//! Camera images (PNG, JPEG) in and PNG out, and image-aligned maps (depth, class ids) in, with
//! errors that name the file.

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

type FileImageReader = ImageReader<std::io::BufReader<std::fs::File>>;

/// An image file opened with its format detected from the content (`format()` is `None` for content
/// the `image` crate does not know).
fn open_image(path: &Path) -> Result<FileImageReader> {
    // a FIFO would block the open, a device would be read as an image
    crate::read_capped::check_regular_file(path)?;
    ImageReader::open(path)
        .map_err(|e| Error::io(path, e))?
        .with_guessed_format()
        .map_err(|e| Error::io(path, e))
}

/// [`open_image`] for a camera image: any known format, else an error naming the file.
fn open_camera_image(path: &Path) -> Result<FileImageReader> {
    let reader = open_image(path)?;
    if reader.format().is_none() {
        return Err(Error::format(
            path,
            "not a PNG or JPEG image (unrecognised content)",
        ));
    }
    Ok(reader)
}

/// The decoded image of a PNG or JPEG file (format detected from the content), read strictly: the
/// file must be a regular file of at most [`MAX_CAMERA_IMAGE_BYTES`], and complete
/// ([`check_complete`]: the `image` crate's JPEG decoder fills a truncated image with grey
/// without an error). Errors name the file.
///
/// [`MAX_CAMERA_IMAGE_BYTES`]: crate::read_capped::MAX_CAMERA_IMAGE_BYTES
pub fn read_image(path: &Path) -> Result<image::DynamicImage> {
    read_image_as(path, None)
}

/// [`read_image`], refusing any format but `only` when it is given (before decoding).
fn read_image_as(path: &Path, only: Option<ImageFormat>) -> Result<image::DynamicImage> {
    let bytes = crate::read_capped::read_metadata(
        path,
        crate::read_capped::MAX_CAMERA_IMAGE_BYTES,
        "an image",
    )?;
    let mut reader = ImageReader::new(std::io::Cursor::new(bytes.as_slice()))
        .with_guessed_format()
        .map_err(|e| Error::io(path, e))?;
    // content the crate does not recognise is decoded as its extension says, so that a broken
    // `x.png` is "cannot decode" with the decoder's reason (as a reader on the file does)
    let recognised = reader.format().is_some();
    if !recognised && let Ok(f) = ImageFormat::from_path(path) {
        reader.set_format(f);
    }
    let format = match (reader.format(), only) {
        (None, _) => {
            return Err(Error::format(
                path,
                "not a PNG or JPEG image (unrecognised content)",
            ));
        }
        (Some(f), Some(want)) if f != want => {
            let name = if want == ImageFormat::Png {
                "PNG".to_string()
            } else {
                format!("{want:?}")
            };
            return Err(Error::format(path, format!("not a {name} image")));
        }
        (Some(f), _) => f,
    };
    if recognised {
        check_complete(&bytes, format).map_err(|why| Error::format(path, why))?;
    }
    reader.decode().map_err(|e| image_error(path, e))
}

/// Read a PNG or JPEG camera image as 8-bit RGB ([`read_image`]: a truncated or corrupt file is an
/// error naming the file).
pub fn read_rgb_image(path: &Path) -> Result<RgbImage> {
    Ok(read_image(path)?.into_rgb8())
}

/// Checks that the bytes of a PNG or JPEG image hold the whole image, by walking the file's
/// structure (no pixel is decoded): a PNG's chunks up to `IEND`, a JPEG's segments and
/// entropy-coded scans up to the end-of-image marker (what follows it, a trailer some cameras
/// append, is ignored). Other formats pass. The `Err` says where the data end.
pub fn check_complete(bytes: &[u8], format: ImageFormat) -> std::result::Result<(), String> {
    match format {
        ImageFormat::Png => png_complete(bytes),
        ImageFormat::Jpeg => jpeg_complete(bytes),
        _ => Ok(()),
    }
}

/// A PNG's chunks: `length (4, big-endian) | type (4) | data | CRC (4)` after the 8-byte signature,
/// up to the `IEND` chunk.
fn png_complete(bytes: &[u8]) -> std::result::Result<(), String> {
    let truncated = |what: String| {
        Err(format!(
            "truncated PNG: the file ({} bytes) ends {what} (no IEND chunk)",
            bytes.len()
        ))
    };
    if !bytes.starts_with(b"\x89PNG\r\n\x1a\n") {
        return Err("not a PNG image (no PNG signature)".into());
    }
    let mut pos = 8usize;
    loop {
        let Some(head) = bytes.get(pos..pos + 8) else {
            return truncated(format!("at byte {pos}, where a chunk should start"));
        };
        let len = u32::from_be_bytes([head[0], head[1], head[2], head[3]]) as usize;
        let kind = String::from_utf8_lossy(&head[4..8]).into_owned();
        let end = pos.saturating_add(12).saturating_add(len);
        if end > bytes.len() {
            return truncated(format!(
                "inside its {} chunk at byte {pos} ({len} bytes of data)",
                kind.escape_debug()
            ));
        }
        if &head[4..8] == b"IEND" {
            return Ok(());
        }
        pos = end;
    }
}

/// A JPEG's segments from SOI to EOI: markers `FF xx` with a 2-byte length, except the standalone
/// ones (`RSTn`, `TEM`), and after each start of scan its entropy-coded data, which ends at the
/// first `FF` followed by neither `00` (a stuffed byte) nor a restart marker.
fn jpeg_complete(bytes: &[u8]) -> std::result::Result<(), String> {
    let truncated = |what: &str| {
        Err(format!(
            "truncated JPEG: the file ({} bytes) ends {what}, before its end-of-image marker",
            bytes.len()
        ))
    };
    if !bytes.starts_with(&[0xFF, 0xD8]) {
        return Err("not a JPEG image (no start-of-image marker)".into());
    }
    let mut pos = 2usize; // after SOI (FF D8)
    loop {
        // the next marker: FF (fill bytes FF allowed), then its code; stray bytes are skipped, as
        // decoders do
        let Some(ff) = bytes[pos.min(bytes.len())..]
            .iter()
            .position(|&b| b == 0xFF)
        else {
            return truncated("between two segments");
        };
        pos += ff;
        while bytes.get(pos) == Some(&0xFF) {
            pos += 1;
        }
        let Some(&code) = bytes.get(pos) else {
            return truncated("inside a marker");
        };
        pos += 1;
        match code {
            0xD9 => return Ok(()),
            0xD0..=0xD7 | 0x01 | 0x00 => continue,
            _ => {}
        }
        let Some(len) = bytes.get(pos..pos + 2) else {
            return truncated(&format!("inside the length of segment FF{code:02X}"));
        };
        let len = usize::from(u16::from_be_bytes([len[0], len[1]]));
        let end = pos + len;
        if len < 2 || end > bytes.len() {
            return truncated(&format!(
                "inside segment FF{code:02X} at byte {} ({len} bytes)",
                pos - 2
            ));
        }
        pos = end;
        if code == 0xDA {
            // entropy-coded data up to the next marker
            loop {
                let Some(ff) = bytes[pos..].iter().position(|&b| b == 0xFF) else {
                    return truncated("inside its image data");
                };
                pos += ff;
                match bytes.get(pos + 1) {
                    None => return truncated("inside its image data"),
                    Some(0x00 | 0xD0..=0xD7) => pos += 2,
                    Some(0xFF) => pos += 1,
                    Some(_) => break,
                }
            }
        }
    }
}

/// Width and height of an image from its header only (cheap; the pixels are not decoded).
pub fn image_dimensions(path: &Path) -> Result<(u32, u32)> {
    open_camera_image(path)?
        .into_dimensions()
        .map_err(|e| image_error(path, e))
}

/// The image at `path` decoded when `load`, else only its size read from the header; with its
/// `(width, height)` either way.
pub fn read_rgb_image_if(path: &Path, load: bool) -> Result<(Option<RgbImage>, (u32, u32))> {
    if load {
        let img = read_rgb_image(path)?;
        let d = img.dimensions();
        Ok((Some(img), d))
    } else {
        Ok((None, image_dimensions(path)?))
    }
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

/// A row-major `height x width` map aligned with a camera image (depth in metres, or class ids).
#[derive(Debug, Clone, PartialEq)]
pub struct ImageMap<T> {
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
    /// `height * width` values, row-major.
    pub data: Vec<T>,
}

fn lower_ext(path: &Path) -> String {
    path.extension()
        .map(|e| e.to_string_lossy().to_lowercase())
        .unwrap_or_default()
}

/// Decodes a PNG map (any other content is an error naming the file; read as [`read_image`]
/// reads, a truncated file is one too).
fn decode_png(path: &Path) -> Result<image::DynamicImage> {
    read_image_as(path, Some(ImageFormat::Png))
}

/// Read a depth map aligned with a camera image:
///
/// * `.png`: 16-bit greyscale in the KITTI depth convention, `depth_m = value / 256`, 0 = no depth
///   (what `veila simulate` writes to `depth_2/` and KITTI's depth benchmark uses). An 8-bit or colour
///   PNG is refused: it cannot hold metric depth.
/// * `.npy`: a float32 / float64 array of shape `[H, W]` (leading axes of size 1 allowed), values as
///   stored (metres, or a relative depth to be aligned; not disparity).
pub fn read_depth_map(path: &Path) -> Result<ImageMap<f32>> {
    match lower_ext(path).as_str() {
        "png" => match decode_png(path)? {
            image::DynamicImage::ImageLuma16(img) => Ok(ImageMap {
                width: img.width(),
                height: img.height(),
                data: img
                    .into_raw()
                    .into_iter()
                    .map(|v| v as f32 / 256.0)
                    .collect(),
            }),
            other => Err(Error::format(
                path,
                format!(
                    "a depth PNG must be 16-bit greyscale (metres x 256, the KITTI convention), this one is {:?}",
                    other.color()
                ),
            )),
        },
        "npy" => {
            let arrays = crate::peer_samples::read_sample_arrays(path)?;
            let a = arrays
                .into_iter()
                .next()
                .ok_or_else(|| Error::format(path, "no array"))?;
            // leading axes of size 1 go, down to the two of [H, W] (a 1 x 1 map keeps both)
            let extra = a.shape.len().saturating_sub(2);
            let lead = a.shape.iter().take(extra).take_while(|&&d| d == 1).count();
            let dims = &a.shape[lead..];
            let (h, w) = match dims {
                [h, w] if *h > 0 && *w > 0 => (*h, *w),
                _ => {
                    return Err(Error::format(
                        path,
                        format!(
                            "a depth map must have shape [H, W] (leading axes of size 1 allowed) \
                             with H, W > 0; this one has {:?}",
                            a.shape
                        ),
                    ));
                }
            };
            let (height, width) = (
                u32::try_from(h).map_err(|_| Error::format(path, "height out of range"))?,
                u32::try_from(w).map_err(|_| Error::format(path, "width out of range"))?,
            );
            Ok(ImageMap {
                width,
                height,
                data: a.data,
            })
        }
        _ => Err(Error::format(
            path,
            "a depth map is a 16-bit PNG (metres x 256) or a .npy float array",
        )),
    }
}

/// Read a class-id map aligned with a camera image: an 8- or 16-bit greyscale PNG whose values are
/// class ids (a colour PNG is refused: colours are not ids).
pub fn read_label_map(path: &Path) -> Result<ImageMap<u32>> {
    if lower_ext(path) != "png" {
        return Err(Error::format(
            path,
            "a class map is an 8- or 16-bit greyscale PNG of class ids",
        ));
    }
    match decode_png(path)? {
        image::DynamicImage::ImageLuma8(img) => Ok(ImageMap {
            width: img.width(),
            height: img.height(),
            data: img.into_raw().into_iter().map(u32::from).collect(),
        }),
        image::DynamicImage::ImageLuma16(img) => Ok(ImageMap {
            width: img.width(),
            height: img.height(),
            data: img.into_raw().into_iter().map(u32::from).collect(),
        }),
        other => Err(Error::format(
            path,
            format!(
                "a class map must be an 8- or 16-bit greyscale PNG of class ids, this one is {:?}",
                other.color()
            ),
        )),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A float32 `.npy` of `vals` (the hand-written numpy layout of the `peer_samples` tests).
    fn npy_f32(shape: &str, vals: &[f32]) -> Vec<u8> {
        let payload: Vec<u8> = vals.iter().flat_map(|v| v.to_le_bytes()).collect();
        crate::peer_samples::tests::npy_bytes("<f4", shape, &payload)
    }

    #[test]
    fn depth_and_label_maps_from_png_and_npy() {
        let dir = tempfile::tempdir().unwrap();
        // 16-bit depth PNG: value / 256 metres, 0 stays 0
        let raw: Vec<u16> = vec![0, 256, 2560, 65535, 384, 1];
        let img: image::ImageBuffer<image::Luma<u16>, Vec<u16>> =
            image::ImageBuffer::from_raw(3, 2, raw.clone()).unwrap();
        let p = dir.path().join("d.png");
        img.save(&p).unwrap();
        let m = read_depth_map(&p).unwrap();
        assert_eq!((m.width, m.height), (3, 2));
        let want: Vec<f32> = raw.iter().map(|&v| v as f32 / 256.0).collect();
        assert_eq!(m.data, want);
        assert_eq!(m.data[1], 1.0);
        // the same PNG read as a class map gives the raw ids
        let l = read_label_map(&p).unwrap();
        assert_eq!(l.data, raw.iter().map(|&v| v as u32).collect::<Vec<_>>());
        // 8-bit: a class map yes, a depth map no (and the error names the file)
        let p8 = dir.path().join("l8.png");
        image::GrayImage::from_raw(2, 1, vec![9, 40])
            .unwrap()
            .save(&p8)
            .unwrap();
        assert_eq!(read_label_map(&p8).unwrap().data, vec![9, 40]);
        let e = read_depth_map(&p8).unwrap_err().to_string();
        assert!(e.contains("l8.png") && e.contains("16-bit"), "{e}");
        // colour PNGs are neither
        let prgb = dir.path().join("c.png");
        RgbImage::new(2, 2).save(&prgb).unwrap();
        assert!(
            read_label_map(&prgb)
                .unwrap_err()
                .to_string()
                .contains("c.png")
        );
        assert!(read_depth_map(&prgb).is_err());
        // .npy float map, [1, H, W]
        let pn = dir.path().join("d.npy");
        let vals = [1.5f32, 2.0, 0.0, 7.25, 3.0, 4.0];
        std::fs::write(&pn, npy_f32("(1, 2, 3)", &vals)).unwrap();
        let m = read_depth_map(&pn).unwrap();
        assert_eq!((m.width, m.height), (3, 2));
        assert_eq!(m.data, vals.to_vec());
        // a 1-D array or another extension is refused, naming the file
        let p1 = dir.path().join("flat.npy");
        std::fs::write(&p1, npy_f32("(4,)", &[1.0, 2.0, 3.0, 4.0])).unwrap();
        assert!(
            read_depth_map(&p1)
                .unwrap_err()
                .to_string()
                .contains("flat.npy")
        );
        assert!(read_depth_map(&dir.path().join("x.exr")).is_err());
    }

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
