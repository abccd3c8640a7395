use super::*;
use crate::{
    Batch, Diffusion, DiffusionConfig, Sampler, SamplerConfig, TimeInput, TrainConfig, Trainer,
    noise::randn,
};
use candle_core::DType;
use candle_nn::VarMap;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use veila_geom::{BeamLayout, LidarSensor};
use veila_nn::config::{ConditioningConfig, Cues, Fusion, PfcConfig, TimeEmbeddingConfig};
use veila_nn::{ConditionInput, DenoiserConfig};

/// A very small conditional Veila U-Net: 8 x 32 range images, CACM without GCMA, PFC.
fn small_config() -> DenoiserConfig {
    DenoiserConfig {
        sensor: LidarSensor {
            rows: 8,
            cols: 32,
            beams: BeamLayout::Uniform,
            ..LidarSensor::hdl64e()
        },
        in_channels: 3,
        out_channels: 3,
        base_channels: 8,
        channel_mults: vec![1, 2],
        num_res_blocks: 1,
        norm_groups: 4,
        residual_scale: std::f32::consts::FRAC_1_SQRT_2,
        time: TimeEmbeddingConfig {
            dim: 16,
            max_period: 10_000.0,
            input_scale: 1000.0,
        },
        ray_features: None,
        pfc: Some(PfcConfig { num_heads: 2 }),
        conditioning: Some(ConditioningConfig {
            cues: Cues::Both,
            fusion: Fusion::Cacm,
            semantic_channels: vec![4, 6],
            depth_channels: vec![4, 6],
            feature_sizes: vec![[6, 10], [3, 5]],
            cond_channels: vec![8, 8],
            cacm_delta: 1e-6,
            num_views: 1,
            gcma: None,
        }),
    }
}

fn features(b: usize, seed: u64) -> ConditionInput {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut pyr = |chs: [usize; 2]| {
        vec![
            randn(&mut rng, &[b, chs[0], 6, 10], &Device::Cpu).unwrap(),
            randn(&mut rng, &[b, chs[1], 3, 5], &Device::Cpu).unwrap(),
        ]
    };
    ConditionInput {
        semantic: Some(pyr([4, 6])),
        depth: Some(pyr([4, 6])),
        keep: None,
    }
}

fn build(seed: u64) -> (VeilaDenoiser<'static>, VarMap) {
    let vm = VarMap::new();
    let vb = veila_nn::seeded_var_builder(&vm, seed, DType::F32, &Device::Cpu);
    let net = veila_nn::Denoiser::new(&small_config(), vb).unwrap();
    (VeilaDenoiser::new(net), vm)
}

fn max_abs(t: &Tensor) -> f32 {
    t.abs()
        .unwrap()
        .max_all()
        .unwrap()
        .to_scalar::<f32>()
        .unwrap()
}

#[test]
fn dropped_samples_get_the_unconditional_output() {
    let (model, _vm) = build(1);
    let cond = model
        .net()
        .prepare_condition(&features(2, 3), None)
        .unwrap();
    let x = randn(
        &mut ChaCha8Rng::seed_from_u64(4),
        &[2, 3, 8, 32],
        &Device::Cpu,
    )
    .unwrap();
    let t = Tensor::new(&[0.3f32, 0.7], &Device::Cpu).unwrap();
    let with = model
        .forward(&x, &t, Some(&NetCond::from(cond.clone())))
        .unwrap();
    let without = model.forward(&x, &t, None).unwrap();
    let mixed = model
        .forward(
            &x,
            &t,
            Some(
                &NetCond::from(cond.clone())
                    .drop_samples(&[true, false])
                    .unwrap(),
            ),
        )
        .unwrap();
    assert!(
        max_abs(&(&with - &without).unwrap()) > 1e-4,
        "the condition matters at all"
    );
    assert!(max_abs(&(mixed.get(0).unwrap() - without.get(0).unwrap()).unwrap()) < 1e-5);
    assert!(max_abs(&(mixed.get(1).unwrap() - with.get(1).unwrap()).unwrap()) < 1e-5);
    // dropping twice stays dropped; a wrong mask length is an error
    let twice = cond
        .drop_samples(&[true, false])
        .unwrap()
        .drop_samples(&[false, false])
        .unwrap();
    assert_eq!(
        twice.keep.unwrap().to_vec1::<f32>().unwrap(),
        vec![0.0, 1.0]
    );
    assert!(cond.drop_samples(&[true]).is_err());
}

