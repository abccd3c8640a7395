//! Tests of the image encoders: checkpoint layouts written here independently in the HuggingFace
//! naming, numerics against plain-Rust references, the small CNN's overfit, losses, freezing.

use std::collections::{BTreeSet, HashMap};
use std::path::{Path, PathBuf};

use candle_core::{DType, Device, Tensor};
use candle_nn::{Optimizer, VarBuilder, VarMap};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use veila_nn::encoders::depth_anything::{
    DepthAnythingV2, DepthAnythingV2Config, DepthAnythingV2Encoder,
};
use veila_nn::encoders::dinov2::{DinoV2Backbone, DinoV2Config, bicubic_resize};
use veila_nn::encoders::losses::{log_depth_l1, pixel_accuracy, semantic_cross_entropy, silog};
use veila_nn::encoders::mit::{
    MitAttention, MitConfig, MitEncoder, OverlapPatchEmbed, SegFormer, SegFormerConfig,
};
use veila_nn::encoders::small_cnn::{DepthLoss, SmallCnn, SmallCnnConfig, SmallCnnLossConfig};
use veila_nn::encoders::{
    Frozen, ImageEncoder, Normalization, depthwise_conv2d, freeze_varmap, record_tensor_specs,
    resize_bilinear, resize_bilinear_differentiable, rgb8_to_tensor, size_for_multiple,
};

const DEV: Device = Device::Cpu;

fn rvec(rng: &mut ChaCha8Rng, n: usize, scale: f32) -> Vec<f32> {
    (0..n).map(|_| rng.random_range(-scale..scale)).collect()
}

fn rand_t(rng: &mut ChaCha8Rng, shape: &[usize], scale: f32) -> Tensor {
    let n = shape.iter().product();
    Tensor::from_vec(rvec(rng, n, scale), shape, &DEV).unwrap()
}

fn flat(t: &Tensor) -> Vec<f32> {
    t.flatten_all().unwrap().to_vec1::<f32>().unwrap()
}

fn max_abs_diff(a: &[f32], b: &[f32]) -> f32 {
    assert_eq!(a.len(), b.len());
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f32::max)
}

fn save(dir: &Path, name: &str, tensors: &HashMap<String, Tensor>) -> PathBuf {
    let path = dir.join(name);
    candle_core::safetensors::save(tensors, &path).unwrap();
    path
}

fn load_vb(path: &Path) -> VarBuilder<'static> {
    let bytes = std::fs::read(path).unwrap();
    VarBuilder::from_buffered_safetensors(bytes, DType::F32, &DEV).unwrap()
}

// ---------------------------------------------------------------------------------------------
// SegFormer MiT
// ---------------------------------------------------------------------------------------------

fn tiny_mit(prefix: &str) -> MitConfig {
    MitConfig {
        hidden_sizes: [8, 16, 24, 32],
        depths: [1, 1, 1, 1],
        num_attention_heads: [1, 2, 3, 4],
        weight_prefix: prefix.to_string(),
        ..MitConfig::mit_b0()
    }
}

/// Writes a random checkpoint in the transformers `SegformerForImageClassification` layout, names
/// spelled out here from modeling_segformer.py (not from the crate).
fn mit_checkpoint(cfg: &MitConfig, prefix: &str, rng: &mut ChaCha8Rng) -> HashMap<String, Tensor> {
    let mut t = HashMap::new();
    let mut put = |name: String, shape: &[usize], rng: &mut ChaCha8Rng| {
        t.insert(name, rand_t(rng, shape, 0.3));
    };
    for i in 0..4 {
        let h = cfg.hidden_sizes[i];
        let cin = if i == 0 { 3 } else { cfg.hidden_sizes[i - 1] };
        let k = cfg.patch_sizes[i];
        let pe = format!("{prefix}patch_embeddings.{i}");
        put(format!("{pe}.proj.weight"), &[h, cin, k, k], rng);
        put(format!("{pe}.proj.bias"), &[h], rng);
        put(format!("{pe}.layer_norm.weight"), &[h], rng);
        put(format!("{pe}.layer_norm.bias"), &[h], rng);
        for j in 0..cfg.depths[i] {
            let b = format!("{prefix}block.{i}.{j}");
            for ln in ["layer_norm_1", "layer_norm_2"] {
                put(format!("{b}.{ln}.weight"), &[h], rng);
                put(format!("{b}.{ln}.bias"), &[h], rng);
            }
            for p in ["query", "key", "value"] {
                put(format!("{b}.attention.self.{p}.weight"), &[h, h], rng);
                put(format!("{b}.attention.self.{p}.bias"), &[h], rng);
            }
            let sr = cfg.sr_ratios[i];
            if sr > 1 {
                put(
                    format!("{b}.attention.self.sr.weight"),
                    &[h, h, sr, sr],
                    rng,
                );
                put(format!("{b}.attention.self.sr.bias"), &[h], rng);
                put(format!("{b}.attention.self.layer_norm.weight"), &[h], rng);
                put(format!("{b}.attention.self.layer_norm.bias"), &[h], rng);
            }
            put(format!("{b}.attention.output.dense.weight"), &[h, h], rng);
            put(format!("{b}.attention.output.dense.bias"), &[h], rng);
            let m = 4 * h;
            put(format!("{b}.mlp.dense1.weight"), &[m, h], rng);
            put(format!("{b}.mlp.dense1.bias"), &[m], rng);
            put(format!("{b}.mlp.dwconv.dwconv.weight"), &[m, 1, 3, 3], rng);
            put(format!("{b}.mlp.dwconv.dwconv.bias"), &[m], rng);
            put(format!("{b}.mlp.dense2.weight"), &[h, m], rng);
            put(format!("{b}.mlp.dense2.bias"), &[h], rng);
        }
        put(format!("{prefix}layer_norm.{i}.weight"), &[h], rng);
        put(format!("{prefix}layer_norm.{i}.bias"), &[h], rng);
    }
    t
}

#[test]
fn mit_loads_hf_layout_and_gives_four_scales() {
    let mut rng = ChaCha8Rng::seed_from_u64(1);
    let cfg = tiny_mit("segformer.encoder");
    let mut ckpt = mit_checkpoint(&cfg, "segformer.encoder.", &mut rng);
    let encoder_names: BTreeSet<String> = ckpt.keys().cloned().collect();
    // a classification head as in nvidia/mit-b0; the encoder must ignore it
    ckpt.insert("classifier.weight".into(), rand_t(&mut rng, &[10, 32], 0.1));
    ckpt.insert("classifier.bias".into(), rand_t(&mut rng, &[10], 0.1));
    let dir = tempfile::tempdir().unwrap();
    let path = save(dir.path(), "mit.safetensors", &ckpt);

    let enc = MitEncoder::new(&cfg, load_vb(&path)).unwrap();
    let image = rand_t(&mut rng, &[2, 3, 64, 96], 2.0);
    let feats = enc.forward(&image).unwrap();
    assert_eq!(feats.len(), 4);
    let expect = [[2, 8, 16, 24], [2, 16, 8, 12], [2, 24, 4, 6], [2, 32, 2, 3]];
    for (f, e) in feats.iter().zip(expect) {
        assert_eq!(f.dims(), e);
        assert!(flat(f).iter().all(|v| v.is_finite()));
    }
    assert_eq!(enc.channels(), [8, 16, 24, 32]);
    assert_eq!(enc.strides(), [4.0, 8.0, 16.0, 32.0]);
    assert_eq!(
        enc.feature_sizes(64, 96),
        [(16, 24), (8, 12), (4, 6), (2, 3)]
    );

    // the model reads exactly the encoder tensors written above (nothing more, nothing less)
    let specs = record_tensor_specs(|vb| MitEncoder::new(&cfg, vb)).unwrap();
    let read: BTreeSet<String> = specs.iter().map(|s| s.name.clone()).collect();
    assert_eq!(read, encoder_names);
    for s in &specs {
        assert_eq!(s.shape, ckpt[&s.name].dims(), "{}", s.name);
    }

    // batch items are independent
    let single = enc.forward(&image.narrow(0, 1, 1).unwrap()).unwrap();
    let d = max_abs_diff(&flat(&single[3]), &flat(&feats[3].narrow(0, 1, 1).unwrap()));
    assert!(d < 1e-4, "batch coupling: {d}");
}

#[test]
fn mit_bare_prefix_and_clear_errors() {
    let mut rng = ChaCha8Rng::seed_from_u64(2);
    let dir = tempfile::tempdir().unwrap();
    // bare SegformerModel naming: "encoder."
    let cfg = tiny_mit("encoder");
    let ckpt = mit_checkpoint(&cfg, "encoder.", &mut rng);
    let path = save(dir.path(), "bare.safetensors", &ckpt);
    let enc = MitEncoder::new(&cfg, load_vb(&path)).unwrap();
    let feats = enc
        .forward(&rand_t(&mut rng, &[1, 3, 32, 32], 1.0))
        .unwrap();
    assert_eq!(feats[0].dims(), &[1, 8, 8, 8]);

    // wrong prefix: the error names the first tensor looked up
    let err = MitEncoder::new(&tiny_mit("segformer.encoder"), load_vb(&path)).unwrap_err();
    assert!(
        err.to_string()
            .contains("segformer.encoder.patch_embeddings.0.proj.weight"),
        "{err}"
    );

    // a missing tensor is named
    let missing = "encoder.block.2.0.attention.self.sr.weight";
    let mut broken = ckpt.clone();
    broken.remove(missing);
    let p = save(dir.path(), "missing.safetensors", &broken);
    let err = MitEncoder::new(&cfg, load_vb(&p)).unwrap_err().to_string();
    assert!(err.contains(missing), "{err}");

    // a mis-shaped tensor is named
    let bad = "encoder.block.1.0.mlp.dwconv.dwconv.weight";
    let mut broken = ckpt.clone();
    broken.insert(bad.into(), rand_t(&mut rng, &[64, 1, 5, 5], 0.1));
    let p = save(dir.path(), "shape.safetensors", &broken);
    let err = MitEncoder::new(&cfg, load_vb(&p)).unwrap_err().to_string();
    assert!(err.contains(bad), "{err}");

    // bad input: wrong channel count, too small for the reduction ratios
    let err = enc
        .forward(&Tensor::zeros((1, 1, 64, 64), DType::F32, &DEV).unwrap())
        .unwrap_err();
    assert!(err.to_string().contains("[B, 3, H, W]"), "{err}");
    let err = enc
        .forward(&Tensor::zeros((1, 3, 16, 64), DType::F32, &DEV).unwrap())
        .unwrap_err();
    assert!(err.to_string().contains("too small"), "{err}");
    // invalid config
    let mut c = tiny_mit("");
    c.num_attention_heads[2] = 5;
    assert!(MitEncoder::new(&c, VarBuilder::zeros(DType::F32, &DEV)).is_err());
}

