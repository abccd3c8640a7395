//! Point clouds as PLY (Stanford polygon format).
//!
//! Writing always produces `binary_little_endian 1.0` with one `vertex` element holding
//! `float x, y, z, intensity`, then `ushort ring` when the cloud has rings and `uint label` when it
//! has labels. Reading accepts `binary_little_endian`, `binary_big_endian` and `ascii`, any scalar
//! property types, extra properties (skipped) and fixed-size elements before `vertex`. Recognised
//! property names: `x y z` (required), intensity as `intensity`, `reflectance`, `remission` or
//! `scalar_intensity`, ring as `ring`, label as `label` or `scalar_label`.

use std::io::Write;
use std::path::Path;

use glam::Vec3;

use crate::atomic::write_atomic_with;
use crate::{Error, PointCloud, Result};

/// The PLY magic line every file starts with.
pub const PLY_MAGIC: &[u8] = b"ply";

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Encoding {
    Ascii,
    BinaryLe,
    BinaryBe,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Scalar {
    I8,
    U8,
    I16,
    U16,
    I32,
    U32,
    F32,
    F64,
}

impl Scalar {
    fn parse(name: &str) -> Option<Scalar> {
        Some(match name {
            "char" | "int8" => Scalar::I8,
            "uchar" | "uint8" => Scalar::U8,
            "short" | "int16" => Scalar::I16,
            "ushort" | "uint16" => Scalar::U16,
            "int" | "int32" => Scalar::I32,
            "uint" | "uint32" => Scalar::U32,
            "float" | "float32" => Scalar::F32,
            "double" | "float64" => Scalar::F64,
            _ => return None,
        })
    }
    fn size(self) -> usize {
        match self {
            Scalar::I8 | Scalar::U8 => 1,
            Scalar::I16 | Scalar::U16 => 2,
            Scalar::I32 | Scalar::U32 | Scalar::F32 => 4,
            Scalar::F64 => 8,
        }
    }
    /// Decode one binary value as f64 (exact for every PLY scalar type).
    fn decode(self, b: &[u8], le: bool) -> f64 {
        macro_rules! num {
            ($t:ty, $n:expr) => {{
                let mut a = [0u8; $n];
                a.copy_from_slice(&b[..$n]);
                (if le {
                    <$t>::from_le_bytes(a)
                } else {
                    <$t>::from_be_bytes(a)
                }) as f64
            }};
        }
        match self {
            Scalar::I8 => b[0] as i8 as f64,
            Scalar::U8 => b[0] as f64,
            Scalar::I16 => num!(i16, 2),
            Scalar::U16 => num!(u16, 2),
            Scalar::I32 => num!(i32, 4),
            Scalar::U32 => num!(u32, 4),
            Scalar::F32 => num!(f32, 4),
            Scalar::F64 => num!(f64, 8),
        }
    }
}

#[derive(Debug, Clone)]
struct Property {
    name: String,
    scalar: Scalar,
}

#[derive(Debug, Clone)]
struct Element {
    name: String,
    count: usize,
    properties: Vec<Property>,
    has_list: bool,
}

#[derive(Debug)]
struct Header {
    encoding: Encoding,
    elements: Vec<Element>,
    body_offset: usize,
}

fn parse_header(bytes: &[u8], path: &Path) -> Result<Header> {
    let fmt = |m: String| Error::format(path, m);
    if !(bytes.starts_with(b"ply\n") || bytes.starts_with(b"ply\r\n")) {
        return Err(fmt("not a PLY file (missing `ply` magic line)".into()));
    }
    let end = find(bytes, b"end_header")
        .ok_or_else(|| fmt("PLY header has no `end_header` line (truncated file?)".into()))?;
    let mut body_offset = end + b"end_header".len();
    if bytes.get(body_offset) == Some(&b'\r') {
        body_offset += 1;
    }
    if bytes.get(body_offset) != Some(&b'\n') {
        return Err(fmt("PLY `end_header` is not followed by a newline".into()));
    }
    body_offset += 1;
    let header = std::str::from_utf8(&bytes[..end])
        .map_err(|_| fmt("PLY header is not valid text".into()))?;
    let mut encoding = None;
    let mut elements: Vec<Element> = Vec::new();
    for (i, line) in header.lines().enumerate().skip(1) {
        let words: Vec<&str> = line.split_whitespace().collect();
        let Some(&kw) = words.first() else { continue };
        let line_no = i + 1;
        match kw {
            "comment" | "obj_info" => {}
            "format" => {
                encoding = Some(match words.get(1).copied() {
                    Some("ascii") => Encoding::Ascii,
                    Some("binary_little_endian") => Encoding::BinaryLe,
                    Some("binary_big_endian") => Encoding::BinaryBe,
                    other => {
                        return Err(fmt(format!(
                            "header line {line_no}: unknown PLY format {other:?}"
                        )));
                    }
                });
            }
            "element" => {
                let (Some(name), Some(count)) = (words.get(1), words.get(2)) else {
                    return Err(fmt(format!(
                        "header line {line_no}: malformed element line"
                    )));
                };
                let count: usize = count.parse().map_err(|_| {
                    fmt(format!(
                        "header line {line_no}: element count `{count}` is not a number"
                    ))
                })?;
                elements.push(Element {
                    name: name.to_string(),
                    count,
                    properties: Vec::new(),
                    has_list: false,
                });
            }
            "property" => {
                let Some(el) = elements.last_mut() else {
                    return Err(fmt(format!(
                        "header line {line_no}: property before any element"
                    )));
                };
                if words.get(1) == Some(&"list") {
                    el.has_list = true;
                    continue;
                }
                let (Some(ty), Some(name)) = (words.get(1), words.get(2)) else {
                    return Err(fmt(format!(
                        "header line {line_no}: malformed property line"
                    )));
                };
                let scalar = Scalar::parse(ty).ok_or_else(|| {
                    fmt(format!(
                        "header line {line_no}: unknown property type `{ty}`"
                    ))
                })?;
                el.properties.push(Property {
                    name: name.to_string(),
                    scalar,
                });
            }
            other => {
                return Err(fmt(format!(
                    "header line {line_no}: unknown keyword `{other}`"
                )));
            }
        }
    }
    let encoding = encoding.ok_or_else(|| fmt("PLY header has no `format` line".into()))?;
    Ok(Header {
        encoding,
        elements,
        body_offset,
    })
}

fn find(hay: &[u8], needle: &[u8]) -> Option<usize> {
    hay.windows(needle.len()).position(|w| w == needle)
}

/// Parse PLY bytes (the content of `path`, named in errors). Non-finite points are kept here; the
/// caller decides (see [`crate::scan::read_points`]).
pub fn parse_ply(bytes: &[u8], path: &Path) -> Result<PointCloud> {
    let header = parse_header(bytes, path)?;
    let fmt = |m: String| Error::format(path, m);
    let vi = header
        .elements
        .iter()
        .position(|e| e.name == "vertex")
        .ok_or_else(|| fmt("PLY file has no `vertex` element".into()))?;
    let vertex = &header.elements[vi];
    if vertex.has_list {
        return Err(fmt(
            "the PLY `vertex` element has a list property (unsupported)".into(),
        ));
    }
    let find_prop = |names: &[&str]| {
        vertex
            .properties
            .iter()
            .position(|p| names.contains(&p.name.as_str()))
    };
    let px = find_prop(&["x"]).ok_or_else(|| fmt("PLY vertex has no `x` property".into()))?;
    let py = find_prop(&["y"]).ok_or_else(|| fmt("PLY vertex has no `y` property".into()))?;
    let pz = find_prop(&["z"]).ok_or_else(|| fmt("PLY vertex has no `z` property".into()))?;
    let pi = find_prop(&["intensity", "reflectance", "remission", "scalar_intensity"]);
    let pr = find_prop(&["ring"]);
    let pl = find_prop(&["label", "scalar_label"]);
    let n = vertex.count;
    // reserve no more vertices than the body can hold (a header's count is a claim): each takes
    // at least its stride in binary, a character and a separator per property in ASCII
    let props = vertex.properties.len().max(1);
    let min_vertex_bytes = match header.encoding {
        Encoding::Ascii => 2 * props,
        Encoding::BinaryLe | Encoding::BinaryBe => vertex
            .properties
            .iter()
            .map(|p| p.scalar.size())
            .sum::<usize>()
            .max(1),
    };
    let body_len = bytes.len().saturating_sub(header.body_offset);
    let reserve = n.min(body_len / min_vertex_bytes).min(1 << 24);

    let mut cloud = PointCloud {
        xyz: Vec::with_capacity(reserve),
        intensity: Vec::with_capacity(reserve),
        ring: pr.map(|_| Vec::with_capacity(reserve)),
        label: pl.map(|_| Vec::with_capacity(reserve)),
    };
    let mut row = vec![0f64; vertex.properties.len()];
    let push = |row: &[f64], cloud: &mut PointCloud, idx: usize| -> Result<()> {
        cloud
            .xyz
            .push(Vec3::new(row[px] as f32, row[py] as f32, row[pz] as f32));
        cloud.intensity.push(pi.map_or(0.0, |i| row[i] as f32));
        if let (Some(r), Some(rings)) = (pr, cloud.ring.as_mut()) {
            let v = row[r];
            if !(0.0..=f64::from(u16::MAX)).contains(&v) || v.fract() != 0.0 {
                return Err(fmt(format!(
                    "vertex {idx}: ring {v} is not an integer in 0..=65535"
                )));
            }
            rings.push(v as u16);
        }
        if let (Some(l), Some(labels)) = (pl, cloud.label.as_mut()) {
            let v = row[l];
            if !(0.0..=f64::from(u32::MAX)).contains(&v) || v.fract() != 0.0 {
                return Err(fmt(format!(
                    "vertex {idx}: label {v} is not an integer in 0..=2^32-1"
                )));
            }
            labels.push(v as u32);
        }
        Ok(())
    };

    match header.encoding {
        Encoding::Ascii => {
            let body = std::str::from_utf8(&bytes[header.body_offset..])
                .map_err(|_| fmt("ASCII PLY body is not valid text".into()))?;
            let mut lines = body.lines().filter(|l| !l.trim().is_empty());
            // skip elements before the vertex element (one line per item)
            for el in &header.elements[..vi] {
                for k in 0..el.count {
                    lines.next().ok_or_else(|| {
                        fmt(format!(
                            "truncated ASCII PLY: element `{}` item {k} missing",
                            el.name
                        ))
                    })?;
                }
            }
            for idx in 0..n {
                let line = lines.next().ok_or_else(|| {
                    fmt(format!(
                        "truncated ASCII PLY: header declares {n} vertices, found {idx}"
                    ))
                })?;
                let mut words = line.split_whitespace();
                for (j, slot) in row.iter_mut().enumerate() {
                    let w = words.next().ok_or_else(|| {
                        fmt(format!(
                            "vertex {idx}: expected {} values, found {j}",
                            vertex.properties.len()
                        ))
                    })?;
                    *slot = w
                        .parse::<f64>()
                        .map_err(|_| fmt(format!("vertex {idx}: `{w}` is not a number")))?;
                }
                push(&row, &mut cloud, idx)?;
            }
        }
        Encoding::BinaryLe | Encoding::BinaryBe => {
            let le = header.encoding == Encoding::BinaryLe;
            let mut offset = header.body_offset;
            for el in &header.elements[..vi] {
                if el.has_list {
                    return Err(fmt(format!(
                        "element `{}` before `vertex` has a list property (unsupported)",
                        el.name
                    )));
                }
                let size: usize = el.properties.iter().map(|p| p.scalar.size()).sum();
                offset = size
                    .checked_mul(el.count)
                    .and_then(|s| s.checked_add(offset))
                    .ok_or_else(|| fmt("element sizes overflow".into()))?;
            }
            let stride: usize = vertex.properties.iter().map(|p| p.scalar.size()).sum();
            let needed = stride
                .checked_mul(n)
                .and_then(|s| s.checked_add(offset))
                .ok_or_else(|| fmt("vertex data size overflows".into()))?;
            if bytes.len() < needed {
                return Err(fmt(format!(
                    "truncated binary PLY: header declares {n} vertices of {stride} bytes ({} bytes of data), file has {}",
                    needed - header.body_offset,
                    bytes.len().saturating_sub(header.body_offset)
                )));
            }
            let offsets: Vec<usize> = vertex
                .properties
                .iter()
                .scan(0usize, |acc, p| {
                    let o = *acc;
                    *acc += p.scalar.size();
                    Some(o)
                })
                .collect();
            for (idx, rec) in bytes[offset..needed]
                .chunks_exact(stride.max(1))
                .enumerate()
                .take(n)
            {
                for (j, p) in vertex.properties.iter().enumerate() {
                    row[j] = p.scalar.decode(&rec[offsets[j]..], le);
                }
                push(&row, &mut cloud, idx)?;
            }
        }
    }
    Ok(cloud)
}

/// Read a PLY file into a point cloud (non-finite points kept; see [`crate::scan::read_points`]).
pub fn read_ply(path: &Path) -> Result<PointCloud> {
    let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
    parse_ply(&bytes, path)
}

/// Encode a point cloud as binary little-endian PLY (see the module docs for the layout).
pub fn encode_ply(cloud: &PointCloud, w: &mut impl Write) -> std::io::Result<()> {
    encode_ply_rgb(cloud, None, w)
}

/// [`encode_ply`] with a colour per point: `uchar red, green, blue` after the other properties,
/// the names Open3D, CloudCompare and MeshLab read as vertex colours (`rgb.len()` must be
/// `cloud.len()`).
pub fn encode_ply_rgb(
    cloud: &PointCloud,
    rgb: Option<&[[u8; 3]]>,
    w: &mut impl Write,
) -> std::io::Result<()> {
    if rgb.is_some_and(|c| c.len() != cloud.len()) {
        return Err(std::io::Error::new(
            std::io::ErrorKind::InvalidInput,
            "one colour per point",
        ));
    }
    write!(
        w,
        "ply\nformat binary_little_endian 1.0\ncomment written by veila-data (LiDAR frame, metres)\nelement vertex {}\nproperty float x\nproperty float y\nproperty float z\nproperty float intensity\n",
        cloud.len()
    )?;
    if cloud.ring.is_some() {
        writeln!(w, "property ushort ring")?;
    }
    if cloud.label.is_some() {
        writeln!(w, "property uint label")?;
    }
    if rgb.is_some() {
        writeln!(
            w,
            "property uchar red\nproperty uchar green\nproperty uchar blue"
        )?;
    }
    writeln!(w, "end_header")?;
    for i in 0..cloud.len() {
        let p = cloud.xyz[i];
        w.write_all(&p.x.to_le_bytes())?;
        w.write_all(&p.y.to_le_bytes())?;
        w.write_all(&p.z.to_le_bytes())?;
        w.write_all(&cloud.intensity[i].to_le_bytes())?;
        if let Some(r) = &cloud.ring {
            w.write_all(&r[i].to_le_bytes())?;
        }
        if let Some(l) = &cloud.label {
            w.write_all(&l[i].to_le_bytes())?;
        }
        if let Some(c) = rgb {
            w.write_all(&c[i])?;
        }
    }
    Ok(())
}

/// Write a point cloud as binary little-endian PLY, atomically (temp file + rename).
pub fn write_ply(path: &Path, cloud: &PointCloud) -> Result<()> {
    cloud.validate()?;
    write_atomic_with(path, |w| encode_ply(cloud, w))
}

/// Write a point cloud with a colour per point ([`encode_ply_rgb`]), atomically.
pub fn write_ply_rgb(path: &Path, cloud: &PointCloud, rgb: &[[u8; 3]]) -> Result<()> {
    cloud.validate()?;
    if rgb.len() != cloud.len() {
        return Err(Error::Invalid {
            what: format!("colours of {}", path.display()),
            message: format!("{} colours for {} points", rgb.len(), cloud.len()),
        });
    }
    write_atomic_with(path, |w| encode_ply_rgb(cloud, Some(rgb), w))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cloud() -> PointCloud {
        PointCloud {
            xyz: vec![Vec3::new(1.5, -2.25, 0.125), Vec3::new(-7.0, 3.0e-7, 12.0)],
            intensity: vec![0.5, 0.99],
            ring: Some(vec![3, 31]),
            label: Some(vec![40, (7 << 16) | 10]),
        }
    }

    #[test]
    fn colours_follow_the_other_properties_and_readers_skip_them() {
        let c = cloud();
        let rgb = [[255u8, 0, 7], [1, 128, 254]];
        let mut buf = Vec::new();
        encode_ply_rgb(&c, Some(&rgb), &mut buf).unwrap();
        let text = String::from_utf8_lossy(&buf);
        let header_end = text.find("end_header\n").unwrap() + "end_header\n".len();
        assert!(text[..header_end].contains(
            "property uint label\nproperty uchar red\nproperty uchar green\nproperty uchar blue\nend_header"
        ));
        // x y z intensity (4 x f32), ring (u16), label (u32), red green blue (3 x u8)
        let stride = 16 + 2 + 4 + 3;
        assert_eq!(buf.len(), header_end + 2 * stride);
        assert_eq!(&buf[header_end + stride - 3..header_end + stride], &rgb[0]);
        assert_eq!(&buf[header_end + 2 * stride - 3..], &rgb[1]);
        let back = parse_ply(&buf, Path::new("mem.ply")).unwrap();
        assert_eq!(back.xyz, c.xyz);
        assert_eq!(back.intensity, c.intensity);
        assert_eq!(back.label, c.label);
        assert!(encode_ply_rgb(&c, Some(&rgb[..1]), &mut Vec::new()).is_err());
    }

    #[test]
    fn binary_round_trip_is_exact() {
        let c = cloud();
        let mut buf = Vec::new();
        encode_ply(&c, &mut buf).unwrap();
        let back = parse_ply(&buf, Path::new("mem.ply")).unwrap();
        assert_eq!(back, c);
    }

    #[test]
    fn ascii_and_big_endian_with_extra_properties() {
        let ascii = b"ply\nformat ascii 1.0\nelement vertex 2\nproperty double x\nproperty double y\nproperty double z\nproperty uchar red\nproperty float reflectance\nend_header\n1 2 3 255 0.5\n-1 -2 -3 0 0.25\n";
        let c = parse_ply(ascii, Path::new("a.ply")).unwrap();
        assert_eq!(
            c.xyz,
            vec![Vec3::new(1.0, 2.0, 3.0), Vec3::new(-1.0, -2.0, -3.0)]
        );
        assert_eq!(c.intensity, vec![0.5, 0.25]);
        assert!(c.ring.is_none() && c.label.is_none());

        let mut be = b"ply\nformat binary_big_endian 1.0\nelement vertex 1\nproperty float x\nproperty float y\nproperty float z\nproperty int label\nend_header\n".to_vec();
        for v in [1.0f32, 2.0, 3.0] {
            be.extend_from_slice(&v.to_be_bytes());
        }
        be.extend_from_slice(&9i32.to_be_bytes());
        let c = parse_ply(&be, Path::new("b.ply")).unwrap();
        assert_eq!(c.xyz, vec![Vec3::new(1.0, 2.0, 3.0)]);
        assert_eq!(c.label, Some(vec![9]));
    }

    #[test]
    fn truncated_and_malformed_files_are_named() {
        let c = cloud();
        let mut buf = Vec::new();
        encode_ply(&c, &mut buf).unwrap();
        let e = parse_ply(&buf[..buf.len() - 3], Path::new("cut.ply"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("cut.ply") && e.contains("truncated"), "{e}");
        let e = parse_ply(
            b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float y\nend_header\n1\n",
            Path::new("nox.ply"),
        )
        .unwrap_err()
        .to_string();
        assert!(e.contains("nox.ply") && e.contains("`x`"), "{e}");
        let e = parse_ply(b"plx\n", Path::new("m.ply"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("magic"), "{e}");
        let e = parse_ply(b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nproperty float z\nproperty float label\nend_header\n1 2 3 -4\n", Path::new("l.ply"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("label"), "{e}");
    }
}
