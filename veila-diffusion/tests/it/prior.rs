//! A prior mean network that starts the sampler (`attach_prior`, `SamplerConfig::start_t`): a
//! draw started near clean data keeps the mean network's scan, one started from pure noise does
//! not; attaching needs the same encoder weights and never touches its inputs.

use std::collections::HashMap;
use std::path::Path;

use candle_core::{DType, Device, Tensor};
use candle_nn::VarMap;
use veila_diffusion::SamplerConfig;
use veila_diffusion::app::bundle::{
    Bundle, BundleConfig, DENOISER_FILE, DEPTH_FILE, MEAN_FILE, Method, SEMANTIC_FILE, Variant,
};
use veila_diffusion::app::{CameraView, GenerateOptions, attach_prior, varmap_tensors};
use veila_geom::RangeImage;
use veila_nn::encoders::small_cnn::SmallCnn;

use super::bundle_pipeline::{camera, image, small_config};

/// Saves `cfg` with random weights: the encoders from `encoder_seed`, the denoiser from
/// `net_seed`, a mean network from `net_seed + 1`.
fn save(dir: &Path, cfg: &BundleConfig, encoder_seed: u64, net_seed: u64) {
    let dev = Device::Cpu;
    let seeded = |seed: u64, f: &dyn Fn(candle_nn::VarBuilder<'_>)| -> HashMap<String, Tensor> {
        let vm = VarMap::new();
        f(veila_nn::seeded_var_builder(&vm, seed, DType::F32, &dev));
        varmap_tensors(&vm).unwrap()
    };
    let mut weights: HashMap<&str, HashMap<String, Tensor>> = HashMap::new();
    for (file, spec) in [
        (SEMANTIC_FILE, &cfg.semantic_encoder),
        (DEPTH_FILE, &cfg.depth_encoder),
    ] {
        let c = spec.as_ref().and_then(|e| e.small_cnn_config()).unwrap();
        weights.insert(
            file,
            seeded(encoder_seed, &|vb| {
                SmallCnn::new(c, vb).unwrap();
            }),
        );
    }
    weights.insert(
        DENOISER_FILE,
        seeded(net_seed, &|vb| {
            veila_nn::Denoiser::new(&cfg.denoiser, vb).unwrap();
        }),
    );
    if let Some(m) = cfg.mean_net() {
        weights.insert(
            MEAN_FILE,
            seeded(net_seed + 1, &|vb| {
                veila_nn::Denoiser::new(m, vb).unwrap();
            }),
        );
    }
    Bundle::save(dir, cfg, &weights).unwrap();
}

/// Mean absolute difference of the ranges of two scans, metres.
fn range_gap(a: &RangeImage, b: &RangeImage) -> f64 {
    let n = a.range_m.len();
    assert_eq!(n, b.range_m.len());
    a.range_m
        .iter()
        .zip(&b.range_m)
        .map(|(x, y)| f64::from((x - y).abs()))
        .sum::<f64>()
        / n as f64
}

fn draw(bundle: &Bundle, sampler: SamplerConfig, residual_weight: f64) -> RangeImage {
    let (cam, img) = (camera(), image(3));
    let views = [CameraView {
        rgb: &img,
        camera: &cam,
    }];
    let options = GenerateOptions {
        residual_weight,
        ..GenerateOptions::new(sampler)
    };
    bundle
        .generate(&views, &options, |_, _| {})
        .unwrap()
        .remove(0)
}

