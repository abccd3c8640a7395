//! Model bundles (save, verified load, tamper detection) and the generation pipeline (seeding,
//! inpainting keeps what it is told to keep, multi-view runs) on a small randomly initialised bundle.

use std::collections::HashMap;

use candle_core::{DType, Device};
use candle_nn::VarMap;
use veila_diffusion::RepaintConfig;
use veila_diffusion::SamplerConfig;
use veila_diffusion::app::bundle::{
    Bundle, BundleConfig, DENOISER_FILE, DEPTH_FILE, MANIFEST_FILE, MEAN_FILE, Method,
    SEMANTIC_FILE, Variant,
};
use veila_diffusion::app::{
    BundleFit, CameraView, DenoiserTraining, GenerateOptions, Stage, TrainExample, fit_bundle,
    varmap_tensors,
};
use veila_geom::PinholeCamera;
use veila_geom::RangeImage;
use veila_nn::ConditioningConfig;
use veila_nn::encoders::small_cnn::SmallCnn;

const IH: usize = 64;
const IW: usize = 96;

fn small_config(variant: Variant) -> BundleConfig {
    let mut cfg = BundleConfig::cpu_default(variant);
    cfg.image_height = IH;
    cfg.image_width = IW;
    cfg.denoiser.sensor.rows = 8;
    cfg.denoiser.sensor.cols = 64;
    if let Some(c) = cfg.denoiser.conditioning.as_mut() {
        c.feature_sizes = ConditioningConfig::pyramid_sizes(IH, IW);
    }
    for e in [&mut cfg.semantic_encoder, &mut cfg.depth_encoder]
        .into_iter()
        .flatten()
    {
        let c = e.config.as_mut().unwrap();
        c.channels = [8, 8, 16, 16];
        c.head_channels = 8;
    }
    if let Some(c) = cfg.denoiser.conditioning.as_mut() {
        c.semantic_channels = vec![8, 8, 16, 16];
        c.depth_channels = vec![8, 8, 16, 16];
    }
    cfg.sampler = SamplerConfig::ddim(3, 0.0);
    cfg.sampler.guidance_scale = 1.5;
    cfg
}

fn save_random_bundle(dir: &std::path::Path, cfg: &BundleConfig, seed: u64) {
    let dev = Device::Cpu;
    let mut weights: HashMap<&str, HashMap<String, candle_core::Tensor>> = HashMap::new();
    for (file, c) in [
        (SEMANTIC_FILE, &cfg.semantic_encoder),
        (DEPTH_FILE, &cfg.depth_encoder),
    ] {
        if let Some(c) = c.as_ref().and_then(|e| e.small_cnn_config()) {
            let vm = VarMap::new();
            SmallCnn::new(c, veila_nn::seeded_var_builder(&vm, seed, DType::F32, &dev)).unwrap();
            weights.insert(file, varmap_tensors(&vm).unwrap());
        }
    }
    let vm = VarMap::new();
    veila_nn::Denoiser::new(
        &cfg.denoiser,
        veila_nn::seeded_var_builder(&vm, seed, DType::F32, &dev),
    )
    .unwrap();
    weights.insert(DENOISER_FILE, varmap_tensors(&vm).unwrap());
    Bundle::save(dir, cfg, &weights).unwrap();
}

fn camera() -> PinholeCamera {
    let k = [
        [60.0, 0.0, IW as f32 / 2.0, 0.0],
        [0.0, 60.0, IH as f32 / 2.0, 0.0],
        [0.0, 0.0, 1.0, 0.0],
    ];
    // LiDAR x forward, y left, z up -> camera x right, y down, z forward
    let cam_from_lidar = glam::Mat4::from_cols_array_2d(&[
        [0.0, 0.0, 1.0, 0.0],
        [-1.0, 0.0, 0.0, 0.0],
        [0.0, -1.0, 0.0, 0.0],
        [0.0, 0.0, 0.0, 1.0],
    ]);
    PinholeCamera::new(k, cam_from_lidar, IW as u32, IH as u32).unwrap()
}