#[test]
fn checked_loading_reports_by_name_and_file() {
    let mut rng = ChaCha8Rng::seed_from_u64(13);
    let dir = tempfile::tempdir().unwrap();
    let cfg = tiny_mit("segformer.encoder");
    let mut ckpt = mit_checkpoint(&cfg, "segformer.encoder.", &mut rng);
    ckpt.insert(
        "decode_head.classifier.weight".into(),
        rand_t(&mut rng, &[19, 8, 1, 1], 0.1),
    );
    let good = save(dir.path(), "good.safetensors", &ckpt);
    let enc = MitEncoder::load(&cfg, &good, DType::F32, &DEV).unwrap();
    assert_eq!(enc.channels(), [8, 16, 24, 32]);

    // missing + mis-shaped + unexpected-in-scope, all in one report, with the file name
    let mut broken = ckpt.clone();
    broken.remove("segformer.encoder.layer_norm.3.bias");
    broken.insert(
        "segformer.encoder.block.0.0.attention.self.query.weight".into(),
        rand_t(&mut rng, &[8, 9], 0.1),
    );
    broken.insert(
        "segformer.encoder.block.0.7.mlp.dense1.weight".into(),
        rand_t(&mut rng, &[2], 0.1),
    );
    let bad = save(dir.path(), "bad.safetensors", &broken);
    let err = MitEncoder::load(&cfg, &bad, DType::F32, &DEV).unwrap_err();
    let msg = err.to_string();
    match &err {
        veila_nn::Error::CheckpointMismatch { report, .. } => {
            assert_eq!(
                report.missing,
                vec!["segformer.encoder.layer_norm.3.bias".to_string()]
            );
            assert_eq!(
                report.unexpected,
                vec!["segformer.encoder.block.0.7.mlp.dense1.weight".to_string()]
            );
            assert_eq!(report.mis_shaped.len(), 1);
            assert_eq!(report.mis_shaped[0].2, vec![8, 9]);
        }
        other => panic!("unexpected error {other}"),
    }
    assert!(
        msg.contains("bad.safetensors") && msg.contains("layer_norm.3.bias"),
        "{msg}"
    );

    // IO and parse errors name the file
    let err = MitEncoder::load(&cfg, &dir.path().join("nope.safetensors"), DType::F32, &DEV)
        .unwrap_err()
        .to_string();
    assert!(err.contains("nope.safetensors"), "{err}");
    let junk = dir.path().join("junk.safetensors");
    std::fs::write(&junk, b"not a safetensors file").unwrap();
    let err = MitEncoder::load(&cfg, &junk, DType::F32, &DEV)
        .unwrap_err()
        .to_string();
    assert!(err.contains("junk.safetensors"), "{err}");

    // Depth-Anything: the full file (with mask_token) loads for the encoder and for the full model
    let dcfg = tiny_da();
    let (dckpt, _) = da_checkpoint(&dcfg, &mut rng, None);
    let dpath = save(dir.path(), "da.safetensors", &dckpt);
    DepthAnythingV2Encoder::load(&dcfg, &dpath, DType::F32, &DEV).unwrap();
    let full = DepthAnythingV2::load(&dcfg, &dpath, DType::F32, &DEV).unwrap();
    assert_eq!(
        full.predict_depth(&rand_t(&mut rng, &[1, 3, 28, 42], 1.0))
            .unwrap()
            .dims(),
        &[1, 28, 42]
    );
    let mut no_head = dckpt.clone();
    no_head.remove("head.conv3.bias");
    let p = save(dir.path(), "da_nohead.safetensors", &no_head);
    DepthAnythingV2Encoder::load(&dcfg, &p, DType::F32, &DEV).unwrap();
    let err = DepthAnythingV2::load(&dcfg, &p, DType::F32, &DEV)
        .unwrap_err()
        .to_string();
    assert!(err.contains("head.conv3.bias"), "{err}");

    // the small CNN round-trips through VarMap::save
    let scfg = SmallCnnConfig {
        channels: [8, 8, 8, 8],
        head_channels: 8,
        ..SmallCnnConfig::default()
    };
    let vm = VarMap::new();
    let model = SmallCnn::new(
        &scfg,
        veila_nn::seeded_var_builder(&vm, 9, DType::F32, &DEV),
    )
    .unwrap();
    let sp = dir.path().join("cnn.safetensors");
    vm.save(&sp).unwrap();
    let loaded = SmallCnn::load(&scfg, &sp, DType::F32, &DEV).unwrap();
    let img = rand_t(&mut rng, &[1, 3, 32, 32], 1.0);
    let a = model.forward_all(&img).unwrap();
    let b = loaded.forward_all(&img).unwrap();
    assert_eq!(
        flat(a.log_depth.as_ref().unwrap()),
        flat(b.log_depth.as_ref().unwrap())
    );
    let no_depth = SmallCnnConfig {
        depth_head: false,
        ..scfg.clone()
    };
    let err = SmallCnn::load(&no_depth, &sp, DType::F32, &DEV)
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("unexpected") && err.contains("depth_head"),
        "{err}"
    );
}

/// PyTorch bilinear, align_corners = false, on one [h, w] plane.
fn bilinear_ref(src: &[f32], h: usize, w: usize, oh: usize, ow: usize) -> Vec<f32> {
    let coord = |o: usize, i: usize, out: usize| -> (usize, usize, f32) {
        let s = ((o as f32 + 0.5) * i as f32 / out as f32 - 0.5).max(0.0);
        let i0 = (s.floor() as usize).min(i - 1);
        let i1 = (i0 + 1).min(i - 1);
        (i0, i1, s - i0 as f32)
    };
    let mut out = vec![0f32; oh * ow];
    for y in 0..oh {
        let (y0, y1, ty) = coord(y, h, oh);
        for x in 0..ow {
            let (x0, x1, tx) = coord(x, w, ow);
            let top = src[y0 * w + x0] * (1.0 - tx) + src[y0 * w + x1] * tx;
            let bot = src[y1 * w + x0] * (1.0 - tx) + src[y1 * w + x1] * tx;
            out[y * ow + x] = top * (1.0 - ty) + bot * ty;
        }
    }
    out
}

#[test]
fn segformer_head_matches_plain_reference_and_loads() {
    let mut rng = ChaCha8Rng::seed_from_u64(15);
    let cfg = SegFormerConfig {
        encoder: tiny_mit("segformer.encoder"),
        decoder_hidden_size: 6,
        num_labels: 5,
        ..SegFormerConfig::b0_cityscapes()
    };
    let mut ckpt = mit_checkpoint(&cfg.encoder, "segformer.encoder.", &mut rng);
    let d = 6;
    for (i, c) in cfg.encoder.hidden_sizes.iter().enumerate() {
        ckpt.insert(
            format!("decode_head.linear_c.{i}.proj.weight"),
            rand_t(&mut rng, &[d, *c], 0.5),
        );
        ckpt.insert(
            format!("decode_head.linear_c.{i}.proj.bias"),
            rand_t(&mut rng, &[d], 0.5),
        );
    }
    ckpt.insert(
        "decode_head.linear_fuse.weight".into(),
        rand_t(&mut rng, &[d, 4 * d, 1, 1], 0.5),
    );
    ckpt.insert(
        "decode_head.batch_norm.weight".into(),
        rand_t(&mut rng, &[d], 1.0),
    );
    ckpt.insert(
        "decode_head.batch_norm.bias".into(),
        rand_t(&mut rng, &[d], 1.0),
    );
    ckpt.insert(
        "decode_head.batch_norm.running_mean".into(),
        rand_t(&mut rng, &[d], 1.0),
    );
    let var: Vec<f32> = (0..d).map(|_| rng.random_range(0.5f32..2.0)).collect();
    ckpt.insert(
        "decode_head.batch_norm.running_var".into(),
        Tensor::from_vec(var, d, &DEV).unwrap(),
    );
    ckpt.insert(
        "decode_head.batch_norm.num_batches_tracked".into(),
        Tensor::new(100i64, &DEV).unwrap(),
    );
    ckpt.insert(
        "decode_head.classifier.weight".into(),
        rand_t(&mut rng, &[5, d, 1, 1], 0.5),
    );
    ckpt.insert(
        "decode_head.classifier.bias".into(),
        rand_t(&mut rng, &[5], 0.5),
    );
    let dir = tempfile::tempdir().unwrap();
    let path = save(dir.path(), "segformer.safetensors", &ckpt);
    let model = SegFormer::load(&cfg, &path, DType::F32, &DEV).unwrap();

    let (h, w) = (64, 96);
    let image = rand_t(&mut rng, &[1, 3, h, w], 1.5);
    let logits = model.logits(&image).unwrap();
    assert_eq!(logits.dims(), &[1, 5, 16, 24]);
    // reference head on the encoder's features
    let feats = model.encoder().forward(&image).unwrap();
    let (h0, w0) = (16, 24);
    let mut cat: Vec<Vec<f32>> = Vec::new(); // channel planes, deepest scale first
    for i in (0..4).rev() {
        let f = &feats[i];
        let (_, c, fh, fw) = f.dims4().unwrap();
        let fv = flat(f);
        let wt = flat(&ckpt[&format!("decode_head.linear_c.{i}.proj.weight")]);
        let bs = flat(&ckpt[&format!("decode_head.linear_c.{i}.proj.bias")]);
        for o in 0..d {
            let plane: Vec<f32> = (0..fh * fw)
                .map(|p| {
                    bs[o]
                        + (0..c)
                            .map(|ci| wt[o * c + ci] * fv[ci * fh * fw + p])
                            .sum::<f32>()
                })
                .collect();
            cat.push(bilinear_ref(&plane, fh, fw, h0, w0));
        }
    }
    let fw_ = flat(&ckpt["decode_head.linear_fuse.weight"]);
    let g = flat(&ckpt["decode_head.batch_norm.weight"]);
    let bb = flat(&ckpt["decode_head.batch_norm.bias"]);
    let rm = flat(&ckpt["decode_head.batch_norm.running_mean"]);
    let rv = flat(&ckpt["decode_head.batch_norm.running_var"]);
    let cw = flat(&ckpt["decode_head.classifier.weight"]);
    let cb = flat(&ckpt["decode_head.classifier.bias"]);
    let mut expect = vec![0f32; 5 * h0 * w0];
    for p in 0..h0 * w0 {
        let hid: Vec<f32> = (0..d)
            .map(|o| {
                let z: f32 = (0..4 * d).map(|k| fw_[o * 4 * d + k] * cat[k][p]).sum();
                ((z - rm[o]) / (rv[o] + 1e-5).sqrt() * g[o] + bb[o]).max(0.0)
            })
            .collect();
        for k in 0..5 {
            expect[k * h0 * w0 + p] = cb[k] + (0..d).map(|o| cw[k * d + o] * hid[o]).sum::<f32>();
        }
    }
    let diff = max_abs_diff(&flat(&logits), &expect);
    assert!(diff < 1e-3, "max diff {diff}");
    let labels = model.predict_labels(&image).unwrap();
    assert_eq!(labels.len(), 1);
    assert_eq!(labels[0].len(), h * w);
    assert!(labels[0].iter().all(|&l| l < 5));
}

