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
    BundleFit, CameraView, DenoiserTraining, EncoderExample, ExampleSource, GenerateOptions, Stage,
    TrainExample, fit_bundle, varmap_tensors,
};
use veila_diffusion::trainer::Precision;
use veila_geom::PinholeCamera;
use veila_geom::RangeImage;
use veila_nn::ConditioningConfig;
use veila_nn::encoders::small_cnn::SmallCnn;

const IH: usize = 64;
const IW: usize = 96;

pub(crate) fn small_config(variant: Variant) -> BundleConfig {
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

pub(crate) fn camera() -> PinholeCamera {
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

pub(crate) fn image(seed: u8) -> Vec<u8> {
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
        .map(|i| {
            // distinct targets, to tell the examples apart in a batch
            TrainExample::new(
                image(i),
                camera(),
                x0.iter().map(|v| v + i as f32 * 0.01).collect(),
            )
        })
        .collect();
    // the denoiser's training data of `examples` under `cfg`, batch 2, seed 9
    let training = |cfg: &BundleConfig, examples: &[TrainExample]| {
        DenoiserTraining::new(
            cfg,
            Some(&sem),
            Some(&dep),
            &net,
            examples,
            Stage::Denoiser,
            None,
            2,
            9,
            &dev,
        )
        .unwrap()
    };
    let data = training(&cfg, &examples);
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
    // gradient accumulation: the two parts of the batch are its two examples, in order
    let parts: Vec<_> = (0..2)
        .map(|k| data.batch_part(&net, 3, k, 2).unwrap())
        .collect();
    for p in &parts {
        assert_eq!(p.x0.dims(), &[1, 3, h, w]);
        assert_eq!(p.cond.as_ref().unwrap().image.as_ref().unwrap().batch(), 1);
    }
    let joined = candle_core::Tensor::cat(&[&parts[0].x0, &parts[1].x0], 0).unwrap();
    assert_eq!(
        joined.flatten_all().unwrap().to_vec1::<f32>().unwrap(),
        batch.x0.flatten_all().unwrap().to_vec1::<f32>().unwrap()
    );
    assert!(
        data.batch_part(&net, 3, 0, 3).is_err(),
        "3 parts of a batch of 2"
    );
    assert_eq!(batch.cond.unwrap().image.unwrap().batch(), 2);
    assert!(
        batch.weight.is_none(),
        "the denoiser weighs every pixel alike by default"
    );
    // with a range weight, each batch carries its own examples' weights, in the batch's order
    let mut weighted = cfg.clone();
    weighted.range_weight = Some(1.0);
    let data_w = training(&weighted, &examples);
    let got = data_w
        .batch(&net, 3)
        .unwrap()
        .weight
        .expect("range weights");
    let want: Vec<f32> = data_w
        .indices(3)
        .iter()
        .flat_map(|&i| {
            veila_diffusion::app::mean::range_weight(&cfg.encoding, &examples[i].x0, h * w, 1.0)
        })
        .collect();
    assert_eq!(got.flatten_all().unwrap().to_vec1::<f32>().unwrap(), want);
    assert!(
        want.iter().any(|&v| v != 1.0),
        "the weights differ from 1 somewhere"
    );
    // examples of another rig train in the same run: the batches holding example 1 carry two
    // geometries, the others one
    let mut mixed = examples.clone();
    mixed[1].camera = second_camera();
    let data = training(&cfg, &mixed);
    let mut seen = [false; 2];
    for step in 0..5 {
        let idx = data.indices(step);
        let two = idx.contains(&1) && idx.iter().any(|&i| i != 1);
        let rigs = data
            .batch(&net, step)
            .unwrap()
            .cond
            .unwrap()
            .image
            .unwrap()
            .num_rigs();
        assert_eq!(rigs, if two { 2 } else { 1 }, "step {step}: {idx:?}");
        seen[usize::from(two)] = true;
    }
    assert_eq!(seen, [true, true]);
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
    overfit_one_accumulating(cfg, scan, steps, dir, 1)
}

/// [`overfit_one`] with every update's batch of 4 run in `parts` parts.
fn overfit_one_accumulating(
    cfg: BundleConfig,
    scan: &RangeImage,
    steps: u64,
    dir: &std::path::Path,
    parts: u64,
) -> Bundle {
    overfit_one_with(cfg, scan, steps, dir, parts, Precision::F32, None)
}

/// Stops the denoiser stage's training after update `at` (a checkpoint is written there).
struct StopDenoiserAt(Option<u64>);
impl<M: veila_diffusion::Denoiser> veila_diffusion::TrainObserver<M> for StopDenoiserAt {
    fn on_step(&mut self, s: &veila_diffusion::StepStats) -> std::ops::ControlFlow<()> {
        if self.0 == Some(s.step) {
            std::ops::ControlFlow::Break(())
        } else {
            std::ops::ControlFlow::Continue(())
        }
    }
}

/// [`overfit_one_accumulating`] in `precision`; `stop_at`: interrupt the denoiser's training
/// after that update and resume it from its checkpoint in a second call, as a user would.
fn overfit_one_with(
    cfg: BundleConfig,
    scan: &RangeImage,
    steps: u64,
    dir: &std::path::Path,
    parts: u64,
    precision: Precision,
    stop_at: Option<u64>,
) -> Bundle {
    let dev = Device::Cpu;
    let mut cfg = cfg;
    let (h, w) = (cfg.denoiser.height(), cfg.denoiser.width());
    assert_eq!((scan.rows as usize, scan.cols as usize), (h, w));
    let x0 = cfg.encoding.encode_to_vec(scan).unwrap();
    let examples = vec![TrainExample::new(image(4), camera(), x0)];
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
        grad_accum_steps: parts,
        precision,
        ..veila_diffusion::TrainConfig::default()
    };
    let fit = |cfg: &mut BundleConfig, stop: Option<u64>| {
        fit_bundle(
            cfg,
            BundleFit {
                semantic: encoders[0].as_ref(),
                depth: encoders[1].as_ref(),
                examples: (&examples).into(),
                batch_size: 4,
                train: &tc,
                mean_train: None,
                work_dir: &dir.join("work"),
                init: None,
                mean_init: None,
                parallel: None,
            },
            &dev,
            |_, _, _| {},
            |stage, _| StopDenoiserAt(stop.filter(|_| stage == Stage::Denoiser)),
        )
        .unwrap()
    };
    if stop_at.is_some() {
        let first = fit(&mut cfg, stop_at);
        let d = first.denoiser.expect("the denoiser stage ran");
        assert!(
            d.summary.stopped_early && Some(d.step) == stop_at,
            "interrupted"
        );
    }
    let out = fit(&mut cfg, None);
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
/// checks the plumbing, shapes and seeding; quality was measured by the method sweep, BENCHMARKS.md).
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

#[test]
fn gradient_accumulation_trains_a_conditional_bundle_to_the_same_weights() {
    // regression draws no noise and the batch of 4 repeats the one example, so 2 parts of 2
    // give the whole batch's gradient: the same weights up to float rounding (through the
    // conditioned parts of `DenoiserTraining::batch_part`)
    let cfg = small_config(Variant::Full).with_method(Method::Regression);
    let (h, w) = (cfg.denoiser.height(), cfg.denoiser.width());
    let scan = structured_scan(h, w);
    let weights = |parts: u64| {
        let tmp = tempfile::tempdir().unwrap();
        let b = overfit_one_accumulating(cfg.clone(), &scan, 3, tmp.path(), parts);
        let t = candle_core::safetensors::load(
            tmp.path().join("bundle").join(DENOISER_FILE),
            &Device::Cpu,
        )
        .unwrap();
        let mut names: Vec<_> = t.keys().cloned().collect();
        names.sort();
        drop(b);
        names
            .iter()
            .flat_map(|n| t[n].flatten_all().unwrap().to_vec1::<f32>().unwrap())
            .collect::<Vec<f32>>()
    };
    let (one, two) = (weights(1), weights(2));
    let diff = max_diff(&one, &two);
    assert!(diff < 1e-4, "max |diff| {diff}");
}

/// The denoiser's saved weights, flattened in name order.
fn denoiser_weights(bundle_dir: &std::path::Path) -> Vec<f32> {
    let t = candle_core::safetensors::load(bundle_dir.join(DENOISER_FILE), &Device::Cpu).unwrap();
    let mut names: Vec<_> = t.keys().cloned().collect();
    names.sort();
    names
        .iter()
        .flat_map(|n| {
            assert_eq!(t[n].dtype(), DType::F32, "{n}: saved as f32");
            t[n].flatten_all().unwrap().to_vec1::<f32>().unwrap()
        })
        .collect()
}

/// Mixed precision (bf16 activations on f32 master weights) trains the real network as f32
/// does: after the same updates from the same seeds its residual bundle reproduces its one scan
/// about as closely, and an interrupted bf16 run resumes from its checkpoint to the very weights
/// of an uninterrupted one. (bf16 on the CPU runs candle's reference ops, so this is kept short.)
#[test]
fn bf16_training_tracks_f32_and_resumes_exactly() {
    // enough updates for both networks to move well off their start (the mean network's range
    // MAE is 1.3-1.8 m after 30, 0.6 m after 80), few enough for CI: bf16 trains at a sixth of
    // f32's speed on the CPU, whose bf16 path is candle's reference ops
    const UPDATES: u64 = 30;
    let cfg = small_config(Variant::Full).with_method(Method::Residual);
    let (h, w) = (cfg.denoiser.height(), cfg.denoiser.width());
    let scan = structured_scan(h, w);
    let quality = |precision: Precision| {
        let tmp = tempfile::tempdir().unwrap();
        let b = overfit_one_with(cfg.clone(), &scan, UPDATES, tmp.path(), 1, precision, None);
        let mean = range_mae(&generate_one(&b, SamplerConfig::ddim(0, 0.0), 1), &scan);
        let full = range_mae(&generate_one(&b, SamplerConfig::ddim(8, 0.0), 1), &scan);
        eprintln!(
            "{precision:?}, {UPDATES} updates: mean network range MAE {:.3} m ({:.3} flips), with the \
             residual {:.3} m ({:.3} flips)",
            mean.0, mean.1, full.0, full.1
        );
        (mean, full, denoiser_weights(&tmp.path().join("bundle")))
    };
    let (mean32, full32, w32) = quality(Precision::F32);
    let (mean16, full16, w16) = quality(Precision::Bf16);
    assert_ne!(w32, w16, "the precision mattered");
    for (what, a, b) in [
        ("mean", mean16, mean32),
        ("mean + residual", full16, full32),
    ] {
        assert!(
            a.0.is_finite() && a.0 <= 1.25 * b.0 + 0.05,
            "{what}: bf16 {a:?} against f32 {b:?}"
        );
        assert!(a.1 <= b.1 + 0.03, "{what}: bf16 {a:?} against f32 {b:?}");
    }
    // exact resume: 4 updates straight against 2, a checkpoint, and 2 more in a second call
    let straight = tempfile::tempdir().unwrap();
    overfit_one_with(
        cfg.clone(),
        &scan,
        4,
        straight.path(),
        1,
        Precision::Bf16,
        None,
    );
    let resumed = tempfile::tempdir().unwrap();
    overfit_one_with(cfg, &scan, 4, resumed.path(), 1, Precision::Bf16, Some(2));
    assert_eq!(
        denoiser_weights(&straight.path().join("bundle")),
        denoiser_weights(&resumed.path().join("bundle")),
        "bf16 resume is exact"
    );
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

/// The name [`Bundle::save`] gives the semantic SegFormer-b0's weights inside a bundle.
const SEGFORMER_IN_BUNDLE: &str = "semantic_encoder.segformer-b0.safetensors";

/// A bundle at `tmp/bundle` whose semantic encoder is a random SegFormer-b0 given to
/// [`Bundle::save`] by the absolute path `tmp/weights/segformer-b0.safetensors`.
fn segformer_bundle(tmp: &std::path::Path) -> (BundleConfig, std::path::PathBuf) {
    use veila_diffusion::app::bundle::EncoderSpec;
    use veila_nn::encoders::kind::EncoderKind;
    let weights = tmp.join("weights/segformer-b0.safetensors");
    random_segformer_b0(&weights, 3);
    let sha = veila_diffusion::app::bundle::sha256_hex(&std::fs::read(&weights).unwrap());
    let mut cfg = small_config(Variant::Full);
    let depth = cfg.depth_encoder.clone();
    cfg.set_encoders(
        Some(EncoderSpec::pretrained(
            EncoderKind::SegFormer(0),
            weights.clone(),
            Some(sha),
        )),
        depth,
    )
    .unwrap();
    save_random_bundle(&tmp.join("bundle"), &cfg, 5);
    (cfg, weights)
}

#[test]
fn a_bundle_names_a_pretrained_encoder_by_kind() {
    use veila_nn::encoders::kind::EncoderKind;
    let tmp = tempfile::tempdir().unwrap();
    let (cfg, weights) = segformer_bundle(tmp.path());
    let cc = cfg.denoiser.conditioning.as_ref().unwrap();
    assert_eq!(cc.semantic_channels, vec![32, 64, 160, 256]);
    assert_eq!(cc.feature_sizes[0], [IH / 4, IW / 4]);
    // the semantic weights are not a bundle file; the depth CNN's are
    assert_eq!(cfg.weight_files(), vec![DEPTH_FILE, DENOISER_FILE]);
    let dir = tmp.path().join("bundle");
    let json = std::fs::read_to_string(dir.join("bundle.json")).unwrap();
    assert!(
        json.contains("\"kind\": \"segformer-b0\"") && json.contains("veila-bundle/2"),
        "{json}"
    );
    // the file given by an absolute path came into the bundle, and bundle.json names it there
    let v: serde_json::Value = serde_json::from_str(&json).unwrap();
    assert_eq!(v["semantic_encoder"]["weights"], SEGFORMER_IN_BUNDLE);
    assert_eq!(
        std::fs::read(dir.join(SEGFORMER_IN_BUNDLE)).unwrap(),
        std::fs::read(&weights).unwrap()
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
    // the bundle is whole without the file it was made from
    std::fs::remove_file(&weights).unwrap();
    let moved = Bundle::from_dir(&dir, &Device::Cpu).unwrap();
    assert_eq!(
        moved.generate(&views, &opts(4, 1), |_, _| {}).unwrap()[0].range_m,
        a[0].range_m
    );
    // missing: which file, which encoder, where to get it and where to put it
    std::fs::remove_file(dir.join(SEGFORMER_IN_BUNDLE)).unwrap();
    let err = Bundle::from_dir(&dir, &Device::Cpu)
        .unwrap_err()
        .to_string();
    for want in [
        "semantic_encoder `segformer-b0`",
        "weights not found",
        "nvidia/segformer-b0-finetuned-cityscapes-1024-1024",
        SEGFORMER_IN_BUNDLE,
    ] {
        assert!(err.contains(want), "`{want}` missing from: {err}");
    }
    // another file than the bundle was made with
    random_segformer_b0(&dir.join(SEGFORMER_IN_BUNDLE), 4);
    let err = Bundle::from_dir(&dir, &Device::Cpu)
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("sha256") && err.contains(SEGFORMER_IN_BUNDLE),
        "{err}"
    );
}

/// Sets `bundle.json`'s `semantic_encoder.weights` to `value` and re-records the file's sha256 in
/// the manifest (as a hostile publisher would).
fn set_semantic_weights(dir: &std::path::Path, value: &str) {
    let cp = dir.join("bundle.json");
    let mut c: serde_json::Value = serde_json::from_slice(&std::fs::read(&cp).unwrap()).unwrap();
    c["semantic_encoder"]["weights"] = value.into();
    let bytes = serde_json::to_vec_pretty(&c).unwrap();
    std::fs::write(&cp, &bytes).unwrap();
    let mp = dir.join(MANIFEST_FILE);
    let mut m: serde_json::Value = serde_json::from_slice(&std::fs::read(&mp).unwrap()).unwrap();
    m["files"]["bundle.json"] = veila_diffusion::app::bundle::sha256_hex(&bytes).into();
    std::fs::write(&mp, serde_json::to_vec_pretty(&m).unwrap()).unwrap();
}

/// Issue 58, case 4: a bundle's pretrained `weights` that is absolute, climbs out with `..` or
/// leads out through a link is refused naming the field and `bundle.json`, without the file
/// being hashed (the outside copy is the right file: followed, it would load); a nested path
/// inside loads; an absolute path is still served by a file of its name copied into the bundle.
#[test]
fn pretrained_weights_outside_the_bundle_are_refused_unread() {
    let tmp = tempfile::tempdir().unwrap();
    let (_, weights) = segformer_bundle(tmp.path());
    let dir = tmp.path().join("bundle");
    let outside = tmp.path().join("outside");
    std::fs::create_dir_all(&outside).unwrap();
    std::fs::rename(
        dir.join(SEGFORMER_IN_BUNDLE),
        outside.join("model.safetensors"),
    )
    .unwrap();
    std::fs::remove_file(&weights).unwrap();
    let refused = |value: &str, want: &str| {
        set_semantic_weights(&dir, value);
        let err = Bundle::from_dir(&dir, &Device::Cpu)
            .unwrap_err()
            .to_string();
        assert!(
            err.contains("bundle.json")
                && err.contains(&format!("semantic_encoder.weights `{value}`"))
                && err.contains(want)
                && err.contains("nothing read"),
            "{value}: {err}"
        );
        assert!(!err.contains("sha256"), "{value}: {err}");
    };
    let abs = outside.join("model.safetensors");
    refused(abs.to_str().unwrap(), "an absolute path");
    refused("../outside/model.safetensors", "climbs out");
    #[cfg(unix)]
    {
        std::os::unix::fs::symlink(&outside, dir.join("linked")).unwrap();
        refused(
            "linked/model.safetensors",
            "leads through the link `linked`",
        );
        std::fs::remove_file(dir.join("linked")).unwrap();
    }
    // a nested relative path inside the bundle loads
    std::fs::create_dir_all(dir.join("pretrained")).unwrap();
    std::fs::copy(&abs, dir.join("pretrained/b0.safetensors")).unwrap();
    set_semantic_weights(&dir, "pretrained/b0.safetensors");
    Bundle::from_dir(&dir, &Device::Cpu).unwrap();
    // an absolute path of an older bundle: a file of its name in the bundle serves, the outside
    // one is never read
    std::fs::rename(
        dir.join("pretrained/b0.safetensors"),
        dir.join("model.safetensors"),
    )
    .unwrap();
    random_segformer_b0(&abs, 9);
    set_semantic_weights(&dir, abs.to_str().unwrap());
    Bundle::from_dir(&dir, &Device::Cpu).unwrap();
}

/// A bundle's own file that is a link out of its folder is refused unread, even when what it
/// points to is the right file.
#[cfg(unix)]
#[test]
fn a_bundle_file_linked_out_of_the_folder_is_refused() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("bundle");
    save_random_bundle(&dir, &small_config(Variant::Full), 2);
    Bundle::from_dir(&dir, &Device::Cpu).unwrap();
    let outside = tmp.path().join("denoiser.safetensors");
    std::fs::rename(dir.join(DENOISER_FILE), &outside).unwrap();
    std::os::unix::fs::symlink(&outside, dir.join(DENOISER_FILE)).unwrap();
    let err = Bundle::from_dir(&dir, &Device::Cpu)
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("bundle file `denoiser.safetensors`")
            && err.contains("leads through the link `denoiser.safetensors`"),
        "{err}"
    );
    // a link that stays inside is followed
    std::fs::rename(&outside, dir.join("real-denoiser.safetensors")).unwrap();
    std::fs::remove_file(dir.join(DENOISER_FILE)).unwrap();
    std::os::unix::fs::symlink("real-denoiser.safetensors", dir.join(DENOISER_FILE)).unwrap();
    Bundle::from_dir(&dir, &Device::Cpu).unwrap();
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

/// Examples in memory behind the [`ExampleSource`] trait, with encoder targets, a read counter,
/// and optionally one unreadable example.
struct TestSource {
    examples: Vec<TrainExample>,
    fail_at: Option<usize>,
    reads: std::sync::atomic::AtomicUsize,
}

impl ExampleSource for TestSource {
    fn len(&self) -> usize {
        self.examples.len()
    }

    fn example(&self, index: usize) -> veila_diffusion::Result<TrainExample> {
        self.reads
            .fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        if self.fail_at == Some(index) {
            return Err(veila_diffusion::Error::Data(format!(
                "frame {index}: unreadable (test)"
            )));
        }
        Ok(self.examples[index].clone())
    }

    fn encoder_example(&self, index: usize) -> veila_diffusion::Result<EncoderExample> {
        Ok(encoder_example(&self.examples[index], index))
    }
}

fn encoder_example(ex: &TrainExample, index: usize) -> EncoderExample {
    EncoderExample {
        rgb: ex.rgb.clone(),
        camera: Some(ex.camera),
        labels: Some((0..IH * IW).map(|p| ((p + index) % 4) as u32).collect()),
        depth_m: (0..IH * IW).map(|p| ((p % 7) + index) as f32).collect(),
    }
}

/// A second rig: another focal length and principal point at the same image size.
fn second_camera() -> PinholeCamera {
    let k = [
        [45.0, 0.0, IW as f32 / 2.0 + 3.0, 0.0],
        [0.0, 45.0, IH as f32 / 2.0, 0.0],
        [0.0, 0.0, 1.0, 0.0],
    ];
    PinholeCamera::new(k, camera().cam_from_lidar, IW as u32, IH as u32).unwrap()
}

/// Five different examples of the small config's grid, 1 and 3 from [`second_camera`].
fn five_examples(cfg: &BundleConfig) -> Vec<TrainExample> {
    let (h, w) = (cfg.denoiser.height(), cfg.denoiser.width());
    (0..5)
        .map(|i| {
            let mut scan = structured_scan(h, w);
            for r in scan.range_m.iter_mut().filter(|r| **r > 0.0) {
                *r += i as f32 * 1.5;
            }
            TrainExample::new(
                image(i as u8 * 3),
                if i % 2 == 1 {
                    second_camera()
                } else {
                    camera()
                },
                cfg.encoding.encode_to_vec(&scan).unwrap(),
            )
        })
        .collect()
}

/// The small config's two encoders, seeded (1).
fn seeded_encoders(cfg: &BundleConfig) -> Vec<veila_nn::encoders::kind::AnyEncoder> {
    [
        cfg.semantic_encoder.clone().unwrap(),
        cfg.depth_encoder.clone().unwrap(),
    ]
    .iter()
    .map(|e| {
        let vm = VarMap::new();
        SmallCnn::new(
            e.small_cnn_config().unwrap(),
            veila_nn::seeded_var_builder(&vm, 1, DType::F32, &Device::Cpu),
        )
        .unwrap()
        .into()
    })
    .collect()
}

/// Stops a run after update `at`.
struct StopAt(u64);
impl<M: veila_diffusion::Denoiser> veila_diffusion::TrainObserver<M> for StopAt {
    fn on_step(&mut self, stats: &veila_diffusion::StepStats) -> std::ops::ControlFlow<()> {
        if stats.step >= self.0 {
            std::ops::ControlFlow::Break(())
        } else {
            std::ops::ControlFlow::Continue(())
        }
    }
}

/// Fits the residual small config (seeded random encoders) for 3 updates of each network at
/// batch 2; with `stop_denoiser_at`, the denoiser's run stops there. Returns the mean network's
/// and the denoiser's EMA weights (flattened in name order) and the residual scale.
fn fit_small(
    examples: veila_diffusion::app::Examples<'_>,
    dir: &std::path::Path,
    stop_denoiser_at: Option<u64>,
) -> veila_diffusion::Result<(Vec<f32>, Vec<f32>, Vec<f32>)> {
    let dev = Device::Cpu;
    let mut cfg = small_config(Variant::Full).with_method(Method::Residual);
    let encoders = seeded_encoders(&cfg);
    let tc = veila_diffusion::TrainConfig {
        lr: 3e-3,
        warmup_steps: 1,
        total_steps: 3,
        ema_decay: 0.5,
        checkpoint_every: None,
        ..veila_diffusion::TrainConfig::default()
    };
    let out = fit_bundle(
        &mut cfg,
        BundleFit {
            semantic: Some(&encoders[0]),
            depth: Some(&encoders[1]),
            examples,
            batch_size: 2,
            train: &tc,
            mean_train: None,
            work_dir: dir,
            init: None,
            mean_init: None,
            parallel: None,
        },
        &dev,
        |_, _, _| {},
        |stage, _| {
            StopAt(match (stage, stop_denoiser_at) {
                (Stage::Denoiser, Some(k)) => k,
                _ => u64::MAX,
            })
        },
    )?;
    let flat = |w: &HashMap<String, candle_core::Tensor>| -> Vec<f32> {
        let mut names: Vec<&String> = w.keys().collect();
        names.sort();
        names
            .into_iter()
            .flat_map(|n| w[n].flatten_all().unwrap().to_vec1::<f32>().unwrap())
            .collect()
    };
    let mean = flat(&out.mean.unwrap().ema_weights);
    let den = flat(&out.denoiser.unwrap().ema_weights);
    Ok((mean, den, cfg.residual.unwrap().scale))
}

#[test]
fn fine_tuning_a_residual_bundle_starts_both_networks_from_its_weights() {
    let dev = Device::Cpu;
    let mut cfg = small_config(Variant::Full).with_method(Method::Residual);
    let examples = five_examples(&cfg);
    let seeded = |c: &veila_nn::DenoiserConfig, seed: u64| {
        let vm = VarMap::new();
        veila_nn::Denoiser::new(c, veila_nn::seeded_var_builder(&vm, seed, DType::F32, &dev))
            .unwrap();
        varmap_tensors(&vm).unwrap()
    };
    let den = seeded(&cfg.denoiser, 40);
    let mean = seeded(&cfg.residual.as_ref().unwrap().mean_net, 41);
    let encoders = seeded_encoders(&cfg);
    let tc = veila_diffusion::TrainConfig {
        total_steps: 1,
        warmup_steps: 1,
        lr: 1e-9,
        ema_decay: 0.0,
        checkpoint_every: None,
        ..veila_diffusion::TrainConfig::default()
    };
    let tmp = tempfile::tempdir().unwrap();
    let out = fit_bundle(
        &mut cfg,
        BundleFit {
            semantic: Some(&encoders[0]),
            depth: Some(&encoders[1]),
            examples: (&examples).into(),
            batch_size: 2,
            train: &tc,
            mean_train: None,
            work_dir: tmp.path(),
            init: Some(&den),
            mean_init: Some(&mean),
            parallel: None,
        },
        &dev,
        |_, _, _| {},
        |_, _| Quiet,
    )
    .unwrap();
    let m = out.mean.unwrap();
    assert_eq!(m.initialised, mean.len());
    assert_eq!(out.denoiser.unwrap().initialised, den.len());
    // one update at a learning rate of 1e-9 leaves the given weights (not a seeded init)
    for (name, t) in &mean {
        let got = m.ema_weights[name]
            .flatten_all()
            .unwrap()
            .to_vec1::<f32>()
            .unwrap();
        let want = t.flatten_all().unwrap().to_vec1::<f32>().unwrap();
        assert!(max_diff(&got, &want) < 1e-6, "{name}");
    }
}

fn max_diff(a: &[f32], b: &[f32]) -> f32 {
    assert_eq!(a.len(), b.len());
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs())
        .fold(0f32, f32::max)
}

#[test]
fn streamed_training_matches_training_in_memory_and_resumes_exactly() {
    let cfg = small_config(Variant::Full).with_method(Method::Residual);
    let examples = five_examples(&cfg);
    let source = std::sync::Arc::new(TestSource {
        examples: examples.clone(),
        fail_at: None,
        reads: Default::default(),
    });
    let dyn_source: std::sync::Arc<dyn ExampleSource> = source.clone();
    let stream = veila_diffusion::app::Examples::Stream {
        source: &dyn_source,
        prefetch: 2,
    };
    let tmp = tempfile::tempdir().unwrap();
    let memory = fit_small((&examples).into(), &tmp.path().join("memory"), None).unwrap();
    let streamed = fit_small(stream, &tmp.path().join("stream"), None).unwrap();
    // the mean network (from the seeded initialisation) moved
    let init = fit_small((&examples).into(), &tmp.path().join("memory"), None).unwrap();
    assert_eq!(init, memory, "a finished run reruns to the same weights");
    assert!(source.reads.load(std::sync::atomic::Ordering::Relaxed) > 0);
    // the same batches (`streamed_batches_equal_the_batches_in_memory`): the same weights up to
    // float rounding. The mean predictions run in other batch sizes, which changes their last
    // bits, and Adam's first updates move a weight by about the learning rate whatever its
    // gradient's size, so the denoiser's tolerance is a tenth of one update (3e-3)
    assert!(
        max_diff(&memory.0, &streamed.0) < 1e-5,
        "mean network {}",
        max_diff(&memory.0, &streamed.0)
    );
    assert!(
        max_diff(&memory.1, &streamed.1) < 3e-4,
        "denoiser {}",
        max_diff(&memory.1, &streamed.1)
    );
    assert!(
        max_diff(&memory.2, &streamed.2) < 1e-5,
        "scale {:?} {:?}",
        memory.2,
        streamed.2
    );
    // stopped after the denoiser's first update and run again: the loader restarts at the
    // resumed update, and the weights are those of the uninterrupted run
    let dir = tmp.path().join("stream-resumed");
    fit_small(stream, &dir, Some(1)).unwrap();
    let resumed = fit_small(stream, &dir, None).unwrap();
    assert_eq!(resumed, streamed);
}

#[test]
fn a_failing_read_stops_streamed_training_with_its_error() {
    let cfg = small_config(Variant::Full).with_method(Method::Residual);
    let source: std::sync::Arc<dyn ExampleSource> = std::sync::Arc::new(TestSource {
        examples: five_examples(&cfg),
        fail_at: Some(3),
        reads: Default::default(),
    });
    let tmp = tempfile::tempdir().unwrap();
    let err = fit_small(
        veila_diffusion::app::Examples::Stream {
            source: &source,
            prefetch: 3,
        },
        tmp.path(),
        None,
    )
    .unwrap_err();
    assert!(err.to_string().contains("frame 3: unreadable"), "{err}");
}

/// Five examples' encoder targets, in memory and as a streamed source.
struct EncoderFixture {
    images: Vec<Vec<u8>>,
    labels: Vec<Vec<u32>>,
    depth: Vec<Vec<f32>>,
    cameras: Vec<PinholeCamera>,
    source: std::sync::Arc<dyn ExampleSource>,
}

impl EncoderFixture {
    fn new(cfg: &BundleConfig) -> Self {
        let examples = five_examples(cfg);
        let targets: Vec<EncoderExample> = examples
            .iter()
            .enumerate()
            .map(|(i, e)| encoder_example(e, i))
            .collect();
        Self {
            images: targets.iter().map(|t| t.rgb.clone()).collect(),
            labels: targets.iter().map(|t| t.labels.clone().unwrap()).collect(),
            depth: targets.iter().map(|t| t.depth_m.clone()).collect(),
            cameras: examples.iter().map(|e| e.camera).collect(),
            source: std::sync::Arc::new(TestSource {
                examples,
                fail_at: None,
                reads: Default::default(),
            }),
        }
    }

    /// The in-memory data, with or without the cameras.
    fn memory(&self, cameras: bool) -> veila_diffusion::app::EncoderData<'_> {
        veila_diffusion::app::EncoderData::Memory {
            images: &self.images,
            labels: Some(&self.labels),
            depth_m: &self.depth,
            cameras: cameras.then_some(self.cameras.as_slice()),
        }
    }
}

