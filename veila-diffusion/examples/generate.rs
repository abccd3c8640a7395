//! One camera image and its calibration in, one 360° scan out (KITTI `.bin`), with the bundled model:
//! `cargo run --release -p veila-diffusion --example generate -- IMAGE CALIB OUT.bin [MODEL_DIR]`
use std::path::PathBuf;

use candle_core::Device;
use veila_diffusion::app::{
    Bundle, GenerateOptions, camera_views, load_view, prepare_views, scan_points,
};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<PathBuf> = std::env::args_os().skip(1).map(PathBuf::from).collect();
    let [image, calib, out, model @ ..] = args.as_slice() else {
        return Err("usage: generate IMAGE CALIB OUT.bin [MODEL_DIR]".into());
    };
    let default_model = PathBuf::from(concat!(env!("CARGO_MANIFEST_DIR"), "/../models/default"));
    let bundle = Bundle::from_dir(model.first().unwrap_or(&default_model), &Device::Cpu)?;
    let view = load_view(image, calib, None)?; // KITTI camera 2 or nuScenes CAM_FRONT
    let prepared = prepare_views(&bundle.config, &[view])?; // resized to the model's input
    let options = GenerateOptions::new(bundle.config.sampler.clone()); // one scan, seed 0
    let scan = bundle
        .generate(&camera_views(&prepared), &options, |_, _| {})?
        .remove(0);
    let points = scan_points(&bundle.config, &scan)?;
    veila_data::scan::write_kitti_bin(out, &points)?;
    println!("{}: {} points", out.display(), points.len());
    Ok(())
}