#[test]
fn mit_b0_random_weights_shapes_and_size() {
    let varmap = VarMap::new();
    let vb = veila_nn::seeded_var_builder(&varmap, 7, DType::F32, &DEV);
    let cfg = MitConfig::mit_b0();
    let enc = MitEncoder::new(&cfg, vb).unwrap();
    let params: usize = varmap.all_vars().iter().map(|v| v.elem_count()).sum();
    // SegFormer paper: MiT-b0 encoder 3.4 M parameters (3.3 M without the classifier)
    assert!((3_200_000..3_500_000).contains(&params), "{params}");
    for (h, w) in [(64, 128), (70, 101)] {
        let img = Tensor::zeros((1, 3, h, w), DType::F32, &DEV).unwrap();
        let feats = enc.forward(&img).unwrap();
        let sizes = enc.feature_sizes(h, w);
        for i in 0..4 {
            assert_eq!(
                feats[i].dims(),
                &[1, cfg.hidden_sizes[i], sizes[i].0, sizes[i].1]
            );
        }
    }
    // degenerate and extreme inputs stay finite (LayerNorm of constant tokens, softmax of large
    // scores)
    for scale in [0.0f64, 1e3] {
        let img = (Tensor::ones((1, 3, 64, 64), DType::F32, &DEV).unwrap() * scale).unwrap();
        for f in enc.forward(&img).unwrap() {
            assert!(flat(&f).iter().all(|v| v.is_finite()), "scale {scale}");
        }
    }
    assert_eq!(
        enc.feature_sizes(70, 101),
        [(18, 26), (9, 13), (5, 7), (3, 4)]
    );
}

fn layer_norm_ref(x: &[f32], w: &[f32], b: &[f32], eps: f32) -> Vec<f32> {
    let n = x.len() as f32;
    let mean = x.iter().sum::<f32>() / n;
    let var = x.iter().map(|v| (v - mean) * (v - mean)).sum::<f32>() / n;
    x.iter()
        .enumerate()
        .map(|(i, v)| (v - mean) / (var + eps).sqrt() * w[i] + b[i])
        .collect()
}

/// Plain conv2d on a [C, H, W] buffer: weight [O, C, k, k].
fn conv_ref(
    x: &[f32],
    (c, h, w): (usize, usize, usize),
    wt: &[f32],
    bias: &[f32],
    o: usize,
    k: usize,
    stride: usize,
    pad: usize,
) -> (Vec<f32>, usize, usize) {
    let oh = (h + 2 * pad - k) / stride + 1;
    let ow = (w + 2 * pad - k) / stride + 1;
    let mut out = vec![0f32; o * oh * ow];
    for oc in 0..o {
        for y in 0..oh {
            for xx in 0..ow {
                let mut acc = bias[oc];
                for ic in 0..c {
                    for ky in 0..k {
                        for kx in 0..k {
                            let iy = (y * stride + ky) as isize - pad as isize;
                            let ix = (xx * stride + kx) as isize - pad as isize;
                            if iy < 0 || ix < 0 || iy >= h as isize || ix >= w as isize {
                                continue;
                            }
                            acc += wt[((oc * c + ic) * k + ky) * k + kx]
                                * x[(ic * h + iy as usize) * w + ix as usize];
                        }
                    }
                }
                out[(oc * oh + y) * ow + xx] = acc;
            }
        }
    }
    (out, oh, ow)
}

#[test]
fn overlap_patch_embed_matches_brute_force() {
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    let (c, o, k, s, h, w) = (3, 5, 7, 4, 13, 17);
    let wt = rvec(&mut rng, o * c * k * k, 0.3);
    let bias = rvec(&mut rng, o, 0.3);
    let lnw = rvec(&mut rng, o, 1.0);
    let lnb = rvec(&mut rng, o, 1.0);
    let x = rvec(&mut rng, c * h * w, 2.0);
    let mut ts = HashMap::new();
    ts.insert(
        "pe.proj.weight".to_string(),
        Tensor::from_vec(wt.clone(), (o, c, k, k), &DEV).unwrap(),
    );
    ts.insert(
        "pe.proj.bias".to_string(),
        Tensor::from_vec(bias.clone(), o, &DEV).unwrap(),
    );
    ts.insert(
        "pe.layer_norm.weight".to_string(),
        Tensor::from_vec(lnw.clone(), o, &DEV).unwrap(),
    );
    ts.insert(
        "pe.layer_norm.bias".to_string(),
        Tensor::from_vec(lnb.clone(), o, &DEV).unwrap(),
    );
    let vb = VarBuilder::from_tensors(ts, DType::F32, &DEV);
    let pe = OverlapPatchEmbed::new(c, o, k, s, 1e-5, vb.pp("pe")).unwrap();
    let (tokens, th, tw) = pe
        .forward(&Tensor::from_vec(x.clone(), (1, c, h, w), &DEV).unwrap())
        .unwrap();
    let (conv, oh, ow) = conv_ref(&x, (c, h, w), &wt, &bias, o, k, s, k / 2);
    assert_eq!((th, tw), (oh, ow));
    assert_eq!((oh, ow), (4, 5));
    let mut expect = Vec::new();
    for p in 0..oh * ow {
        let v: Vec<f32> = (0..o).map(|ch| conv[ch * oh * ow + p]).collect();
        expect.extend(layer_norm_ref(&v, &lnw, &lnb, 1e-5));
    }
    assert_eq!(tokens.dims(), &[1, oh * ow, o]);
    let d = max_abs_diff(&flat(&tokens), &expect);
    assert!(d < 1e-4, "max diff {d}");
}

fn linear_ref(x: &[f32], wt: &[f32], b: &[f32], out: usize) -> Vec<f32> {
    let inp = x.len();
    (0..out)
        .map(|o| b[o] + (0..inp).map(|i| wt[o * inp + i] * x[i]).sum::<f32>())
        .collect()
}

#[test]
fn efficient_attention_with_reduction_matches_naive() {
    let mut rng = ChaCha8Rng::seed_from_u64(4);
    let (c, heads, sr, h, w) = (6usize, 2usize, 2usize, 4usize, 6usize);
    let d = c / heads;
    let mut ts = HashMap::new();
    let mut raw: HashMap<&str, Vec<f32>> = HashMap::new();
    let specs: Vec<(&str, Vec<usize>)> = vec![
        ("self.query.weight", vec![c, c]),
        ("self.query.bias", vec![c]),
        ("self.key.weight", vec![c, c]),
        ("self.key.bias", vec![c]),
        ("self.value.weight", vec![c, c]),
        ("self.value.bias", vec![c]),
        ("self.sr.weight", vec![c, c, sr, sr]),
        ("self.sr.bias", vec![c]),
        ("self.layer_norm.weight", vec![c]),
        ("self.layer_norm.bias", vec![c]),
        ("output.dense.weight", vec![c, c]),
        ("output.dense.bias", vec![c]),
    ];
    for (name, shape) in &specs {
        let v = rvec(&mut rng, shape.iter().product(), 0.5);
        ts.insert(
            format!("att.{name}"),
            Tensor::from_vec(v.clone(), shape.as_slice(), &DEV).unwrap(),
        );
        raw.insert(name, v);
    }
    let vb = VarBuilder::from_tensors(ts, DType::F32, &DEV);
    let att = MitAttention::new(c, heads, sr, 1e-5, vb.pp("att")).unwrap();
    let n = h * w;
    let x = rvec(&mut rng, n * c, 1.5);
    let got = att
        .forward(&Tensor::from_vec(x.clone(), (1, n, c), &DEV).unwrap(), h, w)
        .unwrap();

    // naive reference
    let tok = |i: usize| &x[i * c..(i + 1) * c];
    let q: Vec<Vec<f32>> = (0..n)
        .map(|i| {
            linear_ref(
                tok(i),
                &raw["self.query.weight"],
                &raw["self.query.bias"],
                c,
            )
        })
        .collect();
    // spatial reduction: conv k = s = sr over the [C, h, w] map, then LayerNorm
    let (rh, rw) = (h / sr, w / sr);
    let mut reduced = Vec::new();
    for oy in 0..rh {
        for ox in 0..rw {
            let mut r = vec![0f32; c];
            for (oc, slot) in r.iter_mut().enumerate() {
                let mut acc = raw["self.sr.bias"][oc];
                for ic in 0..c {
                    for ky in 0..sr {
                        for kx in 0..sr {
                            let (yy, xx) = (oy * sr + ky, ox * sr + kx);
                            acc += raw["self.sr.weight"][((oc * c + ic) * sr + ky) * sr + kx]
                                * x[(yy * w + xx) * c + ic];
                        }
                    }
                }
                *slot = acc;
            }
            reduced.push(layer_norm_ref(
                &r,
                &raw["self.layer_norm.weight"],
                &raw["self.layer_norm.bias"],
                1e-5,
            ));
        }
    }
    let m = reduced.len();
    let k: Vec<Vec<f32>> = reduced
        .iter()
        .map(|r| linear_ref(r, &raw["self.key.weight"], &raw["self.key.bias"], c))
        .collect();
    let v: Vec<Vec<f32>> = reduced
        .iter()
        .map(|r| linear_ref(r, &raw["self.value.weight"], &raw["self.value.bias"], c))
        .collect();
    let mut expect = Vec::new();
    for i in 0..n {
        let mut ctx = vec![0f32; c];
        for hd in 0..heads {
            let s: Vec<f32> = (0..m)
                .map(|j| {
                    (0..d)
                        .map(|e| q[i][hd * d + e] * k[j][hd * d + e])
                        .sum::<f32>()
                        / (d as f32).sqrt()
                })
                .collect();
            let mx = s.iter().cloned().fold(f32::MIN, f32::max);
            let z: f32 = s.iter().map(|v| (v - mx).exp()).sum();
            for j in 0..m {
                let p = (s[j] - mx).exp() / z;
                for e in 0..d {
                    ctx[hd * d + e] += p * v[j][hd * d + e];
                }
            }
        }
        expect.extend(linear_ref(
            &ctx,
            &raw["output.dense.weight"],
            &raw["output.dense.bias"],
            c,
        ));
    }
    let diff = max_abs_diff(&flat(&got), &expect);
    assert!(diff < 1e-4, "max diff {diff}");
}

