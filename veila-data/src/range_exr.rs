//! Range images as self-describing OpenEXR files.
//!
//! One layer, `rows x cols` pixels (width = azimuth columns, height = beams, row 0 = top beam), ZIP
//! compressed (lossless), channels:
//!
//! | channel       | type | content                                                        |
//! |---------------|------|----------------------------------------------------------------|
//! | `range_m`     | f32  | range in metres, 0 where empty                                 |
//! | `intensity`   | f32  | intensity in the source's scale, 0 where empty                 |
//! | `mask`        | f32  | 1 where the pixel holds a return, else 0                       |
//! | `label`       | u32  | optional: per-pixel label (SemanticKITTI raw label)            |
//! | `point_index` | u32  | optional: index of the source point, `u32::MAX` where empty     |
//!
//! Labels are stored as u32 rather than f32 because a raw SemanticKITTI label (instance in the high 16
//! bits) does not survive a trip through f32. The sensor ([`LidarSensor`]) is stored as JSON in the
//! string attribute `veila_sensor`, and the layer is named [`FORMAT_TAG`] (a `veila_format` attribute with
//! the tag is accepted too); reading checks both, so a file is never unprojected with the wrong
//! geometry. Round trips are bit-exact, and encoding is deterministic: the same image gives the same
//! bytes (tested).

use std::io::Cursor;
use std::path::Path;

use exr::prelude::*;
use veila_geom::{LidarSensor, NO_POINT, RangeImage, RayTable};

use crate::atomic::write_atomic_with;
use crate::{Error, PointCloud, Result};

/// The OpenEXR magic number as the first four bytes of a file (what [`crate::scan`] detects EXR by).
pub const EXR_MAGIC: [u8; 4] = [0x76, 0x2f, 0x31, 0x01];
/// The value of the `veila_format` attribute.
pub const FORMAT_TAG: &str = "veila-range-image/1";
const ATTR_SENSOR: &str = "veila_sensor";
const ATTR_FORMAT: &str = "veila_format";

/// A range image read from (or to be written to) an EXR file, with its sensor.
#[derive(Debug, Clone, PartialEq)]
pub struct RangeExr {
    /// The sensor the image was projected with.
    pub sensor: LidarSensor,
    /// The image; `label` and `point_index` are filled when the file has those channels
    /// (`point_index` is all [`NO_POINT`] otherwise).
    pub image: RangeImage,
}

impl RangeExr {
    /// Unproject to points (pixel centres along the sensor's rays at the stored range), carrying
    /// intensity, labels and, for per-beam sensors, the ring of each row.
    pub fn to_points(&self) -> Result<PointCloud> {
        let rays = RayTable::new(&self.sensor)?;
        let u = rays.unproject(&self.image)?;
        let label = self.image.label.as_ref().map(|l| {
            u.pixels
                .iter()
                .map(|(r, c)| l[self.image.idx(*r, *c)])
                .collect::<Vec<u32>>()
        });
        // per-beam sensors know which ring feeds each row: keep it, so the points re-project exactly
        let ring = matches!(self.sensor.beams, veila_geom::BeamLayout::PerBeam { .. }).then(|| {
            u.pixels
                .iter()
                .map(|(r, _)| self.sensor.ring_of_row(*r).min(u32::from(u16::MAX)) as u16)
                .collect()
        });
        Ok(PointCloud {
            xyz: u.points,
            intensity: u.intensity,
            ring,
            label,
        })
    }
}