fn image(seed: u8) -> Vec<u8> {
    (0..IH * IW * 3)
        .map(|i| ((i * 37 + seed as usize * 11) % 251) as u8)
        .collect()
}

fn opts(seed: u64, samples: usize) -> GenerateOptions {
    let mut sampler = SamplerConfig::ddim(3, 0.0);
    sampler.guidance_scale = 1.5;
    GenerateOptions {
        sampler,
        samples,
        seed,
        unconditional: false,
        residual_weight: 1.0,
    }
}

#[test]
fn bundle_round_trips_and_generation_is_seeded() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("b");
    let cfg = small_config(Variant::Full);
    save_random_bundle(&dir, &cfg, 3);
    let b = Bundle::from_dir(&dir, &Device::Cpu).unwrap();
    assert_eq!(b.config, cfg);
    let cam = camera();
    let img = image(1);
    let view = [CameraView {
        rgb: &img,
        camera: &cam,
    }];
    let a = b.generate(&view, &opts(7, 2), |_, _| {}).unwrap();
    let again = b.generate(&view, &opts(7, 2), |_, _| {}).unwrap();
    let other = b.generate(&view, &opts(8, 2), |_, _| {}).unwrap();
    assert_eq!(a.len(), 2);
    assert_eq!(a, again, "same seed, same scans");
    assert_ne!(a, other, "another seed, other scans");
    assert_ne!(a[0], a[1], "the samples of one call differ");
    assert!(a[0].range_m.iter().all(|r| r.is_finite() && *r >= 0.0));
    // a different image changes the encoder features (the conditioning branches of a freshly
    // initialised denoiser are zero-initialised, so its output does not depend on them yet)
    let img2 = image(9);
    let f1 = b.encode_views(&view).unwrap();
    let f2 = b
        .encode_views(&[CameraView {
            rgb: &img2,
            camera: &cam,
        }])
        .unwrap();
    let diff = (&f1.semantic.as_ref().unwrap()[0] - &f2.semantic.as_ref().unwrap()[0])
        .unwrap()
        .abs()
        .unwrap()
        .sum_all()
        .unwrap()
        .to_scalar::<f32>()
        .unwrap();
    assert!(diff > 0.0);
    // two views run on a model trained with one (no weight depends on the number of views)
    let two = [view[0], view[0]];
    let mv = b.generate(&two, &opts(7, 1), |_, _| {}).unwrap();
    assert_eq!(mv.len(), 1);
}

#[test]
fn tampered_or_incomplete_bundles_are_rejected_naming_the_file() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("b");
    save_random_bundle(&dir, &small_config(Variant::Full), 1);
    // flip one byte of the denoiser weights
    let p = dir.join(DENOISER_FILE);
    let mut bytes = std::fs::read(&p).unwrap();
    let last = bytes.len() - 1;
    bytes[last] ^= 1;
    std::fs::write(&p, bytes).unwrap();
    let e = Bundle::from_dir(&dir, &Device::Cpu)
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("sha256 mismatch") && e.contains(DENOISER_FILE),
        "{e}"
    );

    let dir2 = tmp.path().join("c");
    save_random_bundle(&dir2, &small_config(Variant::Full), 1);
    std::fs::remove_file(dir2.join(SEMANTIC_FILE)).unwrap();
    let e = Bundle::from_dir(&dir2, &Device::Cpu)
        .unwrap_err()
        .to_string();
    assert!(e.contains(SEMANTIC_FILE), "{e}");

    // a manifest that does not list a weight file
    let dir3 = tmp.path().join("d");
    save_random_bundle(&dir3, &small_config(Variant::Full), 1);
    let mp = dir3.join(MANIFEST_FILE);
    let text = std::fs::read_to_string(&mp).unwrap();
    let mut m: serde_json::Value = serde_json::from_str(&text).unwrap();
    m["files"].as_object_mut().unwrap().remove(DEPTH_FILE);
    std::fs::write(&mp, serde_json::to_string(&m).unwrap()).unwrap();
    let e = Bundle::from_dir(&dir3, &Device::Cpu)
        .unwrap_err()
        .to_string();
    assert!(e.contains("not listed in the manifest"), "{e}");
}