#[test]
fn a_prior_starts_the_draw_from_its_mean_networks_scan() {
    let tmp = tempfile::tempdir().unwrap();
    let (res_dir, v_dir, out) = (
        tmp.path().join("residual"),
        tmp.path().join("v"),
        tmp.path().join("prior"),
    );
    save(
        &res_dir,
        &small_config(Variant::Full).with_method(Method::Residual),
        7,
        20,
    );
    save(
        &v_dir,
        &small_config(Variant::Full).with_method(Method::V),
        7,
        30,
    );
    let cfg = attach_prior(&v_dir, &res_dir, 0.4, &out).unwrap();
    assert_eq!(cfg.sampler.start_t, Some(0.4));
    let dev = Device::Cpu;
    let (prior, residual) = (
        Bundle::from_dir(&out, &dev).unwrap(),
        Bundle::from_dir(&res_dir, &dev).unwrap(),
    );
    assert!(prior.config.prior.is_some() && prior.config.residual.is_none());
    // the mean network's scan: the residual bundle with no residual on top
    let mu = draw(&residual, residual.config.sampler.clone(), 0.0);
    let from = |t: f64| {
        let sampler = SamplerConfig {
            start_t: Some(t),
            ..prior.config.sampler.clone()
        };
        draw(&prior, sampler, 1.0)
    };
    // near clean data the random denoiser can move the scan by about σ only
    let (near, noise) = (range_gap(&from(0.01), &mu), range_gap(&from(1.0), &mu));
    assert!(
        near < 0.05 * noise,
        "started at t = 0.01 the draw is {near} m from the mean network's scan, from pure noise {noise} m"
    );
    // the bundle's own start level is in between, and the draw is seeded
    let own = range_gap(&draw(&prior, prior.config.sampler.clone(), 1.0), &mu);
    assert!(near < own && own < noise, "{near} < {own} < {noise}");
    assert_eq!(
        draw(&prior, prior.config.sampler.clone(), 1.0).range_m,
        draw(&prior, prior.config.sampler.clone(), 1.0).range_m
    );
    // 0 steps: the prior's mean network alone, exactly the residual bundle's mean (the same
    // weights); it needs the image
    let zero = SamplerConfig {
        steps: 0,
        start_t: None,
        ..prior.config.sampler.clone()
    };
    assert_eq!(draw(&prior, zero.clone(), 1.0).range_m, mu.range_m);
    let blind = GenerateOptions {
        unconditional: true,
        ..GenerateOptions::new(zero)
    };
    let e = prior
        .generate(&[], &blind, |_, _| {})
        .unwrap_err()
        .to_string();
    assert!(e.contains("image"), "{e}");
    // a start level needs a prior
    let v = Bundle::from_dir(&v_dir, &dev).unwrap();
    let e = GenerateOptions::new(SamplerConfig {
        start_t: Some(0.4),
        ..v.config.sampler.clone()
    })
    .check(&v)
    .unwrap_err()
    .to_string();
    assert!(e.contains("prior"), "{e}");
}

#[test]
fn attaching_a_prior_needs_the_same_encoders_and_leaves_its_inputs_alone() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = |name: &str| tmp.path().join(name);
    let res_cfg = small_config(Variant::Full).with_method(Method::Residual);
    let v_cfg = small_config(Variant::Full).with_method(Method::V);
    save(&dir("residual"), &res_cfg, 7, 20);
    save(&dir("v-other-encoders"), &v_cfg, 8, 30);
    save(&dir("v"), &v_cfg, 7, 30);
    let listing = |d: &Path| {
        let mut v: Vec<(String, Vec<u8>)> = std::fs::read_dir(d)
            .unwrap()
            .map(|e| {
                let e = e.unwrap();
                (
                    e.file_name().to_string_lossy().into_owned(),
                    std::fs::read(e.path()).unwrap(),
                )
            })
            .collect();
        v.sort();
        v
    };
    let before = (listing(&dir("residual")), listing(&dir("v")));
    let refused = |bundle: &str, mean_from: &str, out: &Path| {
        attach_prior(&dir(bundle), &dir(mean_from), 0.5, out)
            .unwrap_err()
            .to_string()
    };
    let e = refused("v-other-encoders", "residual", &dir("out"));
    assert!(e.contains(SEMANTIC_FILE), "{e}");
    let e = refused("residual", "residual", &dir("out"));
    assert!(e.contains("residual bundle"), "{e}");
    let e = refused("v", "v", &dir("out"));
    assert!(e.contains("no mean network"), "{e}");
    let e = refused("v", "residual", &dir("v"));
    assert!(e.contains("input bundle"), "{e}");
    assert!(!dir("out").exists(), "a refused attach wrote its output");
    let e = attach_prior(&dir("v"), &dir("residual"), 0.0, &dir("out"))
        .unwrap_err()
        .to_string();
    assert!(e.contains("start_t"), "{e}");
    assert!(!dir("out").exists());
    assert_eq!(before, (listing(&dir("residual")), listing(&dir("v"))));
    // a config with a start level but no prior, or with a residual and a prior, is refused
    let saved = |cfg: &BundleConfig| {
        Bundle::save(&dir("bad"), cfg, &HashMap::new())
            .unwrap_err()
            .to_string()
    };
    let mut no_prior = v_cfg.clone();
    no_prior.sampler.start_t = Some(0.5);
    assert!(saved(&no_prior).contains("start_t"));
    let mut both = res_cfg.clone();
    both.prior = Some(veila_diffusion::app::PriorConfig {
        mean_net: res_cfg.residual.as_ref().unwrap().mean_net.clone(),
    });
    assert!(saved(&both).contains("not both"));
}