/// Encode a range image as EXR bytes. The image must match the sensor's size and have one entry
/// per pixel in every buffer.
pub fn encode_range_exr(sensor: &LidarSensor, image: &RangeImage) -> Result<Vec<u8>> {
    sensor.validate()?;
    image.validate()?;
    if image.rows != sensor.rows || image.cols != sensor.cols {
        return Err(Error::Mismatch {
            context: "range image and sensor".into(),
            message: format!(
                "image is {}x{} but the sensor is {}x{}",
                image.rows, image.cols, sensor.rows, sensor.cols
            ),
        });
    }
    let json = serde_json::to_string(sensor).map_err(|e| Error::Invalid {
        what: "sensor".into(),
        message: e.to_string(),
    })?;
    let sensor_text = Text::new_or_none(&json).ok_or_else(|| Error::Invalid {
        what: "sensor".into(),
        message: "description is not representable as an EXR string".into(),
    })?;
    let size = (image.cols as usize, image.rows as usize);
    let mask: Vec<f32> = image
        .mask
        .iter()
        .map(|m| if *m { 1.0 } else { 0.0 })
        .collect();
    let mut channels = vec![
        AnyChannel::new("range_m", FlatSamples::F32(image.range_m.clone())),
        AnyChannel::new("intensity", FlatSamples::F32(image.intensity.clone())),
        AnyChannel::new("mask", FlatSamples::F32(mask)),
    ];
    if let Some(l) = &image.label {
        channels.push(AnyChannel::new("label", FlatSamples::U32(l.clone())));
    }
    if image.point_index.iter().any(|p| *p != NO_POINT) {
        channels.push(AnyChannel::new(
            "point_index",
            FlatSamples::U32(image.point_index.clone()),
        ));
    }
    // The format tag is the layer's name and the sensor the only custom attribute: exr keeps custom
    // attributes in a hash map and writes them in its random iteration order, so two custom attributes
    // would make the bytes of identical images differ from run to run.
    let mut attrs = LayerAttributes::named(FORMAT_TAG);
    attrs
        .other
        .insert(Text::from(ATTR_SENSOR), AttributeValue::Text(sensor_text));
    let layer = Layer::new(
        size,
        attrs,
        Encoding::SMALL_LOSSLESS,
        AnyChannels::sort(channels.into_iter().collect()),
    );
    let img = Image::from_layer(layer);
    let mut buf = Cursor::new(Vec::new());
    img.write()
        .to_buffered(&mut buf)
        .map_err(|e| Error::Invalid {
            what: "range image".into(),
            message: format!("EXR encoding failed: {e}"),
        })?;
    Ok(buf.into_inner())
}

/// Write a range image and its sensor as EXR, atomically (temp file + rename).
pub fn write_range_exr(path: &Path, sensor: &LidarSensor, image: &RangeImage) -> Result<()> {
    let bytes = encode_range_exr(sensor, image)?;
    write_atomic_with(path, |w| std::io::Write::write_all(w, &bytes))
}

/// The sensor of range-image EXR bytes, from the header alone (no pixel is decoded): the magic
/// number, the format tag (layer name or `veila_format`), the stored sensor, and the data window
/// of every layer, which must be the sensor's `cols x rows` (width x height).
fn read_header(bytes: &[u8], path: &Path) -> Result<LidarSensor> {
    let fmt = |m: String| Error::format(path, m);
    if !bytes.starts_with(&EXR_MAGIC) {
        return Err(fmt("not an OpenEXR file (bad magic number)".into()));
    }
    let meta = exr::meta::MetaData::read_from_buffered(Cursor::new(bytes), false)
        .map_err(|e| fmt(format!("cannot read EXR header: {e}")))?;
    let header = meta
        .headers
        .first()
        .ok_or_else(|| fmt("EXR has no layer".into()))?;
    let text_attr = |name: &str| -> Option<String> {
        let key = Text::from(name);
        match header
            .own_attributes
            .other
            .get(&key)
            .or_else(|| header.shared_attributes.other.get(&key))
        {
            Some(AttributeValue::Text(t)) => Some(t.to_string()),
            _ => None,
        }
    };
    let layer_name = header
        .own_attributes
        .layer_name
        .as_ref()
        .map(|t| t.to_string());
    check_format_tag(text_attr(ATTR_FORMAT), layer_name, path)?;
    let sensor_json = text_attr(ATTR_SENSOR).ok_or_else(|| {
        fmt(format!(
            "EXR has no `{ATTR_SENSOR}` attribute (the sensor description)"
        ))
    })?;
    let sensor: LidarSensor = serde_json::from_str(&sensor_json).map_err(|e| {
        fmt(format!(
            "`{ATTR_SENSOR}` attribute is not a valid sensor: {e}"
        ))
    })?;
    sensor
        .validate()
        .map_err(|e| fmt(format!("stored sensor is invalid: {e}")))?;
    for (i, h) in meta.headers.iter().enumerate() {
        let (w, hh) = (h.layer_size.width(), h.layer_size.height());
        if w != sensor.cols as usize || hh != sensor.rows as usize {
            let which = if i == 0 {
                String::new()
            } else {
                format!("layer {i}: ")
            };
            return Err(fmt(format!(
                "{which}image is {w}x{hh} (width x height) but its sensor is {} cols x {} rows",
                sensor.cols, sensor.rows
            )));
        }
    }
    Ok(sensor)
}