#[test]
fn depthwise_conv_matches_grouped_conv_and_brute_force() {
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    let (b, c, h, w) = (2, 5, 6, 7);
    let x = rand_t(&mut rng, &[b, c, h, w], 1.0);
    let wt = rand_t(&mut rng, &[c, 1, 3, 3], 1.0);
    let bias = rand_t(&mut rng, &[c], 1.0);
    let got = depthwise_conv2d(&x, &wt, Some(&bias), 1).unwrap();
    // the differentiable tensor path (taken when an input tracks gradients) agrees
    let xv = candle_core::Var::from_tensor(&x).unwrap();
    let got_graph = depthwise_conv2d(xv.as_tensor(), &wt, Some(&bias), 1).unwrap();
    assert!(max_abs_diff(&flat(&got), &flat(&got_graph)) < 1e-5);
    let g = got_graph.sum_all().unwrap().backward().unwrap();
    assert!(g.get(xv.as_tensor()).is_some());
    // other kernel sizes / no padding
    let w5 = rand_t(&mut rng, &[c, 1, 5, 5], 1.0);
    for pad in [0, 2] {
        let a = depthwise_conv2d(&x, &w5, None, pad).unwrap();
        let r = x.conv2d(&w5, pad, 1, 1, c).unwrap();
        assert_eq!(a.dims(), r.dims());
        assert!(max_abs_diff(&flat(&a), &flat(&r)) < 1e-4);
        let a2 = depthwise_conv2d(xv.as_tensor(), &w5, None, pad).unwrap();
        assert!(max_abs_diff(&flat(&a2), &flat(&r)) < 1e-4);
    }
    let grouped = x
        .conv2d(&wt, 1, 1, 1, c)
        .unwrap()
        .broadcast_add(&bias.reshape((1, c, 1, 1)).unwrap())
        .unwrap();
    assert_eq!(got.dims(), grouped.dims());
    assert!(max_abs_diff(&flat(&got), &flat(&grouped)) < 1e-5);
    // brute force on one channel of one image
    let xs = flat(&x.get(1).unwrap().get(3).unwrap());
    let ws = flat(&wt.get(3).unwrap());
    let bs = flat(&bias)[3];
    let (expect, _, _) = conv_ref(&xs, (1, h, w), &ws, &[bs], 1, 3, 1, 1);
    let g = flat(&got.get(1).unwrap().get(3).unwrap());
    assert!(max_abs_diff(&g, &expect) < 1e-5);
}

#[test]
fn mix_ffn_fast_path_matches_differentiable_path() {
    let mut rng = ChaCha8Rng::seed_from_u64(16);
    let (c, m, h, w) = (6, 12, 5, 7);
    let mut ts = HashMap::new();
    for (name, shape) in [
        ("f.dense1.weight", vec![m, c]),
        ("f.dense1.bias", vec![m]),
        ("f.dwconv.dwconv.weight", vec![m, 1, 3, 3]),
        ("f.dwconv.dwconv.bias", vec![m]),
        ("f.dense2.weight", vec![c, m]),
        ("f.dense2.bias", vec![c]),
    ] {
        ts.insert(name.to_string(), rand_t(&mut rng, &shape, 0.5));
    }
    let ffn = veila_nn::encoders::mit::MixFfn::new(
        c,
        m,
        VarBuilder::from_tensors(ts, DType::F32, &DEV).pp("f"),
    )
    .unwrap();
    let x = rand_t(&mut rng, &[2, h * w, c], 1.0);
    let fast = ffn.forward(&x, h, w).unwrap(); // plain tensors: channels-last CPU loop
    let xv = candle_core::Var::from_tensor(&x).unwrap();
    let slow = ffn.forward(xv.as_tensor(), h, w).unwrap(); // tracked: tensor ops on the map
    assert_eq!(fast.dims(), &[2, h * w, c]);
    let d = max_abs_diff(&flat(&fast), &flat(&slow));
    assert!(d < 1e-5, "max diff {d}");
}

// ---------------------------------------------------------------------------------------------
// DINOv2 / Depth-Anything-V2
// ---------------------------------------------------------------------------------------------

fn tiny_da() -> DepthAnythingV2Config {
    DepthAnythingV2Config {
        backbone: DinoV2Config {
            hidden_size: 16,
            num_hidden_layers: 4,
            num_attention_heads: 2,
            patch_size: 14,
            image_size: 28,
            mlp_ratio: 4,
            layer_norm_eps: 1e-6,
            num_channels: 3,
        },
        out_indices: [1, 2, 3, 4],
        neck_hidden_sizes: [4, 8, 16, 16],
        fusion_hidden_size: 8,
        head_hidden_size: 4,
        ..DepthAnythingV2Config::small()
    }
}

/// Random checkpoint in the `DepthAnythingForDepthEstimation` layout (names from transformers'
/// convert_depth_anything_to_hf.py / modeling_dinov2.py, spelled out here). Returns the tensors
/// and the names of the encoder part (backbone without mask_token, plus the reassemble stage).
fn da_checkpoint(
    cfg: &DepthAnythingV2Config,
    rng: &mut ChaCha8Rng,
    layer_scale: Option<f32>,
) -> (HashMap<String, Tensor>, BTreeSet<String>) {
    let bb = &cfg.backbone;
    let c = bb.hidden_size;
    let g = bb.image_size / bb.patch_size;
    let mut t = HashMap::new();
    let mut enc = BTreeSet::new();
    let mut put = |name: String, shape: &[usize], rng: &mut ChaCha8Rng, encoder: bool| {
        if encoder {
            enc.insert(name.clone());
        }
        t.insert(name, rand_t(rng, shape, 0.3));
    };
    put(
        "backbone.embeddings.cls_token".into(),
        &[1, 1, c],
        rng,
        true,
    );
    put("backbone.embeddings.mask_token".into(), &[1, c], rng, false);
    put(
        "backbone.embeddings.position_embeddings".into(),
        &[1, 1 + g * g, c],
        rng,
        true,
    );
    let p = bb.patch_size;
    put(
        "backbone.embeddings.patch_embeddings.projection.weight".into(),
        &[c, 3, p, p],
        rng,
        true,
    );
    put(
        "backbone.embeddings.patch_embeddings.projection.bias".into(),
        &[c],
        rng,
        true,
    );
    for l in 0..bb.num_hidden_layers {
        let b = format!("backbone.encoder.layer.{l}");
        for n in ["norm1", "norm2"] {
            put(format!("{b}.{n}.weight"), &[c], rng, true);
            put(format!("{b}.{n}.bias"), &[c], rng, true);
        }
        for q in ["query", "key", "value"] {
            put(
                format!("{b}.attention.attention.{q}.weight"),
                &[c, c],
                rng,
                true,
            );
            put(format!("{b}.attention.attention.{q}.bias"), &[c], rng, true);
        }
        put(
            format!("{b}.attention.output.dense.weight"),
            &[c, c],
            rng,
            true,
        );
        put(format!("{b}.attention.output.dense.bias"), &[c], rng, true);
        put(format!("{b}.layer_scale1.lambda1"), &[c], rng, true);
        put(format!("{b}.layer_scale2.lambda1"), &[c], rng, true);
        put(format!("{b}.mlp.fc1.weight"), &[4 * c, c], rng, true);
        put(format!("{b}.mlp.fc1.bias"), &[4 * c], rng, true);
        put(format!("{b}.mlp.fc2.weight"), &[c, 4 * c], rng, true);
        put(format!("{b}.mlp.fc2.bias"), &[c], rng, true);
    }
    put("backbone.layernorm.weight".into(), &[c], rng, true);
    put("backbone.layernorm.bias".into(), &[c], rng, true);
    for (i, f) in cfg.reassemble_factors.iter().enumerate() {
        let ch = cfg.neck_hidden_sizes[i];
        let r = format!("neck.reassemble_stage.layers.{i}");
        put(format!("{r}.projection.weight"), &[ch, c, 1, 1], rng, true);
        put(format!("{r}.projection.bias"), &[ch], rng, true);
        if *f > 1.0 {
            let k = *f as usize;
            put(format!("{r}.resize.weight"), &[ch, ch, k, k], rng, true); // ConvTranspose2d
            put(format!("{r}.resize.bias"), &[ch], rng, true);
        } else if *f < 1.0 {
            put(format!("{r}.resize.weight"), &[ch, ch, 3, 3], rng, true);
            put(format!("{r}.resize.bias"), &[ch], rng, true);
        }
    }
    let fz = cfg.fusion_hidden_size;
    for i in 0..4 {
        put(
            format!("neck.convs.{i}.weight"),
            &[fz, cfg.neck_hidden_sizes[i], 3, 3],
            rng,
            false,
        );
        let f = format!("neck.fusion_stage.layers.{i}");
        put(
            format!("{f}.projection.weight"),
            &[fz, fz, 1, 1],
            rng,
            false,
        );
        put(format!("{f}.projection.bias"), &[fz], rng, false);
        for r in ["residual_layer1", "residual_layer2"] {
            for cv in ["convolution1", "convolution2"] {
                put(format!("{f}.{r}.{cv}.weight"), &[fz, fz, 3, 3], rng, false);
                put(format!("{f}.{r}.{cv}.bias"), &[fz], rng, false);
            }
        }
    }
    put("head.conv1.weight".into(), &[fz / 2, fz, 3, 3], rng, false);
    put("head.conv1.bias".into(), &[fz / 2], rng, false);
    put(
        "head.conv2.weight".into(),
        &[cfg.head_hidden_size, fz / 2, 3, 3],
        rng,
        false,
    );
    put(
        "head.conv2.bias".into(),
        &[cfg.head_hidden_size],
        rng,
        false,
    );
    put(
        "head.conv3.weight".into(),
        &[1, cfg.head_hidden_size, 1, 1],
        rng,
        false,
    );
    put("head.conv3.bias".into(), &[1], rng, false);
    if let Some(v) = layer_scale {
        for l in 0..bb.num_hidden_layers {
            for s in ["layer_scale1", "layer_scale2"] {
                let name = format!("backbone.encoder.layer.{l}.{s}.lambda1");
                t.insert(name, Tensor::full(v, c, &DEV).unwrap());
            }
        }
    }
    (t, enc)
}