/// Recipe settings of the encoder tests (one denoiser step; only the encoders train).
fn encoder_settings(
    encoder_steps: usize,
    encoder_augment: Option<veila_diffusion::app::EncoderAugment>,
) -> veila_diffusion::app::RecipeSettings {
    veila_diffusion::app::RecipeSettings {
        seed: 3,
        steps: 1,
        mean_steps: None,
        batch: 2,
        lr: 1e-3,
        ema_decay: 0.9,
        cond_drop_prob: 0.1,
        checkpoint_every: 1,
        keep_checkpoints: 1,
        encoder_steps,
        encoder_batch: 2,
        encoder_lr: 1e-3,
        grad_accum_steps: 1,
        encoder_augment,
        precision: Precision::F32,
        activation_checkpointing: veila_diffusion::ActivationCheckpointing::None,
    }
}

/// Trains `cfg`'s encoders on `data` in `dir` and returns every weight, by file and name, sorted.
fn trained_encoder_weights(
    cfg: &BundleConfig,
    settings: &veila_diffusion::app::RecipeSettings,
    data: veila_diffusion::app::EncoderData<'_>,
    dir: &std::path::Path,
) -> veila_diffusion::Result<Vec<(String, Vec<f32>)>> {
    let e = veila_diffusion::app::prepare_encoders(
        cfg,
        veila_diffusion::app::EncoderSource::Train { data, dir },
        settings,
        &Device::Cpu,
        |_| {},
    )?;
    let mut all: Vec<(String, Vec<f32>)> = e
        .weights
        .iter()
        .flat_map(|(file, w)| {
            w.iter().map(move |(n, t)| {
                (
                    format!("{file}/{n}"),
                    t.flatten_all().unwrap().to_vec1::<f32>().unwrap(),
                )
            })
        })
        .collect();
    all.sort_by(|a, b| a.0.cmp(&b.0));
    Ok(all)
}

