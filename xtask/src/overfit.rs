//! The bundled-size overfit check: a model of the bundled configuration trained on one simulated
//! frame must give that frame back. A defect anywhere between the range encoding and the decoded
//! scan (normalisation, clipping, loss weights, residual scaling, guidance, the sampler's last
//! step, ray-drop decoding) turns the result into noise, however long the training.
//!
//! Run by hand (minutes on 2 cores):
//! `cargo test -p xtask --release -- --ignored overfit --nocapture`
//! with `VEILA_OVERFIT_METHOD=residual|v|eps|flow|regression` (default residual) and
//! `VEILA_OVERFIT_STEPS` (default 3,000 updates of each network: 600 gave 0.557 m, 2,000 gave 0.211 m,
//! BENCHMARKS.md; about 1.2 s per update on one core). The fast version of the check, at 8 x 64, runs with
//! every `cargo test` (`veila-diffusion/tests/bundle_pipeline.rs`).

#[cfg(test)]
mod tests {
    use std::collections::HashMap;

    use candle_core::{Device, Tensor};
    use veila_diffusion::app::bundle::{Bundle, BundleConfig, Method, Variant};
    use veila_diffusion::app::{BundleFit, CameraView, GenerateOptions, fit_bundle};
    use veila_diffusion::{Diffusion, NetCond, SamplerConfig, TrainConfig, VeilaDenoiser};
    use veila_geom::Region;

    use crate::simdata::{render_split, workspace_root};

    struct Quiet;
    impl<M: veila_diffusion::Denoiser> veila_diffusion::TrainObserver<M> for Quiet {}