#[test]
fn inpainting_keeps_the_known_pixels_and_regenerates_the_rest() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("b");
    save_random_bundle(&dir, &small_config(Variant::Full), 5);
    let b = Bundle::from_dir(&dir, &Device::Cpu).unwrap();
    let (h, w) = b.grid();
    // a known scan: a 20 m cylinder with intensity 0.3, every pixel a return
    let known = full_scan(h, w, vec![20.0; h * w], vec![0.3; h * w], vec![true; h * w]);
    let mask: Vec<bool> = (0..h * w).map(|i| i % w < w / 2).collect();
    let cam = camera();
    let img = image(2);
    let out = b
        .inpaint(
            &[CameraView {
                rgb: &img,
                camera: &cam,
            }],
            &known,
            &mask,
            &opts(3, 1),
            &RepaintConfig::default(),
        )
        .unwrap();
    let s = &out[0];
    let enc = &b.config.encoding;
    let round_trip = enc.decode_range(enc.encode_range(20.0));
    let mut changed = 0;
    for i in 0..h * w {
        if mask[i] {
            assert!(s.mask[i], "kept pixel {i} lost its return");
            assert!(
                (s.range_m[i] - round_trip).abs() < 1e-3,
                "pixel {i}: {}",
                s.range_m[i]
            );
        } else if !s.mask[i] || (s.range_m[i] - 20.0).abs() > 0.5 {
            changed += 1;
        }
    }
    assert!(
        changed > (h * w) / 4,
        "only {changed} regenerated pixels differ"
    );
    // wrong mask size is an error, not a panic
    assert!(
        b.inpaint(
            &[CameraView {
                rgb: &img,
                camera: &cam
            }],
            &known,
            &mask[1..],
            &opts(3, 1),
            &RepaintConfig::default()
        )
        .is_err()
    );
}

#[test]
fn training_batches_are_a_pure_function_of_the_step_and_cover_each_epoch() {
    let cfg = small_config(Variant::Full);
    let dev = Device::Cpu;
    let vm = VarMap::new();
    let net = veila_nn::Denoiser::new(
        &cfg.denoiser,
        veila_nn::seeded_var_builder(&vm, 0, DType::F32, &dev),
    )
    .unwrap();
    let sem_vm = VarMap::new();
    let sem: veila_nn::encoders::kind::AnyEncoder = SmallCnn::new(
        cfg.semantic_encoder
            .as_ref()
            .unwrap()
            .small_cnn_config()
            .unwrap(),
        veila_nn::seeded_var_builder(&sem_vm, 0, DType::F32, &dev),
    )
    .unwrap()
    .into();
    let dep: veila_nn::encoders::kind::AnyEncoder = SmallCnn::new(
        cfg.depth_encoder
            .as_ref()
            .unwrap()
            .small_cnn_config()
            .unwrap(),
        veila_nn::seeded_var_builder(&sem_vm, 1, DType::F32, &dev),
    )
    .unwrap()
    .into();
    let (h, w) = (cfg.denoiser.height(), cfg.denoiser.width());
    let scan = full_scan(h, w, vec![10.0; h * w], vec![0.1; h * w], vec![true; h * w]);
    let x0 = cfg.encoding.encode_to_vec(&scan).unwrap();
    let examples: Vec<TrainExample> = (0..5)
        .map(|i| TrainExample {
            rgb: image(i),
            camera: camera(),
            x0: x0.clone(),
        })
        .collect();
    let data = DenoiserTraining::new(
        &cfg,
        Some(&sem),
        Some(&dep),
        &net,
        &examples,
        Stage::Denoiser,
        None,
        2,
        9,
        &dev,
    )
    .unwrap();
    let a: Vec<usize> = (0..5).flat_map(|s| data.indices(s)).collect();
    let b: Vec<usize> = (0..5).flat_map(|s| data.indices(s)).collect();
    assert_eq!(a, b);
    // steps 0..5 with batch 2 = 10 draws = two epochs of 5: each a permutation
    for epoch in a.chunks(5) {
        let mut e = epoch.to_vec();
        e.sort_unstable();
        assert_eq!(e, vec![0, 1, 2, 3, 4]);
    }
    let batch = data.batch(&net, 3).unwrap();
    assert_eq!(batch.x0.dims(), &[2, 3, h, w]);
    assert_eq!(batch.cond.unwrap().image.unwrap().batch(), 2);
    // a different camera in one run is refused
    let mut bad = examples.clone();
    bad[1].camera = camera().resized(IW as u32 / 2, IH as u32 / 2).unwrap();
    assert!(
        DenoiserTraining::new(
            &cfg,
            Some(&sem),
            Some(&dep),
            &net,
            &bad,
            Stage::Denoiser,
            None,
            2,
            9,
            &dev
        )
        .is_err()
    );
}