/// Encoder files a training run finds in its folder are read with a bundle's checks (issue 58):
/// finite, within `MAX_ABS_WEIGHT`, of a float dtype, a regular file under the cap.
#[test]
fn reused_encoder_files_are_checked_as_a_bundles_are() {
    use veila_diffusion::app::{EncoderData, EncoderSource, prepare_encoders};
    let cfg = small_config(Variant::Full);
    let data = EncoderFixture::new(&cfg);
    let settings = encoder_settings(1, None);
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("encoders");
    std::fs::create_dir_all(&dir).unwrap();
    let mut saved = HashMap::new();
    for (file, spec) in [
        (SEMANTIC_FILE, &cfg.semantic_encoder),
        (DEPTH_FILE, &cfg.depth_encoder),
    ] {
        let vm = VarMap::new();
        let c = spec.as_ref().unwrap().small_cnn_config().unwrap();
        SmallCnn::new(
            c,
            veila_nn::seeded_var_builder(&vm, 9, DType::F32, &Device::Cpu),
        )
        .unwrap();
        let t = varmap_tensors(&vm).unwrap();
        let p = dir.join(file);
        std::fs::write(&p, veila_nn::checkpoint::safetensors_bytes(&t, &p).unwrap()).unwrap();
        saved.insert(file, t);
    }
    let prepare = |data: EncoderData<'_>| {
        prepare_encoders(
            &cfg,
            EncoderSource::Train { data, dir: &dir },
            &settings,
            &Device::Cpu,
            |_| {},
        )
    };
    // the files are reused as they are
    let e = prepare(data.memory(true)).unwrap();
    let name = saved[SEMANTIC_FILE].keys().min().unwrap().clone();
    let got = e.weights[SEMANTIC_FILE][&name].flatten_all().unwrap();
    let want = saved[SEMANTIC_FILE][&name].flatten_all().unwrap();
    assert_eq!(
        got.to_vec1::<f32>().unwrap(),
        want.to_vec1::<f32>().unwrap()
    );
    // a NaN or a 3e38 weight is refused naming the file and the tensor
    let p = dir.join(SEMANTIC_FILE);
    for (v, word) in [(f64::NAN, "must be finite"), (3e38, "beyond the limit")] {
        let mut t = saved[SEMANTIC_FILE].clone();
        let w = t.get_mut(&name).unwrap();
        *w = (w.ones_like().unwrap() * v).unwrap();
        candle_core::safetensors::save(&t, &p).unwrap();
        let m = prepare(data.memory(true)).unwrap_err().to_string();
        assert!(
            m.contains(SEMANTIC_FILE) && m.contains(&name) && m.contains(word),
            "{m}"
        );
    }
    // a link to /dev/zero is refused unread
    #[cfg(unix)]
    {
        std::fs::remove_file(&p).unwrap();
        std::os::unix::fs::symlink("/dev/zero", &p).unwrap();
        let t0 = std::time::Instant::now();
        let m = prepare(data.memory(true)).unwrap_err().to_string();
        assert!(
            m.contains(SEMANTIC_FILE) && m.contains("regular file"),
            "{m}"
        );
        assert!(t0.elapsed().as_secs() < 5);
    }
}