/// The format tag, from the `veila_format` attribute or else a `veila-range-image/*` layer name,
/// must be [`FORMAT_TAG`].
fn check_format_tag(attr: Option<String>, layer_name: Option<String>, path: &Path) -> Result<()> {
    let format_tag = attr.or_else(|| layer_name.filter(|n| n.starts_with("veila-range-image/")));
    match format_tag {
        Some(tag) if tag == FORMAT_TAG => Ok(()),
        Some(tag) => Err(Error::format(
            path,
            format!("unsupported range-image version `{tag}` (expected `{FORMAT_TAG}`)"),
        )),
        None => Err(Error::format(
            path,
            format!(
                "EXR has neither a `{ATTR_FORMAT}` attribute nor a layer named `{FORMAT_TAG}`: not a Veila range image"
            ),
        )),
    }
}

/// Decode EXR bytes written by [`encode_range_exr`] (`path` names the source in errors).
///
/// The header is read and checked first: a file whose data window differs from
/// its sensor's `rows x cols` (say one claiming 2^20 x 1024 pixels in a few bytes) is refused
/// before any pixel storage is allocated.
pub fn decode_range_exr(bytes: &[u8], path: &Path) -> Result<RangeExr> {
    let fmt = |m: String| Error::format(path, m);
    let sensor = read_header(bytes, path)?;
    let img = read()
        .no_deep_data()
        .largest_resolution_level()
        .all_channels()
        .first_valid_layer()
        .all_attributes()
        .from_buffered(Cursor::new(bytes))
        .map_err(|e| fmt(format!("cannot read EXR: {e}")))?;
    let layer = &img.layer_data;
    let find = |name: &str| layer.channel_data.list.iter().find(|c| c.name.eq(name));
    let f32_channel = |name: &str| -> Result<Vec<f32>> {
        match find(name).map(|c| &c.sample_data) {
            Some(FlatSamples::F32(v)) => Ok(v.clone()),
            Some(_) => Err(fmt(format!("channel `{name}` must be f32"))),
            None => Err(fmt(format!("missing channel `{name}`"))),
        }
    };
    let u32_channel = |name: &str| -> Result<Option<Vec<u32>>> {
        match find(name).map(|c| &c.sample_data) {
            Some(FlatSamples::U32(v)) => Ok(Some(v.clone())),
            Some(_) => Err(fmt(format!("channel `{name}` must be u32"))),
            None => Ok(None),
        }
    };
    let range_m = f32_channel("range_m")?;
    let intensity = f32_channel("intensity")?;
    let mask_f = f32_channel("mask")?;
    let label = u32_channel("label")?;
    let point_index = u32_channel("point_index")?;
    let mut mask = Vec::with_capacity(mask_f.len());
    for (k, m) in mask_f.iter().enumerate() {
        mask.push(match *m {
            1.0 => true,
            0.0 => false,
            v => return Err(fmt(format!("mask pixel {k} is {v}, expected 0 or 1"))),
        });
    }
    for (k, (&r, &m)) in range_m.iter().zip(&mask).enumerate() {
        if m && !(r.is_finite() && r > 0.0) {
            return Err(fmt(format!(
                "valid pixel {k} has range {r}, expected a finite positive value"
            )));
        }
    }
    let n = sensor.num_pixels();
    let image = RangeImage {
        rows: sensor.rows,
        cols: sensor.cols,
        range_m,
        intensity,
        point_index: point_index.unwrap_or_else(|| vec![NO_POINT; n]),
        mask,
        label,
    };
    image
        .validate()
        .map_err(|e| fmt(format!("inconsistent channels: {e}")))?;
    Ok(RangeExr { sensor, image })
}

