//! Encoders by kind: pretrained weights in Hugging Face layout load whatever prefix the file uses,
//! files of another size or family fail naming the tensors, and the fitted input gives the
//! announced feature sizes.

use std::path::{Path, PathBuf};

use candle_core::{DType, Device, Tensor};
use candle_nn::{VarBuilder, VarMap};
use veila_nn::encoders::ImageEncoder;
use veila_nn::encoders::depth_anything::{DepthAnythingV2Config, DepthAnythingV2Encoder};
use veila_nn::encoders::kind::{AnyEncoder, EncoderKind, VitSize};
use veila_nn::encoders::mit::{MitConfig, MitEncoder};

const DEV: Device = Device::Cpu;

fn parity_file(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/data/encoder_parity")
        .join(name)
}

/// Random weights of `build` saved as safetensors bytes (plus `extra` tensors the encoder ignores).
fn random_file(build: impl Fn(VarBuilder<'_>), extra: &[(&str, Tensor)]) -> Vec<u8> {
    let vm = VarMap::new();
    build(VarBuilder::from_varmap(&vm, DType::F32, &DEV));
    let mut tensors: std::collections::HashMap<String, Tensor> = vm
        .data()
        .lock()
        .unwrap()
        .iter()
        .map(|(k, v)| (k.clone(), v.as_tensor().clone()))
        .collect();
    for (k, t) in extra {
        tensors.insert(k.to_string(), t.clone());
    }
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("w.safetensors");
    candle_core::safetensors::save(&tensors, &p).unwrap();
    std::fs::read(&p).unwrap()
}

fn image(h: usize, w: usize, seed: u64) -> Vec<u8> {
    (0..h * w * 3)
        .map(|i| ((i as u64 * 2654435761 + seed) % 251) as u8)
        .collect()
}

fn max_abs(a: &Tensor, b: &Tensor) -> f32 {
    (a - b)
        .unwrap()
        .abs()
        .unwrap()
        .flatten_all()
        .unwrap()
        .max(0)
        .unwrap()
        .to_scalar()
        .unwrap()
}

#[test]
fn segformer_loads_under_either_prefix_and_rejects_other_sizes() {
    let path = Path::new("b0.safetensors");
    for prefix in ["segformer.encoder", "encoder"] {
        let cfg = MitConfig {
            weight_prefix: prefix.into(),
            ..MitConfig::mit_b0()
        };
        let head = Tensor::zeros((19, 256, 1, 1), DType::F32, &DEV).unwrap();
        let bytes = random_file(
            |vb| {
                MitEncoder::new(&cfg, vb).unwrap();
            },
            &[("decode_head.classifier.weight", head)],
        );
        let enc = EncoderKind::SegFormer(0)
            .load_pretrained(&bytes, path, DType::F32, &DEV)
            .unwrap();
        assert_eq!(enc.kind(), EncoderKind::SegFormer(0));
        assert_eq!(enc.channels(), [32, 64, 160, 256]);
        // the same numbers as the encoder built directly on the file's tensors
        let direct = MitEncoder::new(
            &cfg,
            VarBuilder::from_buffered_safetensors(bytes.clone(), DType::F32, &DEV).unwrap(),
        )
        .unwrap();
        let rgb = image(64, 96, 1);
        let feats = enc.encode_rgb8(&[&rgb], 64, 96, &DEV).unwrap();
        let x =
            veila_nn::encoders::rgb8_to_tensor(&rgb, 64, 96, &Default::default(), &DEV).unwrap();
        let want = direct.forward(&x).unwrap();
        let sizes = enc.feature_sizes_for_image(64, 96).unwrap();
        for i in 0..4 {
            assert_eq!(feats[i].dims()[2..], [sizes[i].0, sizes[i].1], "scale {i}");
            assert_eq!(max_abs(&feats[i], &want[i]), 0.0, "scale {i}");
        }
        // b0 weights named as b1: the mismatch names the tensor and the file
        let err = EncoderKind::SegFormer(1)
            .load_pretrained(&bytes, path, DType::F32, &DEV)
            .unwrap_err()
            .to_string();
        assert!(
            err.contains("mis-shaped")
                && err.contains(&format!("{prefix}.block.0.0"))
                && err.contains("b0.safetensors"),
            "{err}"
        );
    }
}

#[test]
fn small_parity_files_are_not_the_real_architectures() {
    // the committed parity files hold tiny configs in Hugging Face layout: right family, wrong size
    let bytes = std::fs::read(parity_file("segformer_small.safetensors")).unwrap();
    let err = EncoderKind::SegFormer(0)
        .load_pretrained(
            &bytes,
            Path::new("segformer_small.safetensors"),
            DType::F32,
            &DEV,
        )
        .unwrap_err()
        .to_string();
    assert!(err.contains("segformer.encoder."), "{err}");
    let bytes = std::fs::read(parity_file("depth_anything_small.safetensors")).unwrap();
    let err = EncoderKind::DepthAnythingV2(VitSize::Small)
        .load_pretrained(&bytes, Path::new("da.safetensors"), DType::F32, &DEV)
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("backbone.") && err.contains("da.safetensors"),
        "{err}"
    );
    // and a file of another family says what it expected and where to get it
    let err = EncoderKind::DepthAnythingV2(VitSize::Small)
        .load_pretrained(
            &std::fs::read(parity_file("segformer_small.safetensors")).unwrap(),
            Path::new("seg.safetensors"),
            DType::F32,
            &DEV,
        )
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("not a depth-anything-v2-small checkpoint")
            && err.contains("depth-anything/Depth-Anything-V2-Small-hf"),
        "{err}"
    );
    let err = EncoderKind::SegFormer(0)
        .load_pretrained(b"not safetensors", Path::new("x.bin"), DType::F32, &DEV)
        .unwrap_err()
        .to_string();
    assert!(err.contains("x.bin"), "{err}");
}