/// A structured scan of `h x w` pixels: ground rings (range growing towards the top rows), a
/// 6 m "car" over a quarter of the columns, a dropped band in the top row, intensity by range.
fn structured_scan(h: usize, w: usize) -> RangeImage {
    let mut range_m = vec![0.0; h * w];
    let mut intensity = vec![0.0; h * w];
    let mut mask = vec![true; h * w];
    for r in 0..h {
        for c in 0..w {
            let i = r * w + c;
            let ground = 4.0 + 40.0 / (1.0 + r as f32);
            let car = (w / 8..w / 8 + w / 4).contains(&c) && r >= h / 2;
            range_m[i] = if car { 6.0 } else { ground };
            intensity[i] = if car { 0.8 } else { 0.2 };
            if r == 0 && c % 3 == 0 {
                mask[i] = false;
                range_m[i] = 0.0;
                intensity[i] = 0.0;
            }
        }
    }
    full_scan(h, w, range_m, intensity, mask)
}

/// A range image of given buffers (no source points).
fn full_scan(
    h: usize,
    w: usize,
    range_m: Vec<f32>,
    intensity: Vec<f32>,
    mask: Vec<bool>,
) -> RangeImage {
    RangeImage {
        range_m,
        intensity,
        mask,
        ..RangeImage::new_empty(h as u32, w as u32)
    }
}

/// Mean absolute range error over the pixels where both scans have a return, and the share of
/// pixels whose return/drop decision differs.
fn range_mae(a: &RangeImage, b: &RangeImage) -> (f64, f64) {
    let (mut sum, mut n, mut flips) = (0.0, 0usize, 0usize);
    for i in 0..a.range_m.len() {
        if a.mask[i] && b.mask[i] {
            sum += f64::from((a.range_m[i] - b.range_m[i]).abs());
            n += 1;
        }
        if a.mask[i] != b.mask[i] {
            flips += 1;
        }
    }
    (sum / n.max(1) as f64, flips as f64 / a.range_m.len() as f64)
}

struct Quiet;
impl<M: veila_diffusion::Denoiser> veila_diffusion::TrainObserver<M> for Quiet {}

