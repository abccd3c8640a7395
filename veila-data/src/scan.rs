//! Point files: KITTI `.bin`, nuScenes `.pcd.bin`, PLY and range `.exr`, with format detection.
//!
//! # Detection rules ([`detect_point_format`])
//!
//! 1. Content first: a file starting with the line `ply` is PLY; a file starting with the OpenEXR
//!    magic number `0x762f3101` (bytes `76 2f 31 01`) is a range-image EXR, unprojected with the sensor
//!    stored in its header.
//! 2. Raw float records have no magic, so the name decides: `*.pcd.bin` is nuScenes (5 little-endian
//!    f32 per point: x, y, z, intensity 0..255, ring), any other `*.bin` is KITTI (4 f32 per point:
//!    x, y, z, reflectance 0..1). The length must be a whole number of records; when it is not, the
//!    error says so and mentions the other record size when the length would fit it.
//! 3. A text PCD file (`# .PCD` / `VERSION` header) and anything else are rejected with an error
//!    naming the file.
//!
//! Every reader drops points with a non-finite coordinate or intensity and reports how many
//! ([`LoadedPoints::dropped_non_finite`]); they never reach a projection. Geometry consumers (the
//! metrics) read with [`read_points_with`]`(path, `[`Keep::FiniteXyz`]`)`, which keeps a point whose
//! intensity alone is NaN, as the peers' metric scripts do. A file where no point is kept is an
//! error of [`read_points`] and [`read_points_with`].
//!
//! # Bounded memory
//!
//! Raw float records are read in chunks of at most [`READ_CHUNK_BYTES`] straight into the cloud,
//! and a file longer than [`MAX_SCAN_POINTS`] records is rejected from its length before anything
//! is allocated (a 2 GiB garbage `.bin` costs nothing).

use std::io::Read;
use std::path::Path;

use glam::Vec3;
use veila_geom::LidarSensor;

use crate::atomic::write_atomic_with;
use crate::{Error, PointCloud, Result};

/// Bytes per KITTI velodyne record (x, y, z, reflectance as f32).
pub const KITTI_RECORD_BYTES: usize = 16;
/// Bytes per nuScenes LIDAR_TOP record (x, y, z, intensity, ring as f32).
pub const NUSCENES_RECORD_BYTES: usize = 20;
/// The most points a raw point file may hold: 16 Mi, 50x a 128-beam scan (a KITTI file of this many
/// points is 256 MiB). Longer files are rejected before they are read.
pub const MAX_SCAN_POINTS: usize = 1 << 24;
/// Raw point files are read in chunks of this many bytes (a whole number of both record sizes).
pub const READ_CHUNK_BYTES: usize = 80 * 16 * 1024;

/// The on-disk format of a point file.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PointFormat {
    /// KITTI velodyne `.bin`: f32 x, y, z, reflectance.
    KittiBin,
    /// nuScenes `.pcd.bin`: f32 x, y, z, intensity, ring.
    NuScenesPcdBin,
    /// PLY (binary or ASCII).
    Ply,
    /// A Veila range-image OpenEXR file (see [`crate::range_exr`]).
    RangeExr,
}

impl std::fmt::Display for PointFormat {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            PointFormat::KittiBin => "KITTI .bin",
            PointFormat::NuScenesPcdBin => "nuScenes .pcd.bin",
            PointFormat::Ply => "PLY",
            PointFormat::RangeExr => "range-image EXR",
        })
    }
}

/// A point cloud read from a file, with what the reader learned on the way.
#[derive(Debug, Clone, PartialEq)]
pub struct LoadedPoints {
    /// The finite points, attributes aligned.
    pub cloud: PointCloud,
    /// The detected format.
    pub format: PointFormat,
    /// How many records had a NaN or infinite coordinate or intensity and were dropped.
    pub dropped_non_finite: usize,
    /// The sensor, when the file describes it (range-image EXR).
    pub sensor: Option<LidarSensor>,
}