/// Pretrained encoder weights are read only when they are a regular file under the cap, checked
/// before anything is read (a 5 GB file was read whole, a link to /dev/zero until memory ran out).
#[test]
fn pretrained_weights_are_capped_before_reading() {
    use veila_diffusion::app::bundle::EncoderSpec;
    use veila_nn::encoders::kind::EncoderKind;
    let tmp = tempfile::tempdir().unwrap();
    let spec = EncoderSpec::pretrained(EncoderKind::SegFormer(0), "w.safetensors".into(), None);
    let big = tmp.path().join("w.safetensors");
    std::fs::File::create(&big)
        .unwrap()
        .set_len(veila_nn::checkpoint::MAX_WEIGHTS_FILE_BYTES + 1)
        .unwrap();
    let t0 = std::time::Instant::now();
    let m = spec
        .load_at(&big, "semantic_encoder", &Device::Cpu)
        .unwrap_err()
        .to_string();
    assert!(
        m.contains("w.safetensors") && m.contains("more than the cap"),
        "{m}"
    );
    #[cfg(unix)]
    {
        let zero = tmp.path().join("zero.safetensors");
        std::os::unix::fs::symlink("/dev/zero", &zero).unwrap();
        let m = spec
            .load_at(&zero, "semantic_encoder", &Device::Cpu)
            .unwrap_err()
            .to_string();
        assert!(
            m.contains("zero.safetensors") && m.contains("regular file"),
            "{m}"
        );
    }
    assert!(t0.elapsed().as_secs() < 5, "{:?}", t0.elapsed());
    // the training config's `[model] semantic_weights` is read the same way
    let cfg_path = tmp.path().join("train.toml");
    let mut file: veila_diffusion::app::train_config::TrainFile =
        serde_json::from_value(serde_json::json!({
            "data": {"shards": "s"},
            "model": {"semantic_encoder": "segformer-b0", "semantic_weights": "w.safetensors"},
            "output": {"dir": "out"},
        }))
        .unwrap();
    file.resolve_and_check(&cfg_path).unwrap();
    let m = file.bundle_config(&cfg_path).unwrap_err().to_string();
    assert!(
        m.contains("train.toml") && m.contains("w.safetensors") && m.contains("more than the cap"),
        "{m}"
    );
}

