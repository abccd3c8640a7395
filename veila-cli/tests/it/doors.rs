//! One image-to-scan pipeline behind every door: `veila generate` writes, byte for byte, the scan
//! that the library's `ScanPipeline` gives (which `examples/generate.rs` and the Python `generate`
//! call; python/tests checks the wheel against this binary) on the real KITTI and nuScenes samples
//! of `../shared/data/real` (skipped when absent). No door can call the pipeline's steps itself:
//! they are private to `veila_diffusion`.

use std::path::{Path, PathBuf};

use crate::common::{generate, model_dir, ok};
use candle_core::Device;
use veila_data::range_exr::read_range_exr;
use veila_data::scan::write_kitti_bin;
use veila_diffusion::app::{Bundle, GenerateOptions, ScanPipeline, load_view};

fn workspace_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("..")
}

/// The first file in `dir` (the real samples have one per folder).
fn first_file(dir: &Path) -> PathBuf {
    let mut files: Vec<PathBuf> = std::fs::read_dir(dir)
        .unwrap_or_else(|e| panic!("{}: {e}", dir.display()))
        .map(|e| e.unwrap().path())
        .collect();
    files.sort();
    files.remove(0)
}

/// `(name, image, calibration, quarter turns into the model frame)` of the real samples: KITTI
/// object 000001 (x forward) and nuScenes CAM_FRONT (y forward).
fn real_rigs() -> Option<Vec<(&'static str, PathBuf, PathBuf, i32)>> {
    let real = workspace_root().join("../shared/data/real");
    if !real.is_dir() {
        eprintln!("skipping: {} not found", real.display());
        return None;
    }
    let kitti = real.join("kitti/training");
    let nus = real.join("nuscenes");
    Some(vec![
        (
            "kitti-000001",
            kitti.join("image_2/000001.png"),
            kitti.join("calib/000001.txt"),
            0,
        ),
        (
            "nuscenes-cam-front",
            first_file(&nus.join("samples/CAM_FRONT")),
            first_file(&nus.join("calib")),
            1,
        ),
    ])
}

/// The CLI with its defaults (the bundle's sampler, seed 0, one scan) and the library with
/// `GenerateOptions::new` (the example's call) write identical `.bin` bytes and range images.
#[test]
fn the_cli_and_the_library_give_the_same_scan_bytes() {
    let Some(rigs) = real_rigs() else { return };
    let tmp = tempfile::tempdir().unwrap();
    let bundle = Bundle::from_dir(&model_dir(), &Device::Cpu).unwrap();
    for (name, image, calib, turns) in rigs {
        let out = tmp.path().join(name);
        ok(&generate(&image, &calib, &out, &[]));
        let json: serde_json::Value =
            serde_json::from_slice(&std::fs::read(out.join("generate.json")).unwrap()).unwrap();
        assert_eq!(json["model_frame_quarter_turns"], turns, "{name}");

        let view = load_view(&image, &calib, None).unwrap();
        let pipeline = ScanPipeline::from_views(&bundle, &[view]).unwrap();
        assert_eq!(pipeline.quarter_turns(), turns, "{name}");
        let scan = pipeline
            .generate(
                &GenerateOptions::new(bundle.config.sampler.clone()),
                |_, _| {},
            )
            .unwrap()
            .remove(0);
        assert!(scan.points.len() > 1000, "{name}: {}", scan.points.len());
        let lib_bin = tmp.path().join(format!("{name}-library.bin"));
        write_kitti_bin(&lib_bin, &scan.points).unwrap();
        let cli = std::fs::read(out.join("scan_000.bin")).unwrap();
        assert!(
            cli == std::fs::read(&lib_bin).unwrap(),
            "{name}: the CLI's scan_000.bin ({} bytes) differs from the library's scan",
            cli.len()
        );
        let exr = read_range_exr(&out.join("scan_000.exr")).unwrap().image;
        assert_eq!(exr.range_m, scan.range.range_m, "{name}");
        assert_eq!(exr.mask, scan.range.mask, "{name}");
    }
}