/// Trains `cfg` (with random frozen encoders) on one example for `steps` updates and returns the
/// bundle, read back through the verifying loader.
fn overfit_one(cfg: BundleConfig, scan: &RangeImage, steps: u64, dir: &std::path::Path) -> Bundle {
    let dev = Device::Cpu;
    let mut cfg = cfg;
    let (h, w) = (cfg.denoiser.height(), cfg.denoiser.width());
    assert_eq!((scan.rows as usize, scan.cols as usize), (h, w));
    let x0 = cfg.encoding.encode_to_vec(scan).unwrap();
    let examples = vec![TrainExample {
        rgb: image(4),
        camera: camera(),
        x0,
    }];
    let mut weights: HashMap<&str, HashMap<String, candle_core::Tensor>> = HashMap::new();
    let mut encoders = Vec::new();
    for (file, c) in [
        (SEMANTIC_FILE, cfg.semantic_encoder.clone()),
        (DEPTH_FILE, cfg.depth_encoder.clone()),
    ] {
        let Some(c) = c else {
            encoders.push(None);
            continue;
        };
        let vm = VarMap::new();
        let c = c.small_cnn_config().unwrap();
        let net = SmallCnn::new(c, veila_nn::seeded_var_builder(&vm, 1, DType::F32, &dev)).unwrap();
        weights.insert(file, varmap_tensors(&vm).unwrap());
        encoders.push(Some(veila_nn::encoders::kind::AnyEncoder::from(net)));
    }
    let tc = veila_diffusion::TrainConfig {
        seed: 0,
        lr: 3e-3,
        min_lr: 3e-4,
        warmup_steps: 10,
        total_steps: steps,
        ema_decay: 0.9,
        cond_drop_prob: 0.0,
        checkpoint_every: None,
        ..veila_diffusion::TrainConfig::default()
    };
    let out = fit_bundle(
        &mut cfg,
        BundleFit {
            semantic: encoders[0].as_ref(),
            depth: encoders[1].as_ref(),
            examples: &examples,
            batch_size: 4,
            train: &tc,
            mean_train: None,
            work_dir: &dir.join("work"),
            init: None,
            parallel: None,
        },
        &dev,
        |_, _, _| {},
        |_, _| Quiet,
    )
    .unwrap();
    if let Some(m) = out.mean {
        weights.insert(MEAN_FILE, m.ema_weights);
    }
    weights.insert(DENOISER_FILE, out.denoiser.unwrap().ema_weights);
    let bdir = dir.join("bundle");
    Bundle::save(&bdir, &cfg, &weights).unwrap();
    Bundle::from_dir(&bdir, &dev).unwrap()
}

fn generate_one(b: &Bundle, sampler: SamplerConfig, seed: u64) -> RangeImage {
    generate_weighted(b, sampler, seed, 1.0).unwrap()
}

fn generate_weighted(
    b: &Bundle,
    sampler: SamplerConfig,
    seed: u64,
    residual_weight: f64,
) -> veila_diffusion::Result<RangeImage> {
    let cam = camera();
    let img = image(4);
    let view = [CameraView {
        rgb: &img,
        camera: &cam,
    }];
    let o = GenerateOptions {
        sampler,
        samples: 1,
        seed,
        unconditional: false,
        residual_weight,
    };
    Ok(b.generate(&view, &o, |_, _| {})?.remove(0))
}