#[test]
fn encoders_train_to_the_same_weights_from_a_source() {
    let cfg = small_config(Variant::Full);
    let data = EncoderFixture::new(&cfg);
    let settings = encoder_settings(3, None);
    let tmp = tempfile::tempdir().unwrap();
    let weights =
        |d, dir: &str| trained_encoder_weights(&cfg, &settings, d, &tmp.path().join(dir)).unwrap();
    let memory = weights(data.memory(true), "memory");
    let streamed = weights(
        veila_diffusion::app::EncoderData::Stream(&data.source),
        "stream",
    );
    assert_eq!(memory.len(), streamed.len());
    assert!(!memory.is_empty());
    assert_eq!(memory, streamed);
}

#[test]
fn streamed_batches_equal_the_batches_in_memory() {
    use veila_diffusion::Denoiser as _;
    let dev = Device::Cpu;
    let mut cfg = small_config(Variant::Full).with_method(Method::Residual);
    cfg.residual.as_mut().unwrap().scale = vec![0.1, 0.2, 0.3];
    let examples = five_examples(&cfg);
    let source: std::sync::Arc<dyn ExampleSource> = std::sync::Arc::new(TestSource {
        examples: examples.clone(),
        fail_at: None,
        reads: Default::default(),
    });
    let enc =
        |spec: &veila_diffusion::app::bundle::EncoderSpec| -> veila_nn::encoders::kind::AnyEncoder {
            let vm = VarMap::new();
            SmallCnn::new(
                spec.small_cnn_config().unwrap(),
                veila_nn::seeded_var_builder(&vm, 2, DType::F32, &dev),
            )
            .unwrap()
            .into()
        };
    let (sem, dep) = (
        enc(cfg.semantic_encoder.as_ref().unwrap()),
        enc(cfg.depth_encoder.as_ref().unwrap()),
    );
    let seeded = |c: &veila_nn::DenoiserConfig, seed: u64| {
        let vm = VarMap::new();
        let net =
            veila_nn::Denoiser::new(c, veila_nn::seeded_var_builder(&vm, seed, DType::F32, &dev))
                .unwrap();
        (net, varmap_tensors(&vm).unwrap())
    };
    let (_, mean_weights) = seeded(&cfg.residual.as_ref().unwrap().mean_net, 4);
    let (net, _) = seeded(&cfg.denoiser, 5);
    let means = veila_diffusion::app::predict_means(
        &cfg,
        Some(&sem),
        Some(&dep),
        &mean_weights,
        &examples,
        2,
        &dev,
    )
    .unwrap();
    let (b, c, h, w) = (
        3,
        cfg.channels(),
        cfg.denoiser.height(),
        cfg.denoiser.width(),
    );
    let t = candle_core::Tensor::new(&[0.3f32, 0.6, 0.9][..b], &dev).unwrap();
    let x = candle_core::Tensor::ones((b, c, h, w), DType::F32, &dev).unwrap();
    for stage in [Stage::Mean, Stage::Denoiser] {
        let (net, mw) = match stage {
            Stage::Mean => (seeded(&cfg.residual.as_ref().unwrap().mean_net, 6).0, None),
            Stage::Denoiser => (net.clone(), Some(&mean_weights)),
        };
        let memory = DenoiserTraining::new(
            &cfg,
            Some(&sem),
            Some(&dep),
            &net,
            &examples,
            stage,
            (stage == Stage::Denoiser).then_some(&means[..]),
            3,
            7,
            &dev,
        )
        .unwrap();
        let stream = DenoiserTraining::streaming(
            &cfg,
            Some(&sem),
            Some(&dep),
            &net,
            source.clone(),
            stage,
            mw,
            3,
            7,
            2,
            &dev,
        )
        .unwrap();
        let model = veila_diffusion::app::VeilaDenoiser::new(net.clone());
        // steps out of order (a jump restarts the loader), and the parts of one step
        for step in [0u64, 1, 2, 5, 3] {
            let (m, s) = (
                memory.batch(&net, step).unwrap(),
                stream.batch(&net, step).unwrap(),
            );
            let v = |t: &candle_core::Tensor| t.flatten_all().unwrap().to_vec1::<f32>().unwrap();
            assert!(
                // residual targets divide the means' rounding (other batch sizes) by the scale
                max_diff(&v(&m.x0), &v(&s.x0)) < 1e-4,
                "{stage:?} step {step}: targets {}",
                max_diff(&v(&m.x0), &v(&s.x0))
            );
            assert_eq!(
                m.weight.as_ref().map(v),
                s.weight.as_ref().map(v),
                "{stage:?} step {step}"
            );
            let (mc, sc) = (m.cond.unwrap(), s.cond.unwrap());
            match (&mc.mean, &sc.mean) {
                (Some(a), Some(b)) => assert!(
                    max_diff(&v(a), &v(b)) < 1e-5,
                    "{stage:?} step {step}: means"
                ),
                (None, None) => assert_eq!(stage, Stage::Mean),
                _ => panic!("{stage:?} step {step}: one batch has a mean, the other not"),
            }
            let (om, os) = (
                model.forward(&x, &t, Some(&mc)).unwrap(),
                model.forward(&x, &t, Some(&sc)).unwrap(),
            );
            assert!(
                max_diff(&v(&om), &v(&os)) < 1e-4,
                "{stage:?} step {step}: conditioned output"
            );
            for part in 0..2 {
                let (mp, sp) = (
                    memory.batch_part(&net, step, part, 2).unwrap(),
                    stream.batch_part(&net, step, part, 2).unwrap(),
                );
                assert!(
                    max_diff(&v(&mp.x0), &v(&sp.x0)) < 1e-5,
                    "{stage:?} step {step} part {part}"
                );
            }
        }
    }
}