#[test]
fn depth_anything_and_dinov2_from_one_file() {
    let cfg = DepthAnythingV2Config::small();
    let bytes = random_file(
        |vb| {
            DepthAnythingV2Encoder::new(&cfg, vb).unwrap();
        },
        &[],
    );
    let path = Path::new("da2s.safetensors");
    let da = EncoderKind::DepthAnythingV2(VitSize::Small)
        .load_pretrained(&bytes, path, DType::F32, &DEV)
        .unwrap();
    // a 96 x 320 camera image is fed at 98 x 322
    let rgb = image(96, 320, 7);
    let feats = da.encode_rgb8(&[&rgb, &rgb], 96, 320, &DEV).unwrap();
    let sizes = da.feature_sizes_for_image(96, 320).unwrap();
    assert_eq!(sizes, [(28, 92), (14, 46), (7, 23), (4, 12)]);
    for i in 0..4 {
        assert_eq!(
            feats[i].dims(),
            &[2, da.channels()[i], sizes[i].0, sizes[i].1]
        );
    }
    // the same file's backbone as a plain DINOv2-S encoder: its last map is the backbone's
    // normalised last hidden state, which Depth-Anything's deepest reassemble layer reads
    let dino = EncoderKind::DinoV2(VitSize::Small)
        .load_pretrained(&bytes, path, DType::F32, &DEV)
        .unwrap();
    assert!(matches!(dino, AnyEncoder::DinoV2(..)));
    let f = dino.encode_rgb8(&[&rgb], 96, 320, &DEV).unwrap();
    assert_eq!(f[3].dims(), &[1, 384, 7, 23]);
    let AnyEncoder::DepthAnythingV2(_, inner) = &da else {
        panic!()
    };
    let x = veila_nn::encoders::preprocess::ImageProcessor {
        resize: veila_nn::encoders::preprocess::ResizeRule::NearestMultiple { multiple: 14 },
        ..veila_nn::encoders::preprocess::ImageProcessor::depth_anything_v2()
    }
    .preprocess(&rgb, 96, 320, &DEV)
    .unwrap();
    let (hs, ph, pw) = inner.backbone().hidden_states(&x, &[12], true).unwrap();
    let last = hs[0]
        .narrow(1, 1, ph * pw)
        .unwrap()
        .transpose(1, 2)
        .unwrap()
        .reshape((1, 384, ph, pw))
        .unwrap();
    assert_eq!(max_abs(&f[3], &last), 0.0);
    assert!(
        max_abs(&f[0], &f[3]) > 0.0,
        "different layers give different maps"
    );
}