fn name_of(path: &Path) -> String {
    path.file_name()
        .map(|n| n.to_string_lossy().to_lowercase())
        .unwrap_or_default()
}

/// Decide the format of `path` from its first bytes and, for raw float records, its name (rules in
/// the module docs). Reads at most 16 bytes.
pub fn detect_point_format(path: &Path) -> Result<PointFormat> {
    let mut head = [0u8; 16];
    let mut f = std::fs::File::open(path).map_err(|e| Error::io(path, e))?;
    let mut n = 0;
    while n < head.len() {
        match f.read(&mut head[n..]) {
            Ok(0) => break,
            Ok(k) => n += k,
            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
            Err(e) => return Err(Error::io(path, e)),
        }
    }
    detect_from(&head[..n], path)
}

fn detect_from(head: &[u8], path: &Path) -> Result<PointFormat> {
    if head.starts_with(b"ply\n") || head.starts_with(b"ply\r\n") {
        return Ok(PointFormat::Ply);
    }
    if head.starts_with(&crate::range_exr::EXR_MAGIC) {
        return Ok(PointFormat::RangeExr);
    }
    let name = name_of(path);
    if name.ends_with(".pcd.bin") {
        return Ok(PointFormat::NuScenesPcdBin);
    }
    if name.ends_with(".bin") {
        return Ok(PointFormat::KittiBin);
    }
    if head.starts_with(b"# .PCD") || head.starts_with(b"VERSION") {
        return Err(Error::format(
            path,
            "PCD text files are not supported (convert to .ply or a .bin of f32 records)",
        ));
    }
    Err(Error::format(
        path,
        "unknown point file format: not PLY or EXR by content, and the name ends neither in `.bin` (KITTI) nor `.pcd.bin` (nuScenes)",
    ))
}

/// Which points a reader keeps.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Keep {
    /// Points whose coordinates and intensity are all finite (what projections need).
    #[default]
    FiniteRecords,
    /// Points whose coordinates are finite, whatever their intensity (what geometry metrics need).
    FiniteXyz,
}

impl Keep {
    fn apply(self, cloud: &mut PointCloud) -> usize {
        match self {
            Keep::FiniteRecords => cloud.retain_finite(),
            Keep::FiniteXyz => cloud.retain_finite_xyz(),
        }
    }
}

/// Read any supported point file (format detected; see the module docs). Non-finite points are dropped
/// and counted.
pub fn read_points(path: &Path) -> Result<LoadedPoints> {
    read_points_with(path, Keep::FiniteRecords)
}

/// [`read_points`] with a choice of which points to keep ([`Keep`]).
pub fn read_points_with(path: &Path, keep: Keep) -> Result<LoadedPoints> {
    let loaded = read_points_any(path, keep)?;
    if loaded.cloud.is_empty() && loaded.dropped_non_finite > 0 {
        let what = match keep {
            Keep::FiniteRecords => "NaN or infinite coordinates or intensity",
            Keep::FiniteXyz => "NaN or infinite coordinates",
        };
        return Err(Error::format(
            path,
            format!(
                "all {} points are non-finite ({what})",
                loaded.dropped_non_finite
            ),
        ));
    }
    Ok(loaded)
}

fn read_points_any(path: &Path, keep: Keep) -> Result<LoadedPoints> {
    match detect_point_format(path)? {
        PointFormat::KittiBin => read_kitti_bin_with(path, keep),
        PointFormat::NuScenesPcdBin => read_nuscenes_pcd_bin_with(path, keep),
        PointFormat::Ply => {
            let mut cloud = crate::ply::read_ply(path)?;
            let dropped = keep.apply(&mut cloud);
            Ok(LoadedPoints {
                cloud,
                format: PointFormat::Ply,
                dropped_non_finite: dropped,
                sensor: None,
            })
        }
        PointFormat::RangeExr => {
            let exr = crate::range_exr::read_range_exr(path)?;
            let cloud = exr.to_points()?;
            Ok(LoadedPoints {
                cloud,
                format: PointFormat::RangeExr,
                dropped_non_finite: 0,
                sensor: Some(exr.sensor),
            })
        }
    }
}