#[test]
fn each_method_samples_by_default_where_its_texture_forms() {
    use veila_diffusion::Spacing;
    use veila_diffusion::sampler::SamplerKind;
    for v in [Variant::Full, Variant::Unconditional] {
        // direct diffusion: steps uniform in log-SNR, whose last ones visit the clean levels
        for m in [Method::Eps, Method::V] {
            let s = BundleConfig::cpu_default(v).with_method(m).sampler;
            assert_eq!(
                (s.kind, s.steps, s.spacing),
                (SamplerKind::DpmSolverPp2M, 16, Spacing::LogSnr),
                "{} {}",
                v.name(),
                m.name()
            );
            let process =
                veila_diffusion::Diffusion::new(BundleConfig::cpu_default(v).diffusion).unwrap();
            let sampler = veila_diffusion::sampler::Sampler::new(&process, s).unwrap();
            let t_last = sampler.levels().last().unwrap().t;
            assert!(t_last < 0.01, "{}: the last call at t = {t_last}", m.name());
        }
        // the residual's: the frontier rule's 16 DDPM steps (BENCHMARKS.md)
        let s = BundleConfig::cpu_default(v)
            .with_method(Method::Residual)
            .sampler;
        assert!(matches!(s.kind, SamplerKind::Ddpm { .. }));
        assert_eq!(
            (s.steps, s.spacing, s.guidance_scale),
            (16, Spacing::Trailing, 1.0)
        );
    }
}

