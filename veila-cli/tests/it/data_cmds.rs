//! `veila project / unproject / render` end to end through the built binary: good input, and every
//! kind of bad input gives a clear error naming the file, a non-zero exit and no partial output.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

use veila_data::image;

fn veila(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_veila"))
        .args(args)
        .output()
        .expect("run veila")
}

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

fn stderr(o: &Output) -> String {
    String::from_utf8_lossy(&o.stderr).to_string()
}

fn stdout(o: &Output) -> String {
    String::from_utf8_lossy(&o.stdout).to_string()
}

/// Fails with the command's output when it did not fail with a message containing every needle.
fn assert_fails(o: &Output, needles: &[&str]) {
    assert!(
        !o.status.success(),
        "expected failure, got success:\n{}",
        stdout(o)
    );
    let e = stderr(o);
    for n in needles {
        assert!(e.contains(n), "stderr lacks {n:?}:\n{e}");
    }
}

/// Files in `dir` (names), to check that nothing, not even a temporary, was left behind.
fn listing(dir: &Path) -> Vec<String> {
    let mut v: Vec<String> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().to_string())
        .collect();
    v.sort();
    v
}

/// A ring of points around the sensor (inside the HDL-64E field of view), KITTI records.
fn scan_records(n: usize) -> Vec<[f32; 4]> {
    (0..n)
        .map(|i| {
            let a = i as f32 * 0.37;
            let r = 5.0 + (i % 13) as f32;
            [
                r * a.cos(),
                r * a.sin(),
                -1.0 + (i % 5) as f32 * 0.1,
                (i % 10) as f32 / 10.0,
            ]
        })
        .collect()
}

fn write_bin(path: &Path, recs: &[[f32; 4]]) {
    let bytes: Vec<u8> = recs
        .iter()
        .flatten()
        .flat_map(|v| v.to_le_bytes())
        .collect();
    std::fs::write(path, bytes).unwrap();
}

const CALIB: &str = "P0: 100 0 50 0 0 100 20 0 0 0 1 0\nP1: 100 0 50 0 0 100 20 0 0 0 1 0\nP2: 100 0 50 0 0 100 20 0 0 0 1 0\nP3: 100 0 50 0 0 100 20 0 0 0 1 0\nR0_rect: 1 0 0 0 1 0 0 0 1\nTr_velo_to_cam: 0 -1 0 0 0 0 -1 0 1 0 0 0\n";

struct Fixture {
    dir: tempfile::TempDir,
}

impl Fixture {
    fn new() -> Self {
        let f = Fixture {
            dir: tempfile::tempdir().unwrap(),
        };
        write_bin(&f.p("scan.bin"), &scan_records(2000));
        std::fs::write(f.p("calib.txt"), CALIB).unwrap();
        let img = image::RgbImage::from_pixel(100, 40, image::Rgb([40, 40, 40]));
        img.save(f.p("img.png")).unwrap();
        f
    }
    fn p(&self, name: &str) -> PathBuf {
        self.dir.path().join(name)
    }
    fn out_dir(&self) -> PathBuf {
        let d = self.p("out");
        std::fs::create_dir_all(&d).unwrap();
        d
    }
}