#[test]
fn depth_anything_loads_hf_layout_and_gives_four_scales() {
    let mut rng = ChaCha8Rng::seed_from_u64(6);
    let cfg = tiny_da();
    let (ckpt, enc_names) = da_checkpoint(&cfg, &mut rng, None);
    let dir = tempfile::tempdir().unwrap();
    let path = save(dir.path(), "da.safetensors", &ckpt);

    let enc = DepthAnythingV2Encoder::new(&cfg, load_vb(&path)).unwrap();
    let image = rand_t(&mut rng, &[2, 3, 56, 84], 2.0); // 4 x 6 patches
    let feats = enc.forward(&image).unwrap();
    let expect = [[2, 4, 16, 24], [2, 8, 8, 12], [2, 16, 4, 6], [2, 16, 2, 3]];
    for (f, e) in feats.iter().zip(expect) {
        assert_eq!(f.dims(), e);
        assert!(flat(f).iter().all(|v| v.is_finite()));
    }
    assert_eq!(enc.channels(), [4, 8, 16, 16]);
    assert_eq!(enc.strides(), [3.5, 7.0, 14.0, 28.0]);
    assert_eq!(
        enc.feature_sizes(56, 84),
        [(16, 24), (8, 12), (4, 6), (2, 3)]
    );
    assert_eq!(enc.input_spec().size_multiple, 14);

    let specs = record_tensor_specs(|vb| DepthAnythingV2Encoder::new(&cfg, vb)).unwrap();
    let read: BTreeSet<String> = specs.iter().map(|s| s.name.clone()).collect();
    assert_eq!(read, enc_names);
    let all: BTreeSet<String> = ckpt
        .keys()
        .filter(|k| !k.ends_with("mask_token"))
        .cloned()
        .collect();
    let specs = record_tensor_specs(|vb| DepthAnythingV2::new(&cfg, vb)).unwrap();
    let read: BTreeSet<String> = specs.iter().map(|s| s.name.clone()).collect();
    assert_eq!(read, all);
    for s in &specs {
        assert_eq!(s.shape, ckpt[&s.name].dims(), "{}", s.name);
    }

    // the full model with its depth head
    let full = DepthAnythingV2::new(&cfg, load_vb(&path)).unwrap();
    let depth = full.predict_depth(&image).unwrap();
    assert_eq!(depth.dims(), &[2, 56, 84]);
    let dv = flat(&depth);
    assert!(dv.iter().all(|v| v.is_finite() && *v >= 0.0));
    // a size that is not a multiple of 14 uses the floor grid, like PyTorch's strided conv
    let odd = full
        .forward(&rand_t(&mut rng, &[1, 3, 60, 90], 1.0))
        .unwrap();
    assert_eq!(odd[2].dims(), &[1, 16, 4, 6]);

    // missing and mis-shaped tensors are named
    let missing = "backbone.encoder.layer.3.layer_scale2.lambda1";
    let mut broken = ckpt.clone();
    broken.remove(missing);
    let p = save(dir.path(), "m.safetensors", &broken);
    let err = DepthAnythingV2Encoder::new(&cfg, load_vb(&p))
        .unwrap_err()
        .to_string();
    assert!(err.contains(missing), "{err}");
    let bad = "neck.reassemble_stage.layers.0.resize.weight";
    let mut broken = ckpt.clone();
    broken.insert(bad.into(), rand_t(&mut rng, &[4, 4, 2, 2], 0.1));
    let p = save(dir.path(), "s.safetensors", &broken);
    let err = DepthAnythingV2Encoder::new(&cfg, load_vb(&p))
        .unwrap_err()
        .to_string();
    assert!(err.contains(bad), "{err}");
    // image smaller than one patch
    let err = enc
        .forward(&Tensor::zeros((1, 3, 10, 40), DType::F32, &DEV).unwrap())
        .unwrap_err();
    assert!(err.to_string().contains("too small"), "{err}");
}

#[test]
fn depth_anything_v2_small_has_the_published_parameter_count() {
    // Depth-Anything-V2 paper / model card: Small 24.8 M parameters (backbone, neck and head)
    let specs = record_tensor_specs(|vb| DepthAnythingV2::new(&DepthAnythingV2Config::small(), vb))
        .unwrap();
    let n: usize = specs
        .iter()
        .map(|s| s.shape.iter().product::<usize>())
        .sum();
    assert!((24_750_000..24_850_000).contains(&n), "{n}");
    // the checkpoint's stored position grid is 37 x 37 (+ CLS) for 518 px training images
    let pos = specs
        .iter()
        .find(|s| s.name == "backbone.embeddings.position_embeddings")
        .unwrap();
    assert_eq!(pos.shape, vec![1, 1 + 37 * 37, 384]);
}

/// PyTorch's bicubic kernel, written as the 2-D sum over the 4x4 neighbourhood.
fn bicubic_ref(src: &[f32], ih: usize, iw: usize, oh: usize, ow: usize) -> Vec<f32> {
    let kern = |x: f32| {
        let a = -0.75f32;
        let x = x.abs();
        if x <= 1.0 {
            (a + 2.0) * x.powi(3) - (a + 3.0) * x.powi(2) + 1.0
        } else if x < 2.0 {
            a * x.powi(3) - 5.0 * a * x.powi(2) + 8.0 * a * x - 4.0 * a
        } else {
            0.0
        }
    };
    let mut out = vec![0f32; oh * ow];
    for oy in 0..oh {
        for ox in 0..ow {
            let sy = (oy as f32 + 0.5) * ih as f32 / oh as f32 - 0.5;
            let sx = (ox as f32 + 0.5) * iw as f32 / ow as f32 - 0.5;
            let (fy, fx) = (sy.floor() as i64, sx.floor() as i64);
            let mut acc = 0f32;
            for yy in fy - 1..=fy + 2 {
                for xx in fx - 1..=fx + 2 {
                    let wgt = kern(sy - yy as f32) * kern(sx - xx as f32);
                    let cy = yy.clamp(0, ih as i64 - 1) as usize;
                    let cx = xx.clamp(0, iw as i64 - 1) as usize;
                    acc += wgt * src[cy * iw + cx];
                }
            }
            out[oy * ow + ox] = acc;
        }
    }
    out
}

#[test]
fn bicubic_position_interpolation_matches_reference() {
    let mut rng = ChaCha8Rng::seed_from_u64(8);
    for (ih, iw, oh, ow) in [(4, 4, 7, 3), (5, 5, 2, 9), (37, 37, 13, 44), (3, 3, 3, 3)] {
        let c = 2;
        let src = rvec(&mut rng, c * ih * iw, 1.0);
        let got = bicubic_resize(&src, c, ih, iw, oh, ow);
        for ch in 0..c {
            let expect = bicubic_ref(&src[ch * ih * iw..(ch + 1) * ih * iw], ih, iw, oh, ow);
            let d = max_abs_diff(&got[ch * oh * ow..(ch + 1) * oh * ow], &expect);
            assert!(d < 1e-5, "{ih}x{iw}->{oh}x{ow}: {d}");
        }
        if (ih, iw) == (oh, ow) {
            assert!(
                max_abs_diff(&got, &src) < 1e-6,
                "same size must be the identity"
            );
        }
    }
    // constants are preserved (weights sum to one, border clamping)
    let got = bicubic_resize(&[2.5; 9], 1, 3, 3, 5, 7);
    assert!(got.iter().all(|v| (v - 2.5).abs() < 1e-5));
    // inconsistent input gives an empty result rather than a panic
    assert!(bicubic_resize(&[1.0; 5], 1, 2, 2, 3, 3).is_empty());
}