/// The small, fast version of the overfit check (the bundled-size one, for every method, is
/// `cargo xtask overfit`): a residual bundle trained on one scan gives that scan back, from its
/// mean network alone (0 steps) and with the residual diffusion on top. A defect anywhere in
/// encoding, loss weights, residual scaling, sampler or decoding shows up here as noise.
#[test]
fn a_residual_bundle_trained_on_one_scan_generates_it() {
    let tmp = tempfile::tempdir().unwrap();
    let cfg = small_config(Variant::Full).with_method(Method::Residual);
    let (h, w) = (cfg.denoiser.height(), cfg.denoiser.width());
    let scan = structured_scan(h, w);
    let b = overfit_one(cfg, &scan, 200, tmp.path());
    let r = b.config.residual.as_ref().unwrap();
    assert!(
        r.scale.iter().all(|s| *s > 0.0 && s.is_finite()),
        "{:?}",
        r.scale
    );
    assert!(b.mean.is_some());
    let mean = generate_one(&b, SamplerConfig::ddim(0, 0.0), 1);
    let mean_again = generate_one(&b, SamplerConfig::ddim(0, 0.0), 2);
    assert_eq!(mean, mean_again, "0 steps: the noise seed plays no part");
    let (mae, flips) = range_mae(&mean, &scan);
    eprintln!("mean network: range MAE {mae:.3} m, {flips:.3} ray-drop flips");
    assert!(mae < 0.6 && flips < 0.06, "mean: {mae} m, {flips} flips");
    let full = generate_one(&b, SamplerConfig::ddim(8, 0.0), 1);
    let (mae_full, flips_full) = range_mae(&full, &scan);
    eprintln!("mean + residual: range MAE {mae_full:.3} m, {flips_full:.3} ray-drop flips");
    assert!(
        mae_full < 1.0 && flips_full < 0.08,
        "mean + residual: {mae_full} m, {flips_full} flips"
    );
    assert_ne!(full, mean, "the residual diffusion adds something");
    // the residual weight: 0 is the mean network alone, 1 the full sample, and in between every
    // range lies between the two (the decoding is monotone in the range code)
    let ddim8 = || SamplerConfig::ddim(8, 0.0);
    assert_eq!(generate_weighted(&b, ddim8(), 1, 0.0).unwrap(), mean);
    assert_eq!(generate_weighted(&b, ddim8(), 1, 1.0).unwrap(), full);
    let half = generate_weighted(&b, ddim8(), 1, 0.5).unwrap();
    let mut between = 0;
    for i in 0..half.range_m.len() {
        if half.mask[i] && mean.mask[i] && full.mask[i] {
            let (lo, hi) = (
                mean.range_m[i].min(full.range_m[i]),
                mean.range_m[i].max(full.range_m[i]),
            );
            let r = half.range_m[i];
            assert!(
                r >= lo - 1e-3 && r <= hi + 1e-3,
                "pixel {i}: {r} not in [{lo}, {hi}]"
            );
            between += 1;
        }
    }
    assert!(
        between > half.range_m.len() / 2,
        "{between} pixels compared"
    );
    assert_ne!(half, mean);
    assert_ne!(half, full);
    for bad in [-0.1, 1.5, f64::NAN] {
        let err = generate_weighted(&b, ddim8(), 1, bad).unwrap_err();
        assert!(err.to_string().contains("residual_weight"), "{bad}: {err}");
    }
    // inpainting with a residual bundle: the kept pixels exactly as given, the rest regenerated
    let known = full_scan(h, w, vec![20.0; h * w], vec![0.3; h * w], vec![true; h * w]);
    let keep: Vec<bool> = (0..h * w).map(|i| i % w < w / 2).collect();
    let cam = camera();
    let img = image(4);
    let painted = b
        .inpaint(
            &[CameraView {
                rgb: &img,
                camera: &cam,
            }],
            &known,
            &keep,
            &GenerateOptions::new(SamplerConfig::ddim(8, 0.0)),
            &RepaintConfig::default(),
        )
        .unwrap()
        .remove(0);
    let enc = &b.config.encoding;
    let round_trip = enc.decode_range(enc.encode_range(20.0));
    let mut regenerated = 0;
    for i in 0..h * w {
        if keep[i] {
            assert!(painted.mask[i], "kept pixel {i} lost its return");
            assert_eq!(painted.range_m[i], round_trip, "kept pixel {i}");
        } else if painted.mask[i] && (painted.range_m[i] - 20.0).abs() > 0.5 {
            regenerated += 1;
        }
    }
    assert!(regenerated > h * w / 8, "{regenerated} regenerated pixels");
    // a residual bundle without its mean network is refused, naming the file
    std::fs::remove_file(tmp.path().join("bundle").join(MEAN_FILE)).unwrap();
    let err = Bundle::from_dir(&tmp.path().join("bundle"), &Device::Cpu).unwrap_err();
    assert!(err.to_string().contains(MEAN_FILE), "{err}");
}