/// Read a range-image EXR (see the module docs); every inconsistency is an error naming the file.
pub fn read_range_exr(path: &Path) -> Result<RangeExr> {
    let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
    decode_range_exr(&bytes, path)
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    fn random_image(sensor: &LidarSensor, seed: u64, labels: bool) -> RangeImage {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let mut img = RangeImage::new_empty(sensor.rows, sensor.cols);
        for k in 0..img.num_pixels() {
            if rng.random_bool(0.7) {
                img.mask[k] = true;
                img.range_m[k] = rng.random_range(0.5f32..120.0);
                img.intensity[k] = rng.random::<f32>();
                img.point_index[k] = k as u32 * 3;
            }
        }
        if labels {
            img.label = Some((0..img.num_pixels()).map(|_| rng.random::<u32>()).collect());
        }
        img
    }

    #[test]
    fn encoding_is_deterministic() {
        // every encode builds a fresh attribute hash map with fresh random keys: with two custom
        // attributes their order (and so the bytes) would differ about every other time
        let sensor = LidarSensor {
            rows: 8,
            cols: 32,
            ..LidarSensor::hdl64e()
        };
        let img = random_image(&sensor, 3, true);
        let first = encode_range_exr(&sensor, &img).unwrap();
        for _ in 0..24 {
            assert_eq!(encode_range_exr(&sensor, &img).unwrap(), first);
        }
    }

    #[test]
    fn round_trip_is_bit_exact() {
        let sensor = LidarSensor {
            rows: 8,
            cols: 32,
            ..LidarSensor::hdl64e()
        };
        for labels in [false, true] {
            let img = random_image(&sensor, 7, labels);
            let bytes = encode_range_exr(&sensor, &img).unwrap();
            let back = decode_range_exr(&bytes, Path::new("m.exr")).unwrap();
            assert_eq!(back.sensor, sensor);
            assert_eq!(back.image.label, img.label);
            assert_eq!(back.image.mask, img.mask);
            assert_eq!(back.image.point_index, img.point_index);
            let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
            assert_eq!(bits(&back.image.range_m), bits(&img.range_m));
            assert_eq!(bits(&back.image.intensity), bits(&img.intensity));
        }
    }

    #[test]
    fn per_beam_points_keep_rings_and_reproject_to_their_pixels() {
        let sensor = LidarSensor::hdl32e_per_beam();
        let mut img = random_image(&sensor, 11, false);
        img.point_index.iter_mut().for_each(|p| *p = NO_POINT);
        let exr = RangeExr {
            sensor: sensor.clone(),
            image: img.clone(),
        };
        let pts = exr.to_points().unwrap();
        let rings = pts.ring.as_ref().unwrap();
        let proj =
            veila_geom::Projector::new(&sensor, veila_geom::ProjectionOptions::default()).unwrap();
        let (back, _) = proj
            .project(&pts.xyz, Some(&pts.intensity), Some(rings))
            .unwrap();
        // ranges outside the sensor's interval are rejected on the way back; all else returns home
        let expected: Vec<bool> = img
            .mask
            .iter()
            .zip(&img.range_m)
            .map(|(m, r)| *m && *r >= sensor.min_range_m && *r <= sensor.max_range_m)
            .collect();
        assert_eq!(back.mask, expected);
        for k in 0..back.num_pixels() {
            if back.mask[k] {
                assert!(
                    (back.range_m[k] - img.range_m[k]).abs() <= 1e-4 * img.range_m[k],
                    "pixel {k}"
                );
            }
        }
    }

    #[test]
    fn missing_channel_and_wrong_size_are_rejected() {
        let sensor = LidarSensor {
            rows: 4,
            cols: 16,
            ..LidarSensor::hdl64e()
        };
        // an EXR with the right attributes but no `mask` channel
        let json = serde_json::to_string(&sensor).unwrap();
        let build = |w: usize, h: usize, with_mask: bool| {
            let mut ch = vec![
                AnyChannel::new("range_m", FlatSamples::F32(vec![1.0; w * h])),
                AnyChannel::new("intensity", FlatSamples::F32(vec![0.0; w * h])),
            ];
            if with_mask {
                ch.push(AnyChannel::new("mask", FlatSamples::F32(vec![1.0; w * h])));
            }
            let mut attrs = LayerAttributes::named("veila_range");
            attrs.other.insert(
                Text::from(ATTR_SENSOR),
                AttributeValue::Text(Text::from(json.as_str())),
            );
            attrs.other.insert(
                Text::from(ATTR_FORMAT),
                AttributeValue::Text(Text::from(FORMAT_TAG)),
            );
            let layer = Layer::new(
                (w, h),
                attrs,
                Encoding::UNCOMPRESSED,
                AnyChannels::sort(ch.into_iter().collect()),
            );
            let mut buf = Cursor::new(Vec::new());
            Image::from_layer(layer)
                .write()
                .to_buffered(&mut buf)
                .unwrap();
            buf.into_inner()
        };
        let e = decode_range_exr(&build(16, 4, false), Path::new("nomask.exr"))
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("nomask.exr") && e.contains("missing channel `mask`"),
            "{e}"
        );
        let e = decode_range_exr(&build(16, 5, true), Path::new("size.exr"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("size.exr") && e.contains("16x5"), "{e}");
        assert!(decode_range_exr(&build(16, 4, true), Path::new("ok.exr")).is_ok());
        let good = build(16, 4, true);
        let e = decode_range_exr(&good[..good.len() - 10], Path::new("cut.exr"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("cut.exr"), "{e}");
    }

    /// `bytes` with the data window of its (first) header replaced by `width x height`.
    fn with_data_window(bytes: &[u8], width: i32, height: i32) -> Vec<u8> {
        let key = b"dataWindow\0box2i\0";
        let at = bytes
            .windows(key.len())
            .position(|w| w == key)
            .expect("a dataWindow attribute")
            + key.len()
            + 4; // the attribute's size
        let mut out = bytes.to_vec();
        // x_min, y_min stay 0; x_max, y_max
        out[at + 8..at + 12].copy_from_slice(&(width - 1).to_le_bytes());
        out[at + 12..at + 16].copy_from_slice(&(height - 1).to_le_bytes());
        out
    }

    const HUGE_WINDOW_TEST: &str =
        "range_exr::tests::a_header_claiming_a_huge_window_is_refused_before_decoding";

    #[test]
    fn a_header_claiming_a_huge_window_is_refused_before_decoding() {
        let sensor = LidarSensor {
            rows: 4,
            cols: 16,
            ..LidarSensor::hdl64e()
        };
        let good = encode_range_exr(&sensor, &random_image(&sensor, 5, true)).unwrap();
        assert!(decode_range_exr(&with_data_window(&good, 16, 4), Path::new("same.exr")).is_ok());
        // 1024 x 2^20 pixels: four 4 GiB channels if the pixels were allocated before the check
        let huge = with_data_window(&good, 1024, 1 << 20);
        let e = decode_range_exr(&huge, Path::new("huge.exr"))
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("huge.exr") && e.contains("1024x1048576") && e.contains("16 cols x 4 rows"),
            "{e}"
        );
        let e = decode_range_exr(&with_data_window(&good, 16, 5), Path::new("one_more.exr"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("one_more.exr") && e.contains("16x5"), "{e}");
        // and no allocation of that size happens: the same decode in a child process whose
        // address space is limited to 1 GiB (an allocation of the claimed pixels aborts it)
        #[cfg(target_os = "linux")]
        if std::env::var_os("VEILA_EXR_HUGE_WINDOW_CHILD").is_none() {
            let exe = std::env::current_exe().unwrap();
            let status = std::process::Command::new("sh")
                .arg("-c")
                .arg("ulimit -v 1048576 && exec \"$0\" --exact \"$1\" --test-threads=1 --quiet")
                .arg(exe)
                .arg(HUGE_WINDOW_TEST)
                .env("VEILA_EXR_HUGE_WINDOW_CHILD", "1")
                .stdout(std::process::Stdio::null())
                .status()
                .unwrap();
            assert!(
                status.success(),
                "the decode in a 1 GiB address space failed: {status}"
            );
        }
    }
}