#[test]
fn dinov2_embeddings_match_brute_force_and_zero_layer_scale_is_identity() {
    let mut rng = ChaCha8Rng::seed_from_u64(9);
    let cfg = tiny_da();
    let bb = &cfg.backbone;
    let (ckpt, _) = da_checkpoint(&cfg, &mut rng, Some(0.0));
    let vb = VarBuilder::from_tensors(ckpt.clone(), DType::F32, &DEV);
    let backbone = DinoV2Backbone::new(bb, vb.pp("backbone")).unwrap();
    let (h, w) = (42, 70); // 3 x 5 patches, stored grid 2 x 2
    let image = rand_t(&mut rng, &[1, 3, h, w], 1.0);
    let (hs, ph, pw) = backbone.hidden_states(&image, &[0, 4], false).unwrap();
    assert_eq!((ph, pw), (3, 5));
    // with every layer scale at zero each layer is the identity
    assert!(max_abs_diff(&flat(&hs[0]), &flat(&hs[1])) < 1e-6);

    // brute force: patch conv + CLS + bicubic-resampled position embeddings
    let c = bb.hidden_size;
    let p = bb.patch_size;
    let (conv, oh, ow) = conv_ref(
        &flat(&image),
        (3, h, w),
        &flat(&ckpt["backbone.embeddings.patch_embeddings.projection.weight"]),
        &flat(&ckpt["backbone.embeddings.patch_embeddings.projection.bias"]),
        c,
        p,
        p,
        0,
    );
    assert_eq!((oh, ow), (3, 5));
    let pos = flat(&ckpt["backbone.embeddings.position_embeddings"]);
    let cls = flat(&ckpt["backbone.embeddings.cls_token"]);
    let g = 2;
    let mut expect = vec![0f32; (1 + oh * ow) * c];
    for ch in 0..c {
        expect[ch] = cls[ch] + pos[ch];
        let plane: Vec<f32> = (0..g * g).map(|i| pos[(1 + i) * c + ch]).collect();
        let r = bicubic_ref(&plane, g, g, oh, ow);
        for t in 0..oh * ow {
            expect[(1 + t) * c + ch] = conv[ch * oh * ow + t] + r[t];
        }
    }
    let d = max_abs_diff(&flat(&hs[0]), &expect);
    assert!(d < 1e-4, "max diff {d}");
}

fn erf_ref(x: f64) -> f64 {
    // Abramowitz & Stegun 7.1.26, |error| < 1.5e-7
    let t = 1.0 / (1.0 + 0.3275911 * x.abs());
    let y = 1.0
        - (((((1.061405429 * t - 1.453152027) * t) + 1.421413741) * t - 0.284496736) * t
            + 0.254829592)
            * t
            * (-x * x).exp();
    if x >= 0.0 { y } else { -y }
}

#[test]
fn dinov2_layer_matches_plain_reference() {
    let mut rng = ChaCha8Rng::seed_from_u64(12);
    let cfg = DinoV2Config {
        hidden_size: 8,
        num_attention_heads: 2,
        mlp_ratio: 2,
        ..tiny_da().backbone
    };
    let (c, m, heads) = (8usize, 16usize, 2usize);
    let d = c / heads;
    let specs: Vec<(&str, Vec<usize>)> = vec![
        ("norm1.weight", vec![c]),
        ("norm1.bias", vec![c]),
        ("attention.attention.query.weight", vec![c, c]),
        ("attention.attention.query.bias", vec![c]),
        ("attention.attention.key.weight", vec![c, c]),
        ("attention.attention.key.bias", vec![c]),
        ("attention.attention.value.weight", vec![c, c]),
        ("attention.attention.value.bias", vec![c]),
        ("attention.output.dense.weight", vec![c, c]),
        ("attention.output.dense.bias", vec![c]),
        ("layer_scale1.lambda1", vec![c]),
        ("norm2.weight", vec![c]),
        ("norm2.bias", vec![c]),
        ("mlp.fc1.weight", vec![m, c]),
        ("mlp.fc1.bias", vec![m]),
        ("mlp.fc2.weight", vec![c, m]),
        ("mlp.fc2.bias", vec![c]),
        ("layer_scale2.lambda1", vec![c]),
    ];
    let mut ts = HashMap::new();
    let mut raw: HashMap<&str, Vec<f32>> = HashMap::new();
    for (name, shape) in &specs {
        let v = rvec(&mut rng, shape.iter().product(), 0.8);
        ts.insert(
            format!("l.{name}"),
            Tensor::from_vec(v.clone(), shape.as_slice(), &DEV).unwrap(),
        );
        raw.insert(name, v);
    }
    let layer = veila_nn::encoders::dinov2::DinoV2Layer::new(
        &cfg,
        VarBuilder::from_tensors(ts, DType::F32, &DEV).pp("l"),
    )
    .unwrap();
    let n = 5;
    let x = rvec(&mut rng, n * c, 2.0);
    let got = layer
        .forward(&Tensor::from_vec(x.clone(), (1, n, c), &DEV).unwrap())
        .unwrap();

    let eps = 1e-6;
    let r = |k: &str| raw[k].as_slice();
    let y: Vec<Vec<f32>> = (0..n)
        .map(|i| {
            layer_norm_ref(
                &x[i * c..(i + 1) * c],
                r("norm1.weight"),
                r("norm1.bias"),
                eps,
            )
        })
        .collect();
    let proj = |w: &str, b: &str| -> Vec<Vec<f32>> {
        y.iter().map(|t| linear_ref(t, r(w), r(b), c)).collect()
    };
    let q = proj(
        "attention.attention.query.weight",
        "attention.attention.query.bias",
    );
    let k = proj(
        "attention.attention.key.weight",
        "attention.attention.key.bias",
    );
    let v = proj(
        "attention.attention.value.weight",
        "attention.attention.value.bias",
    );
    let mut expect = Vec::new();
    for i in 0..n {
        let mut ctx = vec![0f32; c];
        for hd in 0..heads {
            let s: Vec<f32> = (0..n)
                .map(|j| {
                    (0..d)
                        .map(|e| q[i][hd * d + e] * k[j][hd * d + e])
                        .sum::<f32>()
                        / (d as f32).sqrt()
                })
                .collect();
            let mx = s.iter().cloned().fold(f32::MIN, f32::max);
            let z: f32 = s.iter().map(|a| (a - mx).exp()).sum();
            for j in 0..n {
                for e in 0..d {
                    ctx[hd * d + e] += (s[j] - mx).exp() / z * v[j][hd * d + e];
                }
            }
        }
        let a = linear_ref(
            &ctx,
            r("attention.output.dense.weight"),
            r("attention.output.dense.bias"),
            c,
        );
        let h1: Vec<f32> = (0..c)
            .map(|e| x[i * c + e] + a[e] * r("layer_scale1.lambda1")[e])
            .collect();
        let y2 = layer_norm_ref(&h1, r("norm2.weight"), r("norm2.bias"), eps);
        let f1: Vec<f32> = linear_ref(&y2, r("mlp.fc1.weight"), r("mlp.fc1.bias"), m)
            .iter()
            .map(|&u| {
                (0.5 * u as f64 * (1.0 + erf_ref(u as f64 / std::f64::consts::SQRT_2))) as f32
            })
            .collect();
        let f2 = linear_ref(&f1, r("mlp.fc2.weight"), r("mlp.fc2.bias"), c);
        expect.extend((0..c).map(|e| h1[e] + f2[e] * r("layer_scale2.lambda1")[e]));
    }
    let diff = max_abs_diff(&flat(&got), &expect);
    assert!(diff < 1e-4, "max diff {diff}");
}

// ---------------------------------------------------------------------------------------------
// Small CNN, losses, freezing, input helpers
// ---------------------------------------------------------------------------------------------

#[test]
fn small_cnn_shapes_and_parameter_budget() {
    let varmap = VarMap::new();
    let cfg = SmallCnnConfig::default();
    let model = SmallCnn::new(
        &cfg,
        veila_nn::seeded_var_builder(&varmap, 1, DType::F32, &DEV),
    )
    .unwrap();
    let data = varmap.data().lock().unwrap();
    let enc: usize = data
        .iter()
        .filter(|(k, _)| k.starts_with("encoder."))
        .map(|(_, v)| v.elem_count())
        .sum();
    let total: usize = data.values().map(|v| v.elem_count()).sum();
    drop(data);
    assert!(
        (100_000..500_000).contains(&enc),
        "encoder parameters {enc}"
    );
    assert!(total < 600_000, "total parameters {total}");
    for (h, w) in [(64, 128), (37, 70)] {
        let img = Tensor::zeros((2, 3, h, w), DType::F32, &DEV).unwrap();
        let out = model.forward_all(&img).unwrap();
        let sizes = model.feature_sizes(h, w);
        for i in 0..4 {
            assert_eq!(
                out.features[i].dims(),
                &[2, cfg.channels[i], sizes[i].0, sizes[i].1]
            );
        }
        assert_eq!(out.semantic_logits.unwrap().dims(), &[2, 20, h, w]);
        assert_eq!(out.log_depth.unwrap().dims(), &[2, 1, h, w]);
    }
    assert_eq!(
        model.feature_sizes(37, 70),
        [(10, 18), (5, 9), (3, 5), (2, 3)]
    );
}

/// A synthetic scene: class 1 sky band on top, class 2 / 3 left / right below, class 0 (unlabelled)
/// in a small box; depth grows towards the top, class 3 is nearer. Colours follow the classes.
fn synthetic(h: usize, w: usize) -> (Vec<u8>, Vec<u32>, Vec<f32>) {
    let mut rgb = vec![0u8; h * w * 3];
    let mut labels = vec![0u32; h * w];
    let mut depth = vec![0f32; h * w];
    for y in 0..h {
        for x in 0..w {
            let i = y * w + x;
            let (l, col, d) = if y < h / 4 {
                (1, [90, 140, 230], 60.0)
            } else if x < w / 2 {
                (2, [120, 120, 110], 4.0 + 30.0 * (h - y) as f32 / h as f32)
            } else {
                (3, [200, 60, 40], 3.0 + 10.0 * (h - y) as f32 / h as f32)
            };
            let l = if (10..14).contains(&y) && (4..8).contains(&x) {
                0
            } else {
                l
            };
            labels[i] = l;
            depth[i] = if y == h - 1 { 0.0 } else { d }; // a row without ground truth
            rgb[i * 3..i * 3 + 3].copy_from_slice(&col);
        }
    }
    (rgb, labels, depth)
}

