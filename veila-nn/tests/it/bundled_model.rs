//! The bundled denoiser (`models/default`) gives the same output with the CPU kernels of
//! `veila_nn::fused` as with candle's own composition: the reference values in
//! `tests/data/bundled_unconditional.json` were written by `regenerate_bundled_reference` with
//! `VEILA_NN_REFERENCE_OPS=1` (candle's ops, none of the fused kernels) for the residual bundle shipped
//! in session 22, 2026-11-26 (T junctions in the training scenes, `scenes/train-v5.txt`; 12,500 updates
//! of each network):
//!
//! ```text
//! VEILA_NN_REFERENCE_OPS=1 cargo test -p veila-nn --test it bundled_model:: -- --ignored
//! ```

use std::collections::HashMap;
use std::path::PathBuf;

use candle_core::{DType, Device, Tensor};
use candle_nn::VarBuilder;
use veila_nn::{Denoiser, DenoiserConfig};

fn workspace() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("..")
}

fn reference_path() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/data/bundled_unconditional.json")
}

/// Every `STRIDE`-th output value is kept in the reference file.
const STRIDE: usize = 61;

/// The bundled model's unconditional output on a fixed batch of two (`None` when the bundle is absent).
fn bundled_output() -> Option<Vec<f32>> {
    let dir = workspace().join("models/default");
    let bundle = std::fs::read_to_string(dir.join("bundle.json")).ok()?;
    let json: serde_json::Value = serde_json::from_str(&bundle).unwrap();
    let cfg: DenoiserConfig = serde_json::from_value(json["denoiser"].clone()).unwrap();
    let dev = Device::Cpu;
    let tensors: HashMap<String, Tensor> =
        candle_core::safetensors::load(dir.join("denoiser.safetensors"), &dev).unwrap();
    let net = Denoiser::new(&cfg, VarBuilder::from_tensors(tensors, DType::F32, &dev)).unwrap();
    let (c, h, w) = (cfg.in_channels, cfg.height(), cfg.width());
    let x: Vec<f32> = (0..2 * c * h * w)
        .map(|i| (0.37 * i as f32).sin() * 1.3 + (0.011 * i as f32).cos() * 0.4)
        .collect();
    let x = Tensor::from_vec(x, (2, c, h, w), &dev).unwrap();
    let t = Tensor::new(&[0.3f32, 0.8], &dev).unwrap();
    let y = net.forward(&x, &t, None).unwrap();
    Some(y.flatten_all().unwrap().to_vec1::<f32>().unwrap())
}

#[test]
#[ignore = "writes the reference file; run once with the reference implementation"]
fn regenerate_bundled_reference() {
    let y = bundled_output().expect("models/default is missing");
    let kept: Vec<f32> = y.iter().step_by(STRIDE).copied().collect();
    let sum: f64 = y.iter().map(|v| f64::from(*v)).sum();
    let sum_sq: f64 = y.iter().map(|v| f64::from(*v) * f64::from(*v)).sum();
    let json = serde_json::json!({ "len": y.len(), "stride": STRIDE, "sum": sum, "sum_sq": sum_sq, "values": kept });
    std::fs::write(reference_path(), serde_json::to_string(&json).unwrap()).unwrap();
}

#[test]
fn bundled_model_output_is_unchanged() {
    let Some(y) = bundled_output() else {
        eprintln!("skipping: models/default is absent");
        return;
    };
    let text = std::fs::read_to_string(reference_path()).unwrap();
    let r: serde_json::Value = serde_json::from_str(&text).unwrap();
    assert_eq!(r["len"].as_u64().unwrap() as usize, y.len());
    let want: Vec<f32> = r["values"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_f64().unwrap() as f32)
        .collect();
    let got: Vec<f32> = y.iter().step_by(STRIDE).copied().collect();
    assert_eq!(want.len(), got.len());
    let scale = want.iter().fold(0f32, |m, v| m.max(v.abs()));
    let worst = want
        .iter()
        .zip(&got)
        .fold(0f32, |m, (a, b)| m.max((a - b).abs()));
    assert!(
        worst <= 1e-4 * scale,
        "max abs difference {worst} (scale {scale})"
    );
    let sum_sq: f64 = y.iter().map(|v| f64::from(*v) * f64::from(*v)).sum();
    let want_sq = r["sum_sq"].as_f64().unwrap();
    assert!(
        (sum_sq - want_sq).abs() <= 1e-4 * want_sq,
        "{sum_sq} vs {want_sq}"
    );
}