/// Every method trains and samples through the same bundle pipeline (a few steps each: this
/// checks the plumbing, shapes and seeding; quality is `cargo xtask method-sweep`'s job).
#[test]
fn every_method_trains_and_generates_through_the_bundle_pipeline() {
    for method in [Method::Eps, Method::Flow, Method::Regression] {
        let tmp = tempfile::tempdir().unwrap();
        let cfg = small_config(Variant::Full).with_method(method);
        assert_eq!(cfg.method(), method);
        let (h, w) = (cfg.denoiser.height(), cfg.denoiser.width());
        let b = overfit_one(cfg, &structured_scan(h, w), 3, tmp.path());
        assert_eq!(b.config.method(), method);
        let a = generate_one(&b, SamplerConfig::ddim(3, 0.0), 1);
        let again = generate_one(&b, SamplerConfig::ddim(3, 0.0), 1);
        assert_eq!(a, again, "{method:?}: seeded");
        assert!(a.range_m.iter().all(|r| r.is_finite()), "{method:?}");
        assert_eq!((a.rows as usize, a.cols as usize), (h, w));
        // only residual bundles sample with 0 steps
        let o = GenerateOptions {
            sampler: SamplerConfig::ddim(0, 0.0),
            samples: 1,
            seed: 0,
            unconditional: false,
            residual_weight: 1.0,
        };
        let cam = camera();
        let img = image(4);
        let view = [CameraView {
            rgb: &img,
            camera: &cam,
        }];
        assert!(b.generate(&view, &o, |_, _| {}).is_err(), "{method:?}");
        // and only they have a residual to weight
        let err = generate_weighted(&b, SamplerConfig::ddim(3, 0.0), 1, 0.5).unwrap_err();
        assert!(
            err.to_string().contains("residual_weight"),
            "{method:?}: {err}"
        );
    }
}

/// Random SegFormer-b0 encoder weights in Hugging Face layout (`segformer.encoder.*`).
fn random_segformer_b0(path: &std::path::Path, seed: u64) {
    let vm = VarMap::new();
    veila_nn::encoders::mit::MitEncoder::new(
        &veila_nn::encoders::mit::MitConfig::mit_b0(),
        veila_nn::seeded_var_builder(&vm, seed, DType::F32, &Device::Cpu),
    )
    .unwrap();
    std::fs::create_dir_all(path.parent().unwrap()).unwrap();
    vm.save(path).unwrap();
}