#[test]
fn small_cnn_overfits_one_image() {
    let (h, w) = (32, 64);
    let (rgb, labels, depth) = synthetic(h, w);
    let image = rgb8_to_tensor(&rgb, h, w, &Normalization::IMAGENET, &DEV).unwrap();
    let labels_t = Tensor::from_vec(labels.clone(), (1, h, w), &DEV).unwrap();
    let depth_t = Tensor::from_vec(depth.clone(), (1, 1, h, w), &DEV).unwrap();
    let cfg = SmallCnnConfig {
        channels: [8, 16, 16, 16],
        head_channels: 16,
        ..SmallCnnConfig::default()
    };
    let varmap = VarMap::new();
    let model = SmallCnn::new(
        &cfg,
        veila_nn::seeded_var_builder(&varmap, 3, DType::F32, &DEV),
    )
    .unwrap();
    let mut opt = candle_nn::AdamW::new(
        varmap.all_vars(),
        candle_nn::ParamsAdamW {
            lr: 1e-2,
            weight_decay: 0.0,
            ..Default::default()
        },
    )
    .unwrap();
    let loss_cfg = SmallCnnLossConfig::default();
    let loss_at = |model: &SmallCnn| -> (Tensor, f32, f32) {
        let l = model
            .loss(&image, Some(&labels_t), Some(&depth_t), &loss_cfg)
            .unwrap();
        (l.total, l.semantic.unwrap(), l.depth.unwrap())
    };
    let (_, ce0, dl0) = loss_at(&model);
    for _ in 0..120 {
        let (loss, _, _) = loss_at(&model);
        opt.backward_step(&loss).unwrap();
    }
    let (_, ce1, dl1) = loss_at(&model);
    eprintln!("cross-entropy {ce0:.4} -> {ce1:.4}, log-depth L1 {dl0:.4} -> {dl1:.4}");
    assert!(ce1 < ce0 / 10.0, "cross-entropy {ce0} -> {ce1}");
    assert!(dl1 < dl0 / 5.0, "log-depth L1 {dl0} -> {dl1}");

    let maps = model.predict_maps(&image).unwrap();
    assert_eq!(maps.len(), 1);
    let m = &maps[0];
    assert_eq!((m.height, m.width), (h, w));
    let pred = m.labels.as_ref().unwrap();
    assert!(
        pred.iter().all(|&l| l != 0),
        "the ignore class is never predicted"
    );
    let (mut hit, mut n) = (0, 0);
    for i in 0..h * w {
        if labels[i] != 0 {
            n += 1;
            hit += usize::from(pred[i] == labels[i]);
        }
    }
    assert!(hit as f32 / n as f32 > 0.95, "accuracy {hit}/{n}");
    let dm = m.depth_m.as_ref().unwrap();
    let mut rel = 0.0;
    let mut cnt = 0;
    for i in 0..h * w {
        if depth[i] > 0.0 {
            rel += (dm[i] - depth[i]).abs() / depth[i];
            cnt += 1;
        }
        assert!(dm[i] >= cfg.min_depth_m && dm[i] <= cfg.max_depth_m);
    }
    assert!(
        rel / (cnt as f32) < 0.2,
        "mean relative depth error {}",
        rel / cnt as f32
    );
}

#[test]
fn losses_match_plain_references_and_stay_finite() {
    let mut rng = ChaCha8Rng::seed_from_u64(10);
    let (b, k, h, w) = (2, 4, 2, 3);
    let logits = rvec(&mut rng, b * k * h * w, 3.0);
    let labels: Vec<u32> = vec![0, 1, 2, 3, 1, 2, 3, 3, 0, 0, 1, 2];
    let lt = Tensor::from_vec(logits.clone(), (b, k, h, w), &DEV).unwrap();
    let lab = Tensor::from_vec(labels.clone(), (b, h, w), &DEV).unwrap();
    let ce = semantic_cross_entropy(&lt, &lab, Some(0))
        .unwrap()
        .to_scalar::<f32>()
        .unwrap();
    let mut sum = 0.0f64;
    let mut n = 0;
    for bi in 0..b {
        for p in 0..h * w {
            let l = labels[bi * h * w + p] as usize;
            if l == 0 {
                continue;
            }
            let z: Vec<f64> = (0..k)
                .map(|c| logits[(bi * k + c) * h * w + p] as f64)
                .collect();
            let mx = z.iter().cloned().fold(f64::MIN, f64::max);
            let lse = mx + z.iter().map(|v| (v - mx).exp()).sum::<f64>().ln();
            sum += lse - z[l];
            n += 1;
        }
    }
    assert!(
        (ce as f64 - sum / n as f64).abs() < 1e-4,
        "{ce} vs {}",
        sum / n as f64
    );
    // no ignore index: class 0 counts
    let ce_all = semantic_cross_entropy(&lt, &lab, None)
        .unwrap()
        .to_scalar::<f32>()
        .unwrap();
    assert!(ce_all.is_finite() && (ce_all - ce).abs() > 1e-6);
    // huge logits stay finite
    let huge = (lt.clone() * 1e6).unwrap();
    let v = semantic_cross_entropy(&huge, &lab, Some(0))
        .unwrap()
        .to_scalar::<f32>()
        .unwrap();
    assert!(v.is_finite());
    // everything ignored -> 0, not NaN
    let zeros = Tensor::zeros((b, h, w), DType::U32, &DEV).unwrap();
    assert_eq!(
        semantic_cross_entropy(&lt, &zeros, Some(0))
            .unwrap()
            .to_scalar::<f32>()
            .unwrap(),
        0.0
    );
    // out-of-range labels are an error that says so
    let bad = Tensor::full(7u32, (b, h, w), &DEV).unwrap();
    let err = semantic_cross_entropy(&lt, &bad, Some(0))
        .unwrap_err()
        .to_string();
    assert!(err.contains("out of range"), "{err}");
    assert!(pixel_accuracy(&lt, &lab, Some(0)).unwrap() <= 1.0);

    // depth losses with holes (0), NaN and inf targets
    let pred = vec![1.0f32, 2.0, 0.5, 3.0, -1.0, 2.5];
    let target = vec![2.0f32, 0.0, f32::NAN, 10.0, f32::INFINITY, 5.0];
    let pt = Tensor::from_vec(pred.clone(), (1, 1, 2, 3), &DEV).unwrap();
    let tt = Tensor::from_vec(target.clone(), (1, 2, 3), &DEV).unwrap();
    let g: Vec<f64> = pred
        .iter()
        .zip(&target)
        .filter(|(_, t)| t.is_finite() && **t > 0.0)
        .map(|(p, t)| *p as f64 - (*t as f64).ln())
        .collect();
    let nv = g.len() as f64;
    let l1 = log_depth_l1(&pt, &tt).unwrap().to_scalar::<f32>().unwrap() as f64;
    assert!((l1 - g.iter().map(|v| v.abs()).sum::<f64>() / nv).abs() < 1e-5);
    for lambda in [0.0, 0.5, 0.85, 1.0] {
        let s = silog(&pt, &tt, lambda).unwrap().to_scalar::<f32>().unwrap() as f64;
        let m2 = g.iter().map(|v| v * v).sum::<f64>() / nv;
        let m1 = g.iter().sum::<f64>() / nv;
        assert!(
            (s - (m2 - lambda * m1 * m1)).abs() < 1e-5,
            "lambda {lambda}"
        );
    }
    // gradients stay finite with invalid targets
    let var = candle_core::Var::from_tensor(&pt).unwrap();
    let loss = silog(var.as_tensor(), &tt, 0.85).unwrap();
    let grads = loss.backward().unwrap();
    let gv = flat(grads.get(var.as_tensor()).unwrap());
    assert!(gv.iter().all(|v| v.is_finite()));
    assert_eq!(gv[1], 0.0);
    assert_eq!(gv[2], 0.0);
    // no valid pixel -> 0
    let none = Tensor::zeros((1, 2, 3), DType::F32, &DEV).unwrap();
    assert_eq!(
        log_depth_l1(&pt, &none)
            .unwrap()
            .to_scalar::<f32>()
            .unwrap(),
        0.0
    );
    assert!(silog(&pt, &tt, 1.5).is_err());
    assert!(log_depth_l1(&pt, &Tensor::zeros((1, 5), DType::F32, &DEV).unwrap()).is_err());
}

#[test]
fn frozen_encoders_receive_no_gradient() {
    let cfg = SmallCnnConfig {
        channels: [8, 8, 8, 8],
        head_channels: 8,
        ..SmallCnnConfig::default()
    };
    let varmap = VarMap::new();
    let model = SmallCnn::new(
        &cfg,
        veila_nn::seeded_var_builder(&varmap, 4, DType::F32, &DEV),
    )
    .unwrap();
    let img = Tensor::ones((1, 3, 32, 32), DType::F32, &DEV).unwrap();
    let vars = varmap.all_vars();

    // trainable: some encoder weight receives a gradient
    let loss = model.forward(&img).unwrap()[3]
        .sqr()
        .unwrap()
        .sum_all()
        .unwrap();
    let grads = loss.backward().unwrap();
    assert!(vars.iter().any(|v| grads.get(v.as_tensor()).is_some()));

    // frozen wrapper: none does
    let frozen = Frozen::new(model.clone());
    let feats = frozen.forward(&img).unwrap();
    let x = candle_core::Var::ones((1, 8, 1, 1), DType::F32, &DEV).unwrap();
    let loss = feats[3]
        .broadcast_mul(x.as_tensor())
        .unwrap()
        .sum_all()
        .unwrap();
    let grads = loss.backward().unwrap();
    assert!(vars.iter().all(|v| grads.get(v.as_tensor()).is_none()));
    assert!(grads.get(x.as_tensor()).is_some());

    // snapshot: later optimiser steps on the VarMap do not change the frozen copy
    let snap = SmallCnn::new(&cfg, freeze_varmap(&varmap, DType::F32, &DEV).unwrap()).unwrap();
    let before = flat(&snap.forward(&img).unwrap()[0]);
    assert!(max_abs_diff(&before, &flat(&model.forward(&img).unwrap()[0])) < 1e-6);
    for v in &vars {
        v.set(&(v.as_tensor() * 1.5).unwrap()).unwrap();
    }
    let after = flat(&snap.forward(&img).unwrap()[0]);
    assert_eq!(before, after);
    assert!(max_abs_diff(&before, &flat(&model.forward(&img).unwrap()[0])) > 1e-4);
}