/// Read a raw file of `record`-byte records in bounded chunks, after checking its length (a whole
/// number of records, at most [`MAX_SCAN_POINTS`]). `each(chunk, first, n)` sees every chunk of
/// whole records, the index of its first record and the file's record count. Returns the count.
fn read_records(
    path: &Path,
    record: usize,
    mut each: impl FnMut(&[u8], usize, usize) -> Result<()>,
) -> Result<usize> {
    let mut f = std::fs::File::open(path).map_err(|e| Error::io(path, e))?;
    let len = f.metadata().map_err(|e| Error::io(path, e))?.len();
    let len = usize::try_from(len).unwrap_or(usize::MAX);
    check_records(len, record, path)?;
    let n = len / record;
    if n > MAX_SCAN_POINTS {
        return Err(Error::format(
            path,
            format!(
                "{len} bytes is {n} points, more than the {MAX_SCAN_POINTS} a scan may hold \
                 (not a single LiDAR scan?)"
            ),
        ));
    }
    let chunk_records = READ_CHUNK_BYTES / record;
    let mut buf = vec![0u8; chunk_records.min(n).max(1) * record];
    let mut done = 0;
    while done < n {
        let k = chunk_records.min(n - done);
        let b = &mut buf[..k * record];
        f.read_exact(b).map_err(|e| {
            if e.kind() == std::io::ErrorKind::UnexpectedEof {
                Error::format(path, "the file became shorter while it was read")
            } else {
                Error::io(path, e)
            }
        })?;
        each(b, done, n)?;
        done += k;
    }
    Ok(n)
}

fn check_records(len: usize, record: usize, path: &Path) -> Result<()> {
    if len.is_multiple_of(record) {
        return Ok(());
    }
    let other = if record == KITTI_RECORD_BYTES {
        NUSCENES_RECORD_BYTES
    } else {
        KITTI_RECORD_BYTES
    };
    let hint = if len.is_multiple_of(other) {
        if other == NUSCENES_RECORD_BYTES {
            " (it is a multiple of 20: a nuScenes scan should be named *.pcd.bin)"
        } else {
            " (it is a multiple of 16: a KITTI scan should be named *.bin, not *.pcd.bin)"
        }
    } else {
        " (truncated or not a point file)"
    };
    Err(Error::format(
        path,
        format!(
            "length {} bytes is not a multiple of the {record}-byte record ({} f32 per point){hint}",
            len,
            record / 4
        ),
    ))
}

#[inline]
fn f32_at(b: &[u8], i: usize) -> f32 {
    f32::from_le_bytes([b[4 * i], b[4 * i + 1], b[4 * i + 2], b[4 * i + 3]])
}

/// Decode KITTI records without dropping anything (callers attach labels first, then drop).
pub(crate) fn decode_kitti_records(bytes: &[u8], path: &Path) -> Result<PointCloud> {
    check_records(bytes.len(), KITTI_RECORD_BYTES, path)?;
    let mut cloud = kitti_cloud(bytes.len() / KITTI_RECORD_BYTES);
    push_kitti(&mut cloud, bytes);
    Ok(cloud)
}

fn kitti_cloud(n: usize) -> PointCloud {
    PointCloud {
        xyz: Vec::with_capacity(n),
        intensity: Vec::with_capacity(n),
        ring: None,
        label: None,
    }
}

fn push_kitti(cloud: &mut PointCloud, bytes: &[u8]) {
    for rec in bytes.chunks_exact(KITTI_RECORD_BYTES) {
        cloud
            .xyz
            .push(Vec3::new(f32_at(rec, 0), f32_at(rec, 1), f32_at(rec, 2)));
        cloud.intensity.push(f32_at(rec, 3));
    }
}

