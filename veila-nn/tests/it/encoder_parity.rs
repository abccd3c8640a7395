//! Numerical parity of the SegFormer and Depth-Anything-V2 encoders with the Hugging Face
//! reference implementations, on the same random weights.
//!
//! `tests/data/encoder_parity/make_parity.py` (run by hand with `torch` and `transformers`, see
//! its docstring) builds `SegformerForSemanticSegmentation` and `DepthAnythingForDepthEstimation`
//! with small random configs, and saves their weights (Hugging Face names), a fixed input and the
//! reference outputs: every stage's multi-scale features, the segmentation logits and the depth.
//! Each output must match within 1e-4 relative to the reference tensor's largest magnitude.
//!
//! The same script's `--real DIR` mode writes the real architectures (DINOv2-S/14 with the
//! Depth-Anything-V2-Small head, SegFormer-B0 and -B2) outside the repository;
//! `real_architectures_match_transformers` checks them when `VEILA_ENCODER_PARITY_DIR` names that
//! directory and skips with a message otherwise.

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use candle_core::{DType, Device, Tensor};
use veila_nn::encoders::depth_anything::{DepthAnythingV2, DepthAnythingV2Config, DepthKind};
use veila_nn::encoders::dinov2::DinoV2Config;
use veila_nn::encoders::mit::{MitConfig, SegFormer, SegFormerConfig};
use veila_nn::encoders::preprocess::{ImageProcessor, ResizeRule};
use veila_nn::encoders::{ImageEncoder, depth_anything_resize_size};

const DEV: Device = Device::Cpu;
const REL_TOL: f32 = 1e-4;

fn data_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/encoder_parity")
}