#[test]
fn a_bundle_names_a_pretrained_encoder_by_kind() {
    use veila_diffusion::app::bundle::EncoderSpec;
    use veila_nn::encoders::kind::EncoderKind;
    let tmp = tempfile::tempdir().unwrap();
    let weights = tmp.path().join("weights/segformer-b0.safetensors");
    random_segformer_b0(&weights, 3);
    let sha = veila_diffusion::app::bundle::sha256_hex(&std::fs::read(&weights).unwrap());
    let mut cfg = small_config(Variant::Full);
    let depth = cfg.depth_encoder.clone();
    cfg.set_encoders(
        Some(EncoderSpec::pretrained(
            EncoderKind::SegFormer(0),
            "../weights/segformer-b0.safetensors".into(),
            Some(sha),
        )),
        depth,
    )
    .unwrap();
    let cc = cfg.denoiser.conditioning.as_ref().unwrap();
    assert_eq!(cc.semantic_channels, vec![32, 64, 160, 256]);
    assert_eq!(cc.feature_sizes[0], [IH / 4, IW / 4]);
    // the semantic weights are not a bundle file; the depth CNN's are
    assert_eq!(cfg.weight_files(), vec![DEPTH_FILE, DENOISER_FILE]);
    let dir = tmp.path().join("bundle");
    save_random_bundle(&dir, &cfg, 5);
    let json = std::fs::read_to_string(dir.join("bundle.json")).unwrap();
    assert!(
        json.contains("\"kind\": \"segformer-b0\"") && json.contains("veila-bundle/2"),
        "{json}"
    );

    let b = Bundle::from_dir(&dir, &Device::Cpu).unwrap();
    assert_eq!(
        b.semantic.as_ref().unwrap().kind(),
        EncoderKind::SegFormer(0)
    );
    let cam = camera();
    let rgb = image(1);
    let views = [CameraView {
        rgb: &rgb,
        camera: &cam,
    }];
    let a = b.generate(&views, &opts(4, 1), |_, _| {}).unwrap();
    assert!(a[0].range_m.iter().all(|v| v.is_finite()));
    // the pretrained encoder sees the image (a random denoiser's zero-initialised condition
    // paths would hide it in the scan)
    let rgb2 = image(9);
    let views2 = [CameraView {
        rgb: &rgb2,
        camera: &cam,
    }];
    let fa = b.encode_views(&views).unwrap().semantic.unwrap();
    let fc = b.encode_views(&views2).unwrap().semantic.unwrap();
    assert_eq!(fa[3].dims(), &[1, 256, IH / 32, IW / 32]);
    let d = (&fa[3] - &fc[3]).unwrap().abs().unwrap().sum_all().unwrap();
    assert!(d.to_scalar::<f32>().unwrap() > 0.0);
    // weights moved into the bundle folder are found there by file name
    std::fs::rename(&weights, dir.join("segformer-b0.safetensors")).unwrap();
    let moved = Bundle::from_dir(&dir, &Device::Cpu).unwrap();
    assert_eq!(
        moved.generate(&views, &opts(4, 1), |_, _| {}).unwrap()[0].range_m,
        a[0].range_m
    );
    // missing: which file, which encoder, where to get it and where to put it
    std::fs::remove_file(dir.join("segformer-b0.safetensors")).unwrap();
    let err = Bundle::from_dir(&dir, &Device::Cpu)
        .unwrap_err()
        .to_string();
    for want in [
        "semantic_encoder `segformer-b0`",
        "weights not found",
        "nvidia/segformer-b0-finetuned-cityscapes-1024-1024",
        "weights/segformer-b0.safetensors",
    ] {
        assert!(err.contains(want), "`{want}` missing from: {err}");
    }
    // another file than the bundle was made with
    random_segformer_b0(&weights, 4);
    let err = Bundle::from_dir(&dir, &Device::Cpu)
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("sha256") && err.contains("segformer-b0.safetensors"),
        "{err}"
    );
}

#[test]
fn version_1_bundles_with_bare_encoder_configs_still_load() {
    use veila_diffusion::app::bundle::EncoderSpec;
    let cfg = small_config(Variant::Full);
    let mut v = serde_json::to_value(&cfg).unwrap();
    // write it the way veila-bundle/1 did: the small CNN's config in place of the spec
    v["format"] = "veila-bundle/1".into();
    for field in ["semantic_encoder", "depth_encoder"] {
        let inner = v[field]["config"].clone();
        assert!(inner.is_object());
        v[field] = inner;
    }
    let old: BundleConfig = serde_json::from_value(v.clone()).unwrap();
    assert_eq!(old.semantic_encoder, cfg.semantic_encoder);
    assert!(matches!(
        old.depth_encoder,
        Some(EncoderSpec {
            config: Some(_),
            ..
        })
    ));
    // a spec with a kind is read strictly
    v["semantic_encoder"] = serde_json::json!({"kind": "segformer-b0", "weight": "x"});
    let err = serde_json::from_value::<BundleConfig>(v.clone())
        .unwrap_err()
        .to_string();
    assert!(err.contains("weight"), "{err}");
    v["semantic_encoder"] = serde_json::json!({"kind": "segformer-b9", "weights": "x"});
    let err = serde_json::from_value::<BundleConfig>(v)
        .unwrap_err()
        .to_string();
    assert!(err.contains("segformer-b9"), "{err}");
}