/// Read the KITTI records of `path` without dropping anything, in bounded chunks.
pub(crate) fn read_kitti_records(path: &Path) -> Result<PointCloud> {
    let mut cloud = kitti_cloud(0);
    read_records(path, KITTI_RECORD_BYTES, |chunk, done, n| {
        if done == 0 {
            cloud.xyz.reserve_exact(n);
            cloud.intensity.reserve_exact(n);
        }
        push_kitti(&mut cloud, chunk);
        Ok(())
    })?;
    Ok(cloud)
}

/// Every KITTI record of `path` in file order, non-finite ones included: the points a
/// SemanticKITTI `.label` file (one label per record) is aligned with. Read in bounded chunks, the
/// length checked against the cap before anything is read.
pub fn read_kitti_bin_records(path: &Path) -> Result<PointCloud> {
    read_kitti_records(path)
}

/// Decode KITTI velodyne bytes (x, y, z, reflectance f32 records). `path` names the source in errors.
pub fn parse_kitti_bin(bytes: &[u8], path: &Path) -> Result<LoadedPoints> {
    let mut cloud = decode_kitti_records(bytes, path)?;
    let dropped = cloud.retain_finite();
    Ok(LoadedPoints {
        cloud,
        format: PointFormat::KittiBin,
        dropped_non_finite: dropped,
        sensor: None,
    })
}

/// Read a KITTI velodyne `.bin` (also SemanticKITTI / KITTI odometry scans).
pub fn read_kitti_bin(path: &Path) -> Result<LoadedPoints> {
    read_kitti_bin_with(path, Keep::FiniteRecords)
}

fn read_kitti_bin_with(path: &Path, keep: Keep) -> Result<LoadedPoints> {
    let mut cloud = read_kitti_records(path)?;
    let dropped = keep.apply(&mut cloud);
    Ok(LoadedPoints {
        cloud,
        format: PointFormat::KittiBin,
        dropped_non_finite: dropped,
        sensor: None,
    })
}

/// Decode nuScenes LIDAR_TOP bytes (x, y, z, intensity, ring f32 records). A ring that is not an
/// integer in 0..=65535 is a format error.
pub fn parse_nuscenes_pcd_bin(bytes: &[u8], path: &Path) -> Result<LoadedPoints> {
    check_records(bytes.len(), NUSCENES_RECORD_BYTES, path)?;
    let mut acc = NuScenesAcc::new(bytes.len() / NUSCENES_RECORD_BYTES);
    acc.push(bytes, 0, path)?;
    Ok(acc.finish(Keep::FiniteRecords))
}

/// nuScenes records decoded so far.
struct NuScenesAcc {
    cloud: PointCloud,
    rings: Vec<u16>,
    non_finite_ring: usize,
}

impl NuScenesAcc {
    fn new(n: usize) -> Self {
        NuScenesAcc {
            cloud: PointCloud {
                xyz: Vec::with_capacity(n),
                intensity: Vec::with_capacity(n),
                ring: None,
                label: None,
            },
            rings: Vec::with_capacity(n),
            non_finite_ring: 0,
        }
    }

    /// Decode the records of `bytes`, the first being record `first` of the file.
    fn push(&mut self, bytes: &[u8], first: usize, path: &Path) -> Result<()> {
        for (i, rec) in bytes.chunks_exact(NUSCENES_RECORD_BYTES).enumerate() {
            let ring = f32_at(rec, 4);
            if !ring.is_finite() {
                self.non_finite_ring += 1;
                self.cloud.xyz.push(Vec3::NAN);
                self.cloud.intensity.push(f32::NAN);
                self.rings.push(0);
                continue;
            }
            if !(0.0..=65535.0).contains(&ring) || ring.fract() != 0.0 {
                return Err(Error::format(
                    path,
                    format!(
                        "record {}: ring {ring} is not an integer in 0..=65535 (is this a nuScenes scan?)",
                        first + i
                    ),
                ));
            }
            self.cloud
                .xyz
                .push(Vec3::new(f32_at(rec, 0), f32_at(rec, 1), f32_at(rec, 2)));
            self.cloud.intensity.push(f32_at(rec, 3));
            self.rings.push(ring as u16);
        }
        Ok(())
    }