#[test]
fn variants_parse_by_name_and_three_cameras_trains_and_generates_with_three_views() {
    for v in Variant::ALL {
        assert_eq!(v.name().parse::<Variant>().unwrap(), v);
        let cfg = BundleConfig::cpu_default(v).with_method(Method::Residual);
        let views = |c: &veila_nn::DenoiserConfig| c.conditioning.as_ref().map(|c| c.num_views);
        let want = (v != Variant::Unconditional).then_some(v.views());
        assert_eq!(views(&cfg.denoiser), want, "{}", v.name());
        assert_eq!(
            views(&cfg.residual.as_ref().unwrap().mean_net),
            want,
            "{}",
            v.name()
        );
    }
    assert!("four-cameras".parse::<Variant>().is_err());
    // a three-camera model on examples with two further cameras
    let dev = Device::Cpu;
    let mut cfg = small_config(Variant::ThreeCameras).with_method(Method::Residual);
    let mut examples = five_examples(&cfg);
    for (i, ex) in examples.iter_mut().enumerate() {
        ex.extra_views = (1..=2)
            .map(|j| veila_diffusion::app::TrainView {
                rgb: image((i * 3 + j) as u8),
                camera: if j == 1 { second_camera() } else { camera() },
            })
            .collect();
    }
    let mut weights: HashMap<&str, HashMap<String, candle_core::Tensor>> = HashMap::new();
    let encoders: Vec<veila_nn::encoders::kind::AnyEncoder> = [
        (SEMANTIC_FILE, cfg.semantic_encoder.clone().unwrap()),
        (DEPTH_FILE, cfg.depth_encoder.clone().unwrap()),
    ]
    .iter()
    .map(|(file, e)| {
        let vm = VarMap::new();
        let net = SmallCnn::new(
            e.small_cnn_config().unwrap(),
            veila_nn::seeded_var_builder(&vm, 1, DType::F32, &dev),
        )
        .unwrap();
        weights.insert(file, varmap_tensors(&vm).unwrap());
        net.into()
    })
    .collect();
    let tc = veila_diffusion::TrainConfig {
        total_steps: 2,
        warmup_steps: 1,
        checkpoint_every: None,
        ..veila_diffusion::TrainConfig::default()
    };
    let tmp = tempfile::tempdir().unwrap();
    let fit = |examples: &[TrainExample], cfg: &mut BundleConfig, dir: &str| {
        fit_bundle(
            cfg,
            BundleFit {
                semantic: Some(&encoders[0]),
                depth: Some(&encoders[1]),
                examples: examples.into(),
                batch_size: 2,
                train: &tc,
                mean_train: None,
                work_dir: &tmp.path().join(dir),
                init: None,
                mean_init: None,
                parallel: None,
            },
            &dev,
            |_, _, _| {},
            |_, _| Quiet,
        )
    };
    let out = fit(&examples, &mut cfg, "three").unwrap();
    // examples with one camera cannot feed it
    let single: Vec<TrainExample> = five_examples(&cfg);
    let err = fit(&single, &mut cfg.clone(), "one").unwrap_err();
    assert!(err.to_string().contains("takes 3 camera views"), "{err}");
    // the trained bundle generates from its three views
    weights.insert(MEAN_FILE, out.mean.unwrap().ema_weights);
    weights.insert(DENOISER_FILE, out.denoiser.unwrap().ema_weights);
    let bdir = tmp.path().join("bundle");
    Bundle::save(&bdir, &cfg, &weights).unwrap();
    let b = Bundle::from_dir(&bdir, &dev).unwrap();
    let ex = &examples[0];
    let views: Vec<CameraView<'_>> = std::iter::once(CameraView {
        rgb: &ex.rgb,
        camera: &ex.camera,
    })
    .chain(ex.extra_views.iter().map(|v| CameraView {
        rgb: &v.rgb,
        camera: &v.camera,
    }))
    .collect();
    let scans = b.generate(&views, &opts(0, 1), |_, _| {}).unwrap();
    assert!(scans[0].range_m.iter().all(|r| r.is_finite()));
    // the weights do not depend on the view count: one view runs too, and sees less
    let one = b.generate(&views[..1], &opts(0, 1), |_, _| {}).unwrap();
    assert_ne!(one[0].range_m, scans[0].range_m);
}

