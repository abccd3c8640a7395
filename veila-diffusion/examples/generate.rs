//! One camera image and its calibration in, one 360° scan out (KITTI `.bin`, in the calibration's
//! LiDAR frame), with the bundled model; the same scan `veila generate` writes for the same image,
//! calibration and seed:
//! `cargo run --release -p veila-diffusion --example generate -- IMAGE CALIB OUT.bin [MODEL_DIR]`
use std::path::PathBuf;

use candle_core::Device;
use veila_diffusion::app::{Bundle, GenerateOptions, ScanPipeline, load_view};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<PathBuf> = std::env::args_os().skip(1).map(PathBuf::from).collect();
    let [image, calib, out, model @ ..] = args.as_slice() else {
        return Err("usage: generate IMAGE CALIB OUT.bin [MODEL_DIR]".into());
    };
    let default_model = PathBuf::from(concat!(env!("CARGO_MANIFEST_DIR"), "/../models/default"));
    let bundle = Bundle::from_dir(model.first().unwrap_or(&default_model), &Device::Cpu)?;
    let view = load_view(image, calib, None)?; // KITTI camera 2 or nuScenes CAM_FRONT
    // resized to the model's input, turned into its frame and the scans back into the LiDAR's
    let pipeline = ScanPipeline::from_views(&bundle, &[view])?;
    let options = GenerateOptions::new(bundle.config.sampler.clone()); // one scan, seed 0
    let scan = pipeline.generate(&options, |_, _| {})?.remove(0);
    veila_data::scan::write_kitti_bin(out, &scan.points)?;
    println!("{}: {} points", out.display(), scan.points.len());
    Ok(())
}