    fn finish(mut self, keep: Keep) -> LoadedPoints {
        self.cloud.ring = Some(self.rings);
        let dropped = keep.apply(&mut self.cloud);
        debug_assert!(dropped >= self.non_finite_ring);
        LoadedPoints {
            cloud: self.cloud,
            format: PointFormat::NuScenesPcdBin,
            dropped_non_finite: dropped,
            sensor: None,
        }
    }
}

/// Read a nuScenes `.pcd.bin` (5 f32 per point, ring kept in [`PointCloud::ring`]).
pub fn read_nuscenes_pcd_bin(path: &Path) -> Result<LoadedPoints> {
    read_nuscenes_pcd_bin_with(path, Keep::FiniteRecords)
}

fn read_nuscenes_pcd_bin_with(path: &Path, keep: Keep) -> Result<LoadedPoints> {
    let mut acc = NuScenesAcc::new(0);
    read_records(path, NUSCENES_RECORD_BYTES, |chunk, done, n| {
        if done == 0 {
            acc = NuScenesAcc::new(n);
        }
        acc.push(chunk, done, path)
    })?;
    Ok(acc.finish(keep))
}

/// Encode a cloud as KITTI `.bin` records (x, y, z, intensity). Rings and labels are not part of the
/// format (labels go to a separate `.label` file, see [`write_labels`](crate::semantic_kitti::write_labels)).
pub fn encode_kitti_bin(cloud: &PointCloud) -> Vec<u8> {
    let mut out = Vec::with_capacity(cloud.len() * KITTI_RECORD_BYTES);
    for (p, i) in cloud.xyz.iter().zip(&cloud.intensity) {
        for v in [p.x, p.y, p.z, *i] {
            out.extend_from_slice(&v.to_le_bytes());
        }
    }
    out
}

/// Write a cloud as a KITTI `.bin`, atomically.
pub fn write_kitti_bin(path: &Path, cloud: &PointCloud) -> Result<()> {
    cloud.validate()?;
    let bytes = encode_kitti_bin(cloud);
    write_atomic_with(path, |w| std::io::Write::write_all(w, &bytes))
}