#[test]
fn the_ground_prior_is_a_bundle_switch_that_reads_each_views_camera() {
    use veila_nn::encoders::ground::GroundPrior;
    let tmp = tempfile::tempdir().unwrap();
    let cam = camera();
    // the same rig raised by 0.5 m: the same image, another flat ground
    let raised = PinholeCamera {
        cam_from_lidar: cam.cam_from_lidar
            * glam::Mat4::from_translation(glam::Vec3::new(0.0, 0.0, -0.5)),
        ..cam
    };
    let img = image(4);
    let feats = |b: &Bundle, c: &PinholeCamera| {
        let f = b
            .encode_views(&[CameraView {
                rgb: &img,
                camera: c,
            }])
            .unwrap();
        [f.semantic.unwrap(), f.depth.unwrap()]
            .iter()
            .flat_map(|p| {
                p.iter()
                    .map(|t| t.flatten_all().unwrap().to_vec1::<f32>().unwrap())
            })
            .collect::<Vec<_>>()
    };

    // off (the default): the config says nothing about it and the camera does not matter
    let off = small_config(Variant::Full);
    let json = serde_json::to_string(&off).unwrap();
    assert!(!json.contains("ground_prior"), "{json}");
    save_random_bundle(&tmp.path().join("off"), &off, 3);
    let b = Bundle::from_dir(&tmp.path().join("off"), &Device::Cpu).unwrap();
    assert_eq!(feats(&b, &cam), feats(&b, &raised));

    // on: stored in bundle.json, the stems take 4 channels, each view's camera matters
    let mut on = off.clone();
    assert_eq!(on.set_ground_prior(Some(GroundPrior::default())), 2);
    save_random_bundle(&tmp.path().join("on"), &on, 3);
    let text = std::fs::read_to_string(tmp.path().join("on/bundle.json")).unwrap();
    assert_eq!(text.matches("\"ground_prior\"").count(), 2, "{text}");
    let b = Bundle::from_dir(&tmp.path().join("on"), &Device::Cpu).unwrap();
    assert_eq!(b.config, on);
    let stem = b.depth.as_ref().unwrap().as_small_cnn().unwrap();
    assert_eq!(stem.config().input_channels(), 4);
    assert_ne!(feats(&b, &cam), feats(&b, &raised));
    // and generation runs through it
    let view = [CameraView {
        rgb: &img,
        camera: &cam,
    }];
    let scans = b.generate(&view, &opts(1, 1), |_, _| {}).unwrap();
    assert!(scans[0].range_m.iter().all(|r| r.is_finite()));
    // a bundle of the other setting does not load the weights of this one
    std::fs::copy(
        tmp.path().join("off/bundle.json"),
        tmp.path().join("on/bundle.json"),
    )
    .unwrap();
    assert!(Bundle::from_dir(&tmp.path().join("on"), &Device::Cpu).is_err());
}

#[test]
fn encoders_with_the_ground_prior_train_from_memory_and_a_source_alike_and_need_cameras() {
    use veila_nn::encoders::ground::GroundPrior;
    let mut cfg = small_config(Variant::Full);
    cfg.set_ground_prior(Some(GroundPrior::default()));
    let data = EncoderFixture::new(&cfg);
    let settings = encoder_settings(2, Some(veila_diffusion::app::EncoderAugment::default()));
    let tmp = tempfile::tempdir().unwrap();
    let train = |d, dir: &str| trained_encoder_weights(&cfg, &settings, d, &tmp.path().join(dir));
    let memory = train(data.memory(true), "memory").unwrap();
    let streamed = train(
        veila_diffusion::app::EncoderData::Stream(&data.source),
        "stream",
    )
    .unwrap();
    assert_eq!(memory, streamed);
    // the stem reads four channels
    let stem = memory
        .iter()
        .find(|(n, _)| n.ends_with("encoder.stem.conv1.weight"))
        .unwrap();
    assert_eq!(stem.1.len(), 8 * 4 * 3 * 3);
    // no cameras: an error naming them, not a panic
    let err = train(data.memory(false), "none").unwrap_err().to_string();
    assert!(err.contains("camera"), "{err}");
}

#[test]
fn depth_features_are_a_bundle_switch_that_widens_the_conditioning() {
    let tmp = tempfile::tempdir().unwrap();
    let cam = camera();
    let img = image(4);
    let off = small_config(Variant::Full);
    assert!(
        !serde_json::to_string(&off)
            .unwrap()
            .contains("depth_features")
    );
    let mut on = off.clone();
    on.set_depth_features(true).unwrap();
    // the depth encoder's maps and both networks' conditioning get one more channel each
    let depth_channels = |c: &BundleConfig| {
        let mut out = vec![
            c.denoiser
                .conditioning
                .as_ref()
                .unwrap()
                .depth_channels
                .clone(),
        ];
        if let Some(r) = &c.residual {
            out.push(
                r.mean_net
                    .conditioning
                    .as_ref()
                    .unwrap()
                    .depth_channels
                    .clone(),
            );
        }
        out
    };
    for (a, b) in depth_channels(&off).iter().zip(depth_channels(&on)) {
        assert_eq!(a.iter().map(|c| c + 1).collect::<Vec<_>>(), b);
    }
    assert_eq!(
        off.semantic_encoder, on.semantic_encoder,
        "only the depth encoder changes"
    );
    save_random_bundle(&tmp.path().join("on"), &on, 3);
    let text = std::fs::read_to_string(tmp.path().join("on/bundle.json")).unwrap();
    assert_eq!(text.matches("\"depth_features\"").count(), 1, "{text}");
    let b = Bundle::from_dir(&tmp.path().join("on"), &Device::Cpu).unwrap();
    assert_eq!(b.config, on);
    let view = [CameraView {
        rgb: &img,
        camera: &cam,
    }];
    let f = b.encode_views(&view).unwrap();
    let want = &depth_channels(&on)[0];
    for (t, c) in f.depth.unwrap().iter().zip(want) {
        assert_eq!(t.dim(1).unwrap(), *c);
    }
    let scans = b.generate(&view, &opts(1, 1), |_, _| {}).unwrap();
    assert!(scans[0].range_m.iter().all(|r| r.is_finite()));
    // the encoders of a bundle made without it serve a run with it (same weights), and then
    // return the wider maps
    save_random_bundle(&tmp.path().join("off"), &off, 3);
    let e = veila_diffusion::app::prepare_encoders(
        &on,
        veila_diffusion::app::EncoderSource::Bundle(&tmp.path().join("off")),
        &encoder_settings(1, None),
        &Device::Cpu,
        |_| {},
    )
    .unwrap();
    let d = e.depth.unwrap();
    assert_eq!(d.channels().to_vec(), *want);
    let plain = Bundle::from_dir(&tmp.path().join("off"), &Device::Cpu).unwrap();
    let x = veila_nn::encoders::rgb8_to_tensor(
        &img,
        on.image_height,
        on.image_width,
        &veila_nn::encoders::Normalization::IMAGENET,
        &Device::Cpu,
    )
    .unwrap();
    use veila_nn::encoders::ImageEncoder;
    let (wide, narrow) = (
        d.forward(&x).unwrap(),
        plain.depth.unwrap().forward(&x).unwrap(),
    );
    for (a, b) in wide.iter().zip(&narrow) {
        let c = b.dim(1).unwrap();
        assert_eq!(
            a.narrow(1, 0, c)
                .unwrap()
                .flatten_all()
                .unwrap()
                .to_vec1::<f32>()
                .unwrap(),
            b.flatten_all().unwrap().to_vec1::<f32>().unwrap()
        );
    }
    // switching it back restores the original config exactly
    let mut back = on.clone();
    back.set_depth_features(false).unwrap();
    assert_eq!(back, off);
    // a model without a small-CNN depth encoder says so
    let mut none = off.clone();
    none.set_encoders(off.semantic_encoder.clone(), None)
        .unwrap();
    let err = none.set_depth_features(true).unwrap_err().to_string();
    assert!(err.contains("depth encoder"), "{err}");
}