fn load_io(dir: &Path, name: &str) -> HashMap<String, Tensor> {
    let path = dir.join(format!("{name}_io.safetensors"));
    candle_core::safetensors::load(&path, &DEV)
        .unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

/// Largest absolute difference divided by the reference's largest magnitude.
fn rel_err(got: &Tensor, want: &Tensor, what: &str) -> f32 {
    assert_eq!(got.dims(), want.dims(), "{what}: shape");
    let g = got
        .to_dtype(DType::F32)
        .unwrap()
        .flatten_all()
        .unwrap()
        .to_vec1::<f32>()
        .unwrap();
    let w = want
        .to_dtype(DType::F32)
        .unwrap()
        .flatten_all()
        .unwrap()
        .to_vec1::<f32>()
        .unwrap();
    let scale = w.iter().fold(0f32, |m, x| m.max(x.abs()));
    assert!(
        scale > 0.0,
        "{what}: reference is all zeros, the comparison would be empty"
    );
    let diff = g
        .iter()
        .zip(&w)
        .fold(0f32, |m, (a, b)| m.max((a - b).abs()));
    assert!(diff.is_finite(), "{what}: non-finite output");
    diff / scale
}

fn check(got: &Tensor, want: &Tensor, what: &str) {
    let e = rel_err(got, want, what);
    println!("{what}: relative max error {e:.2e}");
    assert!(
        e <= REL_TOL,
        "{what}: relative max error {e:.3e} > {REL_TOL:e}"
    );
}

fn segformer_parity(dir: &Path, name: &str, cfg: &SegFormerConfig) {
    let model = SegFormer::load(
        cfg,
        &dir.join(format!("{name}.safetensors")),
        DType::F32,
        &DEV,
    )
    .unwrap_or_else(|e| panic!("{name}: {e}"));
    let io = load_io(dir, name);
    let x = &io["pixel_values"];
    let feats = model.forward(x).unwrap();
    assert_eq!(feats.len(), 4);
    for (i, f) in feats.iter().enumerate() {
        check(f, &io[&format!("stage{i}")], &format!("{name} stage{i}"));
    }
    check(
        &model.logits(x).unwrap(),
        &io["logits"],
        &format!("{name} logits"),
    );
}

fn depth_anything_parity(dir: &Path, name: &str, cfg: &DepthAnythingV2Config) {
    let model = DepthAnythingV2::load(
        cfg,
        &dir.join(format!("{name}.safetensors")),
        DType::F32,
        &DEV,
    )
    .unwrap_or_else(|e| panic!("{name}: {e}"));
    let io = load_io(dir, name);
    let x = &io["pixel_values"];
    let feats = model.forward(x).unwrap();
    assert_eq!(feats.len(), 4);
    for (i, f) in feats.iter().enumerate() {
        check(f, &io[&format!("stage{i}")], &format!("{name} stage{i}"));
    }
    check(
        &model.predict_depth(x).unwrap(),
        &io["depth"],
        &format!("{name} depth"),
    );
}

/// Mirrors `small()` in make_parity.py.
fn small_segformer() -> SegFormerConfig {
    SegFormerConfig {
        encoder: MitConfig {
            hidden_sizes: [8, 16, 24, 32],
            depths: [1, 2, 1, 1],
            num_attention_heads: [1, 2, 3, 4],
            sr_ratios: [4, 2, 2, 1],
            mlp_ratios: [2, 2, 3, 4],
            ..MitConfig::mit_b0()
        },
        decoder_hidden_size: 16,
        num_labels: 5,
        head_prefix: "decode_head".to_string(),
        batch_norm_eps: 1e-5,
    }
}

/// Mirrors `small()` in make_parity.py.
fn small_depth_anything() -> DepthAnythingV2Config {
    DepthAnythingV2Config {
        backbone: DinoV2Config {
            hidden_size: 16,
            num_hidden_layers: 4,
            num_attention_heads: 2,
            patch_size: 4,
            image_size: 32,
            mlp_ratio: 2,
            layer_norm_eps: 1e-6,
            num_channels: 3,
        },
        out_indices: [1, 2, 3, 4],
        apply_layernorm: true,
        neck_hidden_sizes: [4, 8, 12, 16],
        reassemble_factors: [4.0, 2.0, 1.0, 0.5],
        fusion_hidden_size: 8,
        head_hidden_size: 4,
        depth_estimation_type: DepthKind::Relative,
        max_depth: 1.0,
        weight_prefix: String::new(),
    }
}

#[test]
fn segformer_small_matches_transformers() {
    segformer_parity(&data_dir(), "segformer_small", &small_segformer());
}

#[test]
fn depth_anything_small_matches_transformers() {
    depth_anything_parity(&data_dir(), "depth_anything_small", &small_depth_anything());
}

fn pipeline_image(io: &HashMap<String, Tensor>) -> (Vec<u8>, usize, usize) {
    let t = &io["pipeline_image"];
    let (h, w, _) = t.dims3().unwrap();
    (t.flatten_all().unwrap().to_vec1::<u8>().unwrap(), h, w)
}

/// Image in, class map at the image's size out: the SegFormer processor (bilinear resize to the
/// model size, ImageNet normalisation), the model, bilinear upsampling of the logits and argmax,
/// against `SegformerImageProcessorPil` + `post_process_semantic_segmentation`.
#[test]
fn segformer_pipeline_matches_transformers() {
    let cfg = small_segformer();
    let model = SegFormer::load(
        &cfg,
        &data_dir().join("segformer_small.safetensors"),
        DType::F32,
        &DEV,
    )
    .unwrap();
    let io = load_io(&data_dir(), "segformer_small");
    let (rgb, h, w) = pipeline_image(&io);
    let got = model
        .predict_label_map_rgb8(&ImageProcessor::segformer(72, 52), &rgb, h, w, &DEV)
        .unwrap();
    let want: Vec<i64> = io["pipeline_labels"]
        .flatten_all()
        .unwrap()
        .to_vec1::<i64>()
        .unwrap();
    assert_eq!(got.len(), want.len());
    let same = got
        .iter()
        .zip(&want)
        .filter(|(a, b)| i64::from(**a) == **b)
        .count();
    // equal logits give equal labels; allow the odd near-tie
    assert!(
        same * 1000 >= want.len() * 998,
        "{same} of {} labels agree",
        want.len()
    );
    let classes: std::collections::BTreeSet<i64> = want.iter().copied().collect();
    assert!(classes.len() >= 2, "the reference map is not constant");
}

/// Image in, depth at the image's size out: the Depth-Anything processor (aspect kept, patch
/// multiple, bicubic), the model, bicubic resampling to the image size, against
/// `DPTImageProcessorPil` + `post_process_depth_estimation`.
#[test]
fn depth_anything_pipeline_matches_transformers() {
    let cfg = small_depth_anything();
    let model = DepthAnythingV2::load(
        &cfg,
        &data_dir().join("depth_anything_small.safetensors"),
        DType::F32,
        &DEV,
    )
    .unwrap();
    let io = load_io(&data_dir(), "depth_anything_small");
    let (rgb, h, w) = pipeline_image(&io);
    let processor = ImageProcessor {
        resize: ResizeRule::KeepAspectMultiple {
            height: 24,
            width: 44,
            multiple: 4,
        },
        ..ImageProcessor::depth_anything_v2()
    };
    let got = model
        .predict_depth_map_rgb8(&processor, &rgb, h, w, &DEV)
        .unwrap();
    let got = Tensor::from_vec(got, (h, w), &DEV).unwrap();
    check(&got, &io["pipeline_depth"], "depth-anything pipeline");
}

#[test]
fn real_architectures_match_transformers() {
    let Some(dir) = std::env::var_os("VEILA_ENCODER_PARITY_DIR") else {
        println!(
            "skipped: set VEILA_ENCODER_PARITY_DIR to the output of make_parity.py --real DIR"
        );
        return;
    };
    let dir = PathBuf::from(dir);
    depth_anything_parity(
        &dir,
        "depth_anything_v2_small",
        &DepthAnythingV2Config::small(),
    );
    segformer_parity(&dir, "segformer_b0", &SegFormerConfig::b0_cityscapes());
    let b2 = SegFormerConfig {
        encoder: MitConfig::mit_b2(),
        decoder_hidden_size: 768,
        ..SegFormerConfig::b0_cityscapes()
    };
    segformer_parity(&dir, "segformer_b2", &b2);
}

/// The resize rule of the Depth-Anything-V2 `-hf` processor settings, against the output sizes
/// transformers' `DPTImageProcessorPil` produced (KITTI, nuScenes, ties rounded half to even).
#[test]
fn depth_anything_resize_size_matches_the_processor() {
    let path = data_dir().join("depth_anything_processor_sizes.json");
    let text = std::fs::read_to_string(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    let rows: Vec<serde_json::Value> = serde_json::from_str(&text).unwrap();
    assert!(rows.len() >= 10, "{}: too few rows", path.display());
    let pair = |v: &serde_json::Value| -> (usize, usize) {
        let a = v.as_array().unwrap();
        (
            a[0].as_u64().unwrap() as usize,
            a[1].as_u64().unwrap() as usize,
        )
    };
    for row in &rows {
        let (h, w) = pair(&row["input"]);
        let want = pair(&row["output"]);
        assert_eq!(
            depth_anything_resize_size(h, w, (518, 518), 14, true),
            want,
            "input {h}x{w}"
        );
    }
}