#[test]
fn rgb_helpers() {
    let (h, w) = (2, 3);
    let rgb: Vec<u8> = (0..h * w * 3).map(|i| (i * 13 % 256) as u8).collect();
    let t = rgb8_to_tensor(&rgb, h, w, &Normalization::IMAGENET, &DEV).unwrap();
    assert_eq!(t.dims(), &[1, 3, h, w]);
    let data = t.squeeze(0).unwrap().to_vec3::<f32>().unwrap();
    let n = Normalization::IMAGENET;
    for y in 0..h {
        for x in 0..w {
            for c in 0..3 {
                let raw = rgb[(y * w + x) * 3 + c] as f32 / 255.0;
                let e = (raw - n.mean[c]) / n.std[c];
                assert!((data[c][y][x] - e).abs() < 1e-5);
            }
        }
    }
    let err = rgb8_to_tensor(&rgb[1..], h, w, &n, &DEV)
        .unwrap_err()
        .to_string();
    assert!(err.contains("needs 18"), "{err}");
    assert!(rgb8_to_tensor(&[], 0, 3, &n, &DEV).is_err());
    assert_eq!(size_for_multiple(376, 1241, 14), (378, 1246));
    assert_eq!(size_for_multiple(3, 5, 14), (14, 14));
    let r = resize_bilinear(&t, 4, 6).unwrap();
    assert_eq!(r.dims(), &[1, 3, 4, 6]);
    assert!(resize_bilinear(&t, 0, 6).is_err());
}

#[test]
fn differentiable_resize_matches_candle_bilinear() {
    let mut rng = ChaCha8Rng::seed_from_u64(11);
    let x = rand_t(&mut rng, &[2, 3, 5, 7], 1.0);
    for (h, w) in [(10, 14), (3, 4), (5, 13), (8, 7), (1, 1), (17, 2)] {
        let a = resize_bilinear(&x, h, w).unwrap();
        let b = resize_bilinear_differentiable(&x, h, w).unwrap();
        assert_eq!(a.dims(), b.dims());
        let d = max_abs_diff(&flat(&a), &flat(&b));
        assert!(d < 1e-5, "{h}x{w}: {d}");
    }
    // and it has a gradient
    let v = candle_core::Var::from_tensor(&x).unwrap();
    let y = resize_bilinear_differentiable(v.as_tensor(), 9, 9).unwrap();
    let g = y.sum_all().unwrap().backward().unwrap();
    let gx = flat(g.get(v.as_tensor()).unwrap());
    // every output pixel distributes weight 1 over the input: the gradient sums to B*C*9*9
    let total: f32 = gx.iter().sum();
    assert!((total - 2.0 * 3.0 * 81.0).abs() < 1e-3, "{total}");
}

#[test]
fn small_cnn_loss_combines_heads_and_rejects_missing_targets() {
    let mut rng = ChaCha8Rng::seed_from_u64(14);
    let cfg = SmallCnnConfig {
        channels: [8, 8, 8, 8],
        head_channels: 8,
        ..SmallCnnConfig::default()
    };
    let vm = VarMap::new();
    let model =
        SmallCnn::new(&cfg, veila_nn::seeded_var_builder(&vm, 5, DType::F32, &DEV)).unwrap();
    let img = rand_t(&mut rng, &[2, 3, 16, 24], 1.0);
    let labels = Tensor::from_vec(
        (0..2 * 16 * 24).map(|i| (i % 20) as u32).collect(),
        (2, 16, 24),
        &DEV,
    )
    .unwrap();
    let depth = Tensor::full(7.0f32, (2, 16, 24), &DEV).unwrap();
    let out = model.forward_all(&img).unwrap();
    let ce = semantic_cross_entropy(out.semantic_logits.as_ref().unwrap(), &labels, Some(0))
        .unwrap()
        .to_scalar::<f32>()
        .unwrap();
    let si = silog(out.log_depth.as_ref().unwrap(), &depth, 0.5)
        .unwrap()
        .to_scalar::<f32>()
        .unwrap();
    let lc = SmallCnnLossConfig {
        semantic_weight: 0.5,
        depth_weight: 2.0,
        depth_loss: DepthLoss::SiLog { lambda: 0.5 },
    };
    let l = model.loss(&img, Some(&labels), Some(&depth), &lc).unwrap();
    assert!((l.total.to_scalar::<f32>().unwrap() - (0.5 * ce + 2.0 * si)).abs() < 1e-5);
    assert_eq!(l.semantic, Some(ce));
    let only_depth = model.loss(&img, None, Some(&depth), &lc).unwrap();
    assert!(only_depth.semantic.is_none() && only_depth.depth.is_some());
    let err = model.loss(&img, None, None, &lc).unwrap_err().to_string();
    assert!(err.contains("no target"), "{err}");
}

/// A small CNN with a 10 m depth prior, built twice from the same (untrained) weights: with and
/// without the depth-feature channel.
fn small_cnn_pair(min_depth_m: f32, max_depth_m: f32) -> (SmallCnn, SmallCnn) {
    let cfg = SmallCnnConfig {
        channels: [8, 8, 8, 8],
        head_channels: 8,
        semantic_head: false,
        min_depth_m,
        max_depth_m,
        ..SmallCnnConfig::default()
    };
    let vm = VarMap::new();
    let off = SmallCnn::new(
        &cfg,
        veila_nn::seeded_var_builder(&vm, 11, DType::F32, &DEV),
    )
    .unwrap();
    let on_cfg = SmallCnnConfig {
        depth_features: true,
        ..cfg
    };
    let on = SmallCnn::new(&on_cfg, VarBuilder::from_varmap(&vm, DType::F32, &DEV)).unwrap();
    (off, on)
}

#[test]
fn depth_features_append_the_depth_heads_reading_to_every_map() {
    // a depth range wide enough that the clamp never bites (the untrained head reads 2-240 m)
    let (off, on) = small_cnn_pair(0.01, 1000.0);
    assert_eq!(on.channels(), [9; 4]);
    assert_eq!(off.channels(), [8; 4]);
    let (h, w) = (40usize, 72usize);
    let rgb: Vec<u8> = (0..h * w * 3).map(|i| (i * 53 % 251) as u8).collect();
    let x = rgb8_to_tensor(&rgb, h, w, &Normalization::IMAGENET, &DEV).unwrap();
    let plain = off.forward(&x).unwrap();
    let with = on.forward(&x).unwrap();
    let sizes = on.feature_sizes(h, w);
    for (i, (p, q)) in plain.iter().zip(&with).enumerate() {
        assert_eq!(q.dims(), &[1, 9, sizes[i].0, sizes[i].1]);
        // the backbone's channels are untouched
        let head = q.narrow(1, 0, 8).unwrap();
        assert_eq!(flat(&head), flat(p));
    }
    // the finest map's channel, brought to the image size by candle's own bilinear resize, is
    // the head's log-depth relative to the 10 m prior (the head upsamples the same map)
    let fine = with[0].narrow(1, 8, 1).unwrap();
    let up = resize_bilinear(&fine, h, w).unwrap();
    let log_depth = on.forward_all(&x).unwrap().log_depth.unwrap();
    let want = (log_depth - 10f64.ln()).unwrap();
    let diff = max_abs_diff(&flat(&up), &flat(&want));
    assert!(diff < 1e-5, "max difference {diff}");
    // on a 4 x 4 image every map is one pixel: the channel is ln(depth / prior) of the depth
    // predict_maps reports
    let x4 = rgb8_to_tensor(&rgb[..4 * 4 * 3], 4, 4, &Normalization::IMAGENET, &DEV).unwrap();
    let d = on.predict_maps(&x4).unwrap()[0].depth_m.clone().unwrap();
    for m in on.forward(&x4).unwrap() {
        let v = flat(&m.narrow(1, 8, 1).unwrap());
        assert_eq!(v.len(), 1);
        assert!(
            (v[0] - (d[0] / 10.0).ln()).abs() < 1e-5,
            "{} {}",
            v[0],
            d[0]
        );
    }
}

#[test]
fn depth_features_are_clamped_to_the_depth_range_and_need_the_depth_head() {
    // a lower clamp at the prior itself: the untrained head reads 2-240 m, partly below it
    let (_, on) = small_cnn_pair(10.0, 80.0);
    let (h, w) = (32usize, 64usize);
    let rgb: Vec<u8> = (0..h * w * 3).map(|i| (i * 29 % 251) as u8).collect();
    let x = rgb8_to_tensor(&rgb, h, w, &Normalization::IMAGENET, &DEV).unwrap();
    let v = flat(&on.forward(&x).unwrap()[0].narrow(1, 8, 1).unwrap());
    assert!(
        v.iter()
            .all(|&a| a.is_finite() && (0.0..=8f32.ln()).contains(&a)),
        "{v:?}"
    );
    assert!(v.contains(&0.0), "the clamp never bit: {v:?}");
    assert!(v.iter().any(|&a| a > 0.0), "{v:?}");
    // the switch needs the head it reads, and is written to JSON only when on
    let bad = SmallCnnConfig {
        depth_head: false,
        depth_features: true,
        ..SmallCnnConfig::default()
    };
    assert!(bad.validate().is_err());
    let json = serde_json::to_value(SmallCnnConfig::default()).unwrap();
    assert!(json.get("depth_features").is_none(), "{json}");
    let cfg = on.config().clone();
    let json = serde_json::to_value(&cfg).unwrap();
    assert_eq!(json["depth_features"], serde_json::Value::Bool(true));
    assert_eq!(serde_json::from_value::<SmallCnnConfig>(json).unwrap(), cfg);
}