#[test]
fn project_unproject_render_round_trip() {
    let f = Fixture::new();
    let out = f.out_dir();
    let o = veila(&[
        "project",
        s(&f.p("scan.bin")),
        "--sensor",
        "hdl64e",
        "--out",
        s(&out.join("a.exr")),
        "--png",
        s(&out.join("a.png")),
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(stdout(&o).contains("2000 points"), "{}", stdout(&o));
    let exr = veila_data::range_exr::read_range_exr(&out.join("a.exr")).unwrap();
    assert_eq!(exr.sensor, veila_geom::LidarSensor::hdl64e());
    let valid = exr.image.num_valid();
    assert!(valid > 100);
    let png = image::open(out.join("a.png")).unwrap();
    assert_eq!((png.width(), png.height()), (1024, 64 * 4));

    let o = veila(&[
        "unproject",
        s(&out.join("a.exr")),
        "--out",
        s(&out.join("b.ply")),
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let back = veila_data::scan::read_points(&out.join("b.ply")).unwrap();
    assert_eq!(back.cloud.len(), valid);
    let o = veila(&[
        "unproject",
        s(&out.join("a.exr")),
        "--out",
        s(&out.join("b.bin")),
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert_eq!(
        std::fs::metadata(out.join("b.bin")).unwrap().len() as usize,
        valid * 16
    );

    let o = veila(&[
        "render",
        s(&f.p("scan.bin")),
        "--bev",
        s(&out.join("bev.png")),
        "--range",
        s(&out.join("r.png")),
        "--image",
        s(&f.p("img.png")),
        "--calib",
        s(&f.p("calib.txt")),
        "--overlay",
        s(&out.join("ov.png")),
        "--bev-resolution-m",
        "0.5",
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    // brute force: points in front of the camera (x > 0.1 m) whose pixel lands in 100 x 40
    let brute = scan_records(2000)
        .iter()
        .filter(|p| {
            let (xc, yc, zc) = (-p[1], -p[2], p[0]);
            if zc <= 0.1 {
                return false;
            }
            let (u, v) = ((100.0 * xc + 50.0 * zc) / zc, (100.0 * yc + 20.0 * zc) / zc);
            (-0.5..99.5).contains(&u) && (-0.5..39.5).contains(&v)
        })
        .count();
    assert!(
        stdout(&o).contains(&format!("overlay: {brute} points")),
        "{} (brute force {brute})",
        stdout(&o)
    );
    let ov = image::open(out.join("ov.png")).unwrap().to_rgb8();
    assert!(ov.pixels().any(|p| p.0 != [40, 40, 40]));
    assert_eq!(image::open(out.join("bev.png")).unwrap().width(), 200);
    // the EXR renders too (format detected by magic, even under a misleading name)
    std::fs::copy(out.join("a.exr"), out.join("renamed.bin")).unwrap();
    let o = veila(&[
        "render",
        s(&out.join("renamed.bin")),
        "--range",
        s(&out.join("r2.png")),
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(stdout(&o).contains("range-image EXR"));
}

#[test]
fn bin_length_not_a_multiple_of_the_record() {
    let f = Fixture::new();
    let out = f.out_dir();
    let mut bytes = std::fs::read(f.p("scan.bin")).unwrap();
    bytes.truncate(bytes.len() - 6);
    std::fs::write(f.p("cut.bin"), bytes).unwrap();
    let o = veila(&[
        "project",
        s(&f.p("cut.bin")),
        "--out",
        s(&out.join("a.exr")),
        "--png",
        s(&out.join("a.png")),
    ]);
    assert_fails(&o, &["cut.bin", "not a multiple of the 16-byte record"]);
    assert!(listing(&out).is_empty(), "{:?}", listing(&out));
}

#[test]
fn non_finite_points_are_dropped_and_counted() {
    let f = Fixture::new();
    let out = f.out_dir();
    let mut recs = scan_records(500);
    recs[3][0] = f32::NAN;
    recs[10][2] = f32::INFINITY;
    recs[20][3] = f32::NEG_INFINITY;
    write_bin(&f.p("nan.bin"), &recs);
    let o = veila(&[
        "project",
        s(&f.p("nan.bin")),
        "--out",
        s(&out.join("a.exr")),
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(
        stdout(&o).contains("497 points") && stdout(&o).contains("3 non-finite dropped"),
        "{}",
        stdout(&o)
    );
    let exr = veila_data::range_exr::read_range_exr(&out.join("a.exr")).unwrap();
    assert!(
        exr.image
            .range_m
            .iter()
            .chain(&exr.image.intensity)
            .all(|v| v.is_finite())
    );
    // PLY output of such a scan holds finite values only
    let o = veila(&[
        "unproject",
        s(&out.join("a.exr")),
        "--out",
        s(&out.join("a.ply")),
    ]);
    assert!(o.status.success());
    let back = veila_data::scan::read_points(&out.join("a.ply")).unwrap();
    assert_eq!(back.dropped_non_finite, 0);
}

#[test]
fn calib_missing_key_or_malformed_number() {
    let f = Fixture::new();
    let out = f.out_dir();
    for (name, text, needles) in [
        (
            "nokey.txt",
            CALIB.replace("Tr_velo_to_cam", "Tr_velo_to_cax"),
            vec!["nokey.txt", "Tr_velo_to_cam", "missing"],
        ),
        (
            "badnum.txt",
            CALIB.replace("P2: 100 0 50", "P2: 100 0 5,0"),
            vec!["badnum.txt", "P2", "malformed number `5,0`"],
        ),
        (
            "nop2.txt",
            CALIB.replace("P2: 100 0 50 0 0 100 20 0 0 0 1 0\n", ""),
            vec!["nop2.txt", "P2", "missing"],
        ),
    ] {
        std::fs::write(f.p(name), text).unwrap();
        let o = veila(&[
            "render",
            s(&f.p("scan.bin")),
            "--bev",
            s(&out.join("bev.png")),
            "--image",
            s(&f.p("img.png")),
            "--calib",
            s(&f.p(name)),
            "--overlay",
            s(&out.join("ov.png")),
        ]);
        assert_fails(&o, &needles);
        assert!(
            listing(&out).is_empty(),
            "partial output: {:?}",
            listing(&out)
        );
    }
}

#[test]
fn more_or_fewer_labels_than_points() {
    let f = Fixture::new();
    let out = f.out_dir();
    for (n, word) in [(1999usize, "fewer"), (2001, "more")] {
        let bytes: Vec<u8> = (0..n as u32).flat_map(|v| (v % 30).to_le_bytes()).collect();
        std::fs::write(f.p("l.label"), bytes).unwrap();
        let o = veila(&[
            "project",
            s(&f.p("scan.bin")),
            "--labels",
            s(&f.p("l.label")),
            "--out",
            s(&out.join("a.exr")),
        ]);
        assert_fails(
            &o,
            &["l.label", &format!("{n} labels"), "2000 points", word],
        );
        assert!(listing(&out).is_empty());
    }
    // the right count works and the labels reach the EXR
    let bytes: Vec<u8> = (0..2000u32).flat_map(|v| (v % 30).to_le_bytes()).collect();
    std::fs::write(f.p("l.label"), bytes).unwrap();
    let o = veila(&[
        "project",
        s(&f.p("scan.bin")),
        "--labels",
        s(&f.p("l.label")),
        "--out",
        s(&out.join("a.exr")),
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let exr = veila_data::range_exr::read_range_exr(&out.join("a.exr")).unwrap();
    let l = exr.image.label.unwrap();
    for (k, &pi) in exr.image.point_index.iter().enumerate() {
        if pi != veila_geom::NO_POINT {
            assert_eq!(l[k], pi % 30);
        }
    }
}

#[test]
fn unreadable_or_truncated_image() {
    let f = Fixture::new();
    let out = f.out_dir();
    let bytes = std::fs::read(f.p("img.png")).unwrap();
    std::fs::write(f.p("cut.png"), &bytes[..bytes.len() / 2]).unwrap();
    std::fs::write(f.p("text.png"), b"hello").unwrap();
    for (name, needle) in [
        ("cut.png", "cut.png"),
        ("text.png", "text.png"),
        ("missing.png", "missing.png"),
    ] {
        let o = veila(&[
            "render",
            s(&f.p("scan.bin")),
            "--bev",
            s(&out.join("bev.png")),
            "--image",
            s(&f.p(name)),
            "--calib",
            s(&f.p("calib.txt")),
            "--overlay",
            s(&out.join("ov.png")),
        ]);
        assert_fails(&o, &[needle]);
        assert!(
            listing(&out).is_empty(),
            "partial output: {:?}",
            listing(&out)
        );
    }
}

fn patch(bytes: &mut [u8], from: &[u8], to: &[u8]) {
    assert_eq!(from.len(), to.len());
    let at = bytes
        .windows(from.len())
        .position(|w| w == from)
        .expect("pattern in EXR header");
    bytes[at..at + to.len()].copy_from_slice(to);
}

#[test]
fn exr_with_missing_channel_or_wrong_size() {
    let f = Fixture::new();
    let out = f.out_dir();
    let sensor = veila_geom::LidarSensor {
        rows: 4,
        cols: 16,
        ..veila_geom::LidarSensor::hdl64e()
    };
    let mut img = veila_geom::RangeImage::new_empty(4, 16);
    img.mask[5] = true;
    img.range_m[5] = 7.5;
    let good = veila_data::range_exr::encode_range_exr(&sensor, &img).unwrap();

    let mut no_mask = good.clone();
    patch(&mut no_mask, b"mask\0", b"masq\0");
    std::fs::write(f.p("nomask.exr"), no_mask).unwrap();
    let o = veila(&[
        "unproject",
        s(&f.p("nomask.exr")),
        "--out",
        s(&out.join("a.ply")),
    ]);
    assert_fails(&o, &["nomask.exr", "missing channel `mask`"]);

    let mut wrong = good.clone();
    patch(&mut wrong, b"\"rows\":4", b"\"rows\":5");
    std::fs::write(f.p("size.exr"), wrong).unwrap();
    let o = veila(&[
        "unproject",
        s(&f.p("size.exr")),
        "--out",
        s(&out.join("a.ply")),
    ]);
    assert_fails(&o, &["size.exr", "16x4", "5 rows"]);

    std::fs::write(f.p("cut.exr"), &good[..good.len() - 20]).unwrap();
    let o = veila(&[
        "render",
        s(&f.p("cut.exr")),
        "--range",
        s(&out.join("r.png")),
    ]);
    assert_fails(&o, &["cut.exr"]);
    assert!(
        listing(&out).is_empty(),
        "partial output: {:?}",
        listing(&out)
    );

    std::fs::write(f.p("good.exr"), &good).unwrap();
    let o = veila(&[
        "unproject",
        s(&f.p("good.exr")),
        "--out",
        s(&out.join("a.ply")),
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
}

#[test]
fn output_directory_that_cannot_be_written() {
    let f = Fixture::new();
    // a "directory" that is a file, and one that does not exist
    std::fs::write(f.p("afile"), b"x").unwrap();
    for bad in [f.p("afile").join("a.exr"), f.p("no/such/dir/a.exr")] {
        let o = veila(&[
            "project",
            s(&f.p("scan.bin")),
            "--out",
            s(&bad),
            "--png",
            s(&f.p("ok.png")),
        ]);
        assert_fails(&o, &[s(bad.parent().unwrap())]);
        assert!(
            !f.p("ok.png").exists(),
            "the preview was written although the EXR could not be"
        );
    }
    let before = listing(f.dir.path());
    let o = veila(&[
        "unproject",
        s(&f.p("missing.exr")),
        "--out",
        s(&f.p("x.ply")),
    ]);
    assert_fails(&o, &["missing.exr"]);
    assert_eq!(listing(f.dir.path()), before);
}

#[test]
fn real_kitti_overlay_counts() {
    let real = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/data/real/kitti/training");
    if !real.is_dir() {
        eprintln!("skipping: {} not found", real.display());
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let o = veila(&[
        "render",
        s(&real.join("velodyne/000000.bin")),
        "--image",
        s(&real.join("image_2/000000.png")),
        "--calib",
        s(&real.join("calib/000000.txt")),
        "--overlay",
        s(&dir.path().join("ov.png")),
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let out = stdout(&o);
    assert!(out.contains("115384 points"), "{out}");
    let n: usize = out
        .split("overlay: ")
        .nth(1)
        .unwrap()
        .split(' ')
        .next()
        .unwrap()
        .parse()
        .unwrap();
    assert!((19_000..=21_000).contains(&n), "{n}");
}