#[test]
fn trains_and_samples_through_the_generic_api() {
    let (model, vm) = build(2);
    let diffusion = Diffusion::new(DiffusionConfig {
        time_input: TimeInput::Unit,
        ..DiffusionConfig::default()
    })
    .unwrap();
    let cond = NetCond::from(
        model
            .net()
            .prepare_condition(&features(2, 5), None)
            .unwrap(),
    );
    let x0 = (randn(
        &mut ChaCha8Rng::seed_from_u64(6),
        &[2, 3, 8, 32],
        &Device::Cpu,
    )
    .unwrap()
        * 0.5)
        .unwrap()
        .tanh()
        .unwrap();
    let mut trainer = Trainer::new(
        model,
        vm,
        diffusion.clone(),
        TrainConfig {
            total_steps: 2,
            warmup_steps: 1,
            cond_drop_prob: 0.5,
            checkpoint_every: None,
            ..TrainConfig::default()
        },
    )
    .unwrap();
    let before = trainer.weights().unwrap();
    let batch = Batch {
        x0,
        cond: Some(cond.clone()),
        weight: None,
    };
    for _ in 0..2 {
        let s = trainer.train_step(&batch).unwrap();
        assert!(s.loss.is_finite() && !s.skipped);
    }
    let after = trainer.weights().unwrap();
    let changed = before
        .iter()
        .any(|(k, v)| max_abs(&(v - &after[k]).unwrap()) > 0.0);
    assert!(changed, "training updated the Veila weights");
    let sampler = Sampler::new(
        &diffusion,
        SamplerConfig {
            guidance_scale: 2.0,
            ..SamplerConfig::dpm_solver_pp_2m(4)
        },
    )
    .unwrap();
    let x = trainer
        .with_ema_weights(|m| {
            sampler.sample(
                m,
                &[2, 3, 8, 32],
                &Device::Cpu,
                Some(&cond),
                &mut ChaCha8Rng::seed_from_u64(1),
            )
        })
        .unwrap();
    assert_eq!(x.dims(), &[2, 3, 8, 32]);
    assert!(
        x.flatten_all()
            .unwrap()
            .to_vec1::<f32>()
            .unwrap()
            .iter()
            .all(|v| v.is_finite())
    );
}

#[test]
fn a_trainer_with_activation_checkpointing_takes_the_plain_updates() {
    // the recomputed blocks' parameter gradients reach the optimizer through finish_backward:
    // without it those weights would not move and the runs would part at the first update
    let run = |mode: crate::trainer::ActivationCheckpointing| {
        let (model, vm) = build(2);
        let mut net = model.into_inner();
        net.set_recompute_blocks(mode == crate::trainer::ActivationCheckpointing::Block);
        let cond = NetCond::from(net.prepare_condition(&features(2, 5), None).unwrap());
        let x0 = (randn(
            &mut ChaCha8Rng::seed_from_u64(6),
            &[2, 3, 8, 32],
            &Device::Cpu,
        )
        .unwrap()
            * 0.5)
            .unwrap()
            .tanh()
            .unwrap();
        let mut trainer = Trainer::new(
            VeilaDenoiser::new(net),
            vm,
            Diffusion::new(DiffusionConfig::default()).unwrap(),
            TrainConfig {
                total_steps: 3,
                warmup_steps: 1,
                cond_drop_prob: 0.5,
                checkpoint_every: None,
                activation_checkpointing: mode,
                ..TrainConfig::default()
            },
        )
        .unwrap();
        let batch = Batch {
            x0,
            cond: Some(cond),
            weight: None,
        };
        let losses: Vec<f64> = (0..3)
            .map(|_| trainer.train_step(&batch).unwrap().loss)
            .collect();
        (losses, trainer.weights().unwrap())
    };
    let (l0, w0) = run(crate::trainer::ActivationCheckpointing::None);
    let (l1, w1) = run(crate::trainer::ActivationCheckpointing::Block);
    for (a, b) in l0.iter().zip(&l1) {
        assert!(
            (a - b).abs() <= 1e-6 * b.abs(),
            "losses {l0:?} against {l1:?}"
        );
    }
    let mut worst = 0f32;
    for (k, v) in &w0 {
        let scale = max_abs(v).max(1e-6);
        worst = worst.max(max_abs(&(v - &w1[k]).unwrap()) / scale);
    }
    assert!(worst <= 1e-5, "weights after 3 updates differ by {worst:e}");
}

#[test]
fn the_fused_adamw_declines_off_the_gpu_and_leaves_the_parameters_alone() {
    // on the CPU (and in a build without `cuda`) the trainer's per-tensor update must run
    let dev = candle_core::Device::Cpu;
    let p = candle_core::Var::ones(8, candle_core::DType::F32, &dev).unwrap();
    let m = candle_core::Var::zeros(8, candle_core::DType::F32, &dev).unwrap();
    let v = candle_core::Var::zeros(8, candle_core::DType::F32, &dev).unwrap();
    let g = candle_core::Tensor::ones(8, candle_core::DType::F32, &dev).unwrap();
    let f = super::fused_adamw();
    let params = candle_nn::ParamsAdamW::default();
    assert!(!f(&[(&p, &g, &m, &v)], &params, 1, 1.0).unwrap());
    assert!(!f(&[], &params, 1, 1.0).unwrap());
    assert_eq!(p.as_tensor().to_vec1::<f32>().unwrap(), vec![1.0; 8]);
}