    #[test]
    #[ignore = "minutes of training: run by hand (see the module documentation)"]
    fn overfit_bundled_size_model_reproduces_one_frame() {
        let method: Method = std::env::var("VEILA_OVERFIT_METHOD")
            .ok()
            .map(|m| m.parse().unwrap())
            .unwrap_or(Method::Residual);
        let steps: u64 = std::env::var("VEILA_OVERFIT_STEPS")
            .ok()
            .and_then(|s| s.parse().ok())
            .unwrap_or(3000);
        let dev = Device::Cpu;
        let root = workspace_root();
        let base = Bundle::from_dir(&root.join("models/default"), &dev).unwrap();
        let mut cfg = BundleConfig::cpu_default(Variant::Full).with_method(method);
        let frame = render_split(&root.join("scenes/test.txt"), 1, &cfg, "frame")
            .unwrap()
            .remove(0);
        let examples = vec![frame.train_example(&cfg).unwrap()];
        let tc = TrainConfig {
            seed: 0,
            lr: 2e-3,
            min_lr: 2e-4,
            warmup_steps: 20,
            total_steps: steps,
            ema_decay: 0.95,
            cond_drop_prob: 0.0,
            checkpoint_every: None,
            ..TrainConfig::default()
        };
        let tmp = tempfile::tempdir().unwrap();
        let t = std::time::Instant::now();
        let out = fit_bundle(
            &mut cfg,
            BundleFit {
                semantic: base.semantic.as_ref(),
                depth: base.depth.as_ref(),
                examples: (&examples).into(),
                batch_size: 8,
                train: &tc,
                mean_train: None,
                work_dir: tmp.path(),
                init: None,
                mean_init: None,
                parallel: None,
            },
            &dev,
            |_, _, _| {},
            |_, _| Quiet,
        )
        .unwrap();
        let secs = t.elapsed().as_secs_f64();
        let denoiser = out.denoiser.unwrap();
        let net = |w: &HashMap<String, Tensor>, c: &veila_nn::DenoiserConfig| {
            veila_nn::Denoiser::new(
                c,
                candle_nn::VarBuilder::from_tensors(w.clone(), candle_core::DType::F32, &dev),
            )
            .unwrap()
        };
        let bundle = Bundle {
            config: cfg.clone(),
            semantic: base.semantic.clone(),
            depth: base.depth.clone(),
            denoiser: net(&denoiser.ema_weights, &cfg.denoiser),
            weights: HashMap::new(),
            mean: out.mean.as_ref().map(|m| {
                let c = &cfg.residual.as_ref().unwrap().mean_net;
                (net(&m.ema_weights, c), HashMap::new())
            }),
            origin: "(overfit)".into(),
        };
        let view = [CameraView {
            rgb: &frame.rgb,
            camera: &frame.camera,
        }];
        // x̂₀ at the largest noise level: the conditional mean of a one-frame data set is the frame
        if method != Method::Regression && cfg.diffusion.objective.is_diffusion() {
            let d = Diffusion::new(cfg.diffusion.clone()).unwrap();
            let level = d.schedule().level(1.0);
            let (h, w) = bundle.grid();
            let feats = bundle.encode_views(&view).unwrap();
            let geom = bundle
                .denoiser
                .geometry(&[frame.camera], &cfg.epipolar, &dev)
                .unwrap();
            let input = veila_diffusion::app::ViewFeatures::cat(&[&feats]).unwrap();
            let image = bundle
                .denoiser
                .prepare_condition(&input, Some(&geom))
                .unwrap();
            let noise = veila_diffusion::noise::randn(
                &mut <rand_chacha::ChaCha8Rng as rand::SeedableRng>::seed_from_u64(1),
                &[1, cfg.channels(), h, w],
                &dev,
            )
            .unwrap();
            let mean = bundle.mean.as_ref().map(|(m, _)| {
                let prep = m.prepare_condition(&input, Some(&geom)).unwrap();
                m.forward(
                    &noise.zeros_like().unwrap(),
                    &d.flow_time(&[1.0], &dev).unwrap(),
                    Some(&prep),
                )
                .unwrap()
            });
            let cond = NetCond {
                image: Some(image),
                mean,
            };
            let den = d
                .denoise(
                    &VeilaDenoiser::new(bundle.denoiser.clone()),
                    &noise,
                    &level,
                    Some(&cond),
                    None,
                    Some(1.0),
                )
                .unwrap();
            let mut x0 = den.x0.flatten_all().unwrap().to_vec1::<f32>().unwrap();
            // a residual denoiser predicts the scaled residual: x̂₀ = mean + scale ⊙ r̂
            if let (Some(r), Some(m)) = (cfg.residual.as_ref(), cond.mean.as_ref()) {
                let m = m.flatten_all().unwrap().to_vec1::<f32>().unwrap();
                for (i, v) in x0.iter_mut().enumerate() {
                    *v = m[i] + *v * r.scale[i / (h * w)];
                }
            }
            let target = &examples[0].x0;
            let diff: f32 = x0
                .iter()
                .zip(target)
                .map(|(a, b)| (a - b).abs())
                .sum::<f32>()
                / x0.len() as f32;
            eprintln!("x̂₀ at the largest noise level: mean |error| {diff:.4} (encoded units)");
        }
        let sample = |steps: usize, seed: u64| {
            bundle
                .generate(
                    &view,
                    &GenerateOptions {
                        sampler: SamplerConfig {
                            steps,
                            guidance_scale: 1.0,
                            ..cfg.sampler.clone()
                        },
                        samples: 1,
                        seed,
                        unconditional: false,
                        residual_weight: 1.0,
                    },
                    |_, _| {},
                )
                .unwrap()
                .remove(0)
        };
        let mut worst: f64 = 0.0;
        if bundle.mean.is_some() {
            // what the mean network alone gives (0 sampler steps)
            let scan = sample(0, 1);
            let mae = veila_metrics::range::range_mae(&scan, &frame.range, Region::All).unwrap();
            eprintln!("the mean network alone: range MAE {mae:.3} m");
        }
        for seed in [1, 2] {
            let scan = sample(16, seed);
            let mae = veila_metrics::range::range_mae(&scan, &frame.range, Region::All).unwrap();
            let flips = scan
                .mask
                .iter()
                .zip(&frame.range.mask)
                .filter(|(a, b)| a != b)
                .count() as f64
                / scan.mask.len() as f64;
            eprintln!(
                "{} after {steps} steps ({secs:.0} s): seed {seed}: range MAE {mae:.3} m, {flips:.4} ray-drop flips",
                method.name()
            );
            worst = worst.max(mae);
        }
        assert!(worst < 0.2, "range MAE {worst} m");
    }
}