/// Write a cloud in the format its name asks for: `*.ply` (binary PLY with intensity, ring and label)
/// or `*.bin` (KITTI records; rings and labels dropped). Any other name is an error.
pub fn write_points(path: &Path, cloud: &PointCloud) -> Result<()> {
    let name = name_of(path);
    if name.ends_with(".ply") {
        crate::ply::write_ply(path, cloud)
    } else if name.ends_with(".pcd.bin") {
        Err(Error::Invalid {
            what: "output file name".into(),
            message: format!(
                "{}: writing nuScenes .pcd.bin is not supported; use .ply or .bin",
                path.display()
            ),
        })
    } else if name.ends_with(".bin") {
        write_kitti_bin(path, cloud)
    } else {
        Err(Error::Invalid {
            what: "output file name".into(),
            message: format!("{}: expected a name ending in .ply or .bin", path.display()),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn rec(v: &[f32]) -> Vec<u8> {
        v.iter().flat_map(|x| x.to_le_bytes()).collect()
    }

    #[test]
    fn kitti_bin_drops_and_counts_non_finite() {
        let bytes = rec(&[
            1.0,
            2.0,
            3.0,
            0.5, //
            f32::NAN,
            0.0,
            0.0,
            0.1, //
            4.0,
            f32::INFINITY,
            0.0,
            0.2, //
            5.0,
            6.0,
            7.0,
            f32::NAN, //
            -1.0,
            -2.0,
            -3.0,
            0.9,
        ]);
        let l = parse_kitti_bin(&bytes, Path::new("x.bin")).unwrap();
        assert_eq!(l.dropped_non_finite, 3);
        assert_eq!(
            l.cloud.xyz,
            vec![Vec3::new(1.0, 2.0, 3.0), Vec3::new(-1.0, -2.0, -3.0)]
        );
        assert_eq!(l.cloud.intensity, vec![0.5, 0.9]);
    }

    #[test]
    fn finite_xyz_keeps_a_point_whose_intensity_alone_is_nan() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("a.bin");
        std::fs::write(
            &p,
            rec(&[
                1.0,
                2.0,
                3.0,
                f32::NAN,
                f32::NAN,
                0.0,
                0.0,
                0.1,
                4.0,
                5.0,
                6.0,
                0.2,
            ]),
        )
        .unwrap();
        let records = read_points(&p).unwrap();
        assert_eq!(records.cloud.xyz, vec![Vec3::new(4.0, 5.0, 6.0)]);
        let geometry = read_points_with(&p, Keep::FiniteXyz).unwrap();
        assert_eq!(
            geometry.cloud.xyz,
            vec![Vec3::new(1.0, 2.0, 3.0), Vec3::new(4.0, 5.0, 6.0)]
        );
        assert!(geometry.cloud.intensity[0].is_nan());
        assert_eq!(geometry.dropped_non_finite, 1);
    }

    #[test]
    fn record_size_errors_name_file_and_hint() {
        let e = parse_kitti_bin(&[0u8; 20], Path::new("scan.bin"))
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("scan.bin") && e.contains("16-byte") && e.contains("pcd.bin"),
            "{e}"
        );
        let e = parse_kitti_bin(&[0u8; 17], Path::new("scan.bin"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("truncated"), "{e}");
        let e = parse_nuscenes_pcd_bin(&[0u8; 32], Path::new("a.pcd.bin"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("20-byte") && e.contains("KITTI"), "{e}");
    }

    #[test]
    fn pcd_bin_keeps_rings_and_rejects_bad_rings() {
        let bytes = rec(&[
            1.0,
            2.0,
            3.0,
            100.0,
            7.0, //
            0.0,
            0.0,
            f32::NAN,
            9.0,
            1.0, //
            1.0,
            1.0,
            1.0,
            3.0,
            f32::NAN,
        ]);
        let l = parse_nuscenes_pcd_bin(&bytes, Path::new("a.pcd.bin")).unwrap();
        assert_eq!(l.dropped_non_finite, 2);
        assert_eq!(l.cloud.ring, Some(vec![7]));
        let bad = rec(&[1.0, 2.0, 3.0, 100.0, 7.5]);
        assert!(parse_nuscenes_pcd_bin(&bad, Path::new("a.pcd.bin")).is_err());
    }

    #[test]
    fn detection_by_magic_then_name() {
        let p = Path::new("weird_name.bin");
        assert_eq!(detect_from(b"ply\nformat", p).unwrap(), PointFormat::Ply);
        assert_eq!(
            detect_from(&[0x76, 0x2f, 0x31, 0x01, 2, 0, 0, 0], p).unwrap(),
            PointFormat::RangeExr
        );
        assert_eq!(
            detect_from(&[0; 8], Path::new("a.pcd.bin")).unwrap(),
            PointFormat::NuScenesPcdBin
        );
        assert_eq!(
            detect_from(&[0; 8], Path::new("A.BIN")).unwrap(),
            PointFormat::KittiBin
        );
        assert!(detect_from(b"# .PCD v0.7", Path::new("a.pcd")).is_err());
        let e = detect_from(&[0; 8], Path::new("a.xyz"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("a.xyz") && e.contains("unknown"), "{e}");
    }
}
