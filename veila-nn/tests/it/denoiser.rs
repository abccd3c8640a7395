//! The whole denoiser: shapes of every ablation, azimuth-roll equivariance, zero-initialised GCMA,
//! classifier-free-guidance dropout, gradients and deterministic init.

use crate::common::*;
use candle_core::{DType, Device, Tensor};
use veila_nn::{ConditionInput, Cues, DenoiserConfig, Fusion, GcmaGeometry};

fn run(cfg: &DenoiserConfig, b: usize, cameras: &[veila_geom::PinholeCamera]) -> Tensor {
    let (_, net) = varmap_model(cfg, 1);
    let mut r = rng(2);
    let x = rand_tensor(&mut r, &[b, 3, 16, 128]);
    let t = Tensor::new(&vec![0.3f32; b][..], &Device::Cpu).unwrap();
    let out = match &cfg.conditioning {
        None => net.forward(&x, &t, None).unwrap(),
        Some(cc) => {
            let geom = cc
                .gcma
                .as_ref()
                .map(|_| GcmaGeometry::new(cfg, cameras, &epipolar(4), &Device::Cpu).unwrap());
            let (sem, dep) = rand_pyramids(&mut r, cfg, b);
            let input = ConditionInput {
                semantic: (cc.cues != Cues::DepthOnly).then_some(sem),
                depth: (cc.cues != Cues::SemanticOnly).then_some(dep),
                keep: None,
            };
            let prepared = net.prepare_condition(&input, geom.as_ref()).unwrap();
            net.forward(&x, &t, Some(&prepared)).unwrap()
        }
    };
    assert_eq!(out.dims(), &[b, 3, 16, 128]);
    assert!(all_finite(&out));
    out
}

#[test]
fn every_ablation_runs_with_the_right_shapes() {
    let base = small_config();
    let cams = [kitti_camera()];
    run(&base, 2, &cams);
    run(&base.clone().unconditional(), 2, &cams);
    let mut c = base.clone();
    c.conditioning.as_mut().unwrap().fusion = Fusion::Concat; // w/o CACM
    run(&c, 1, &cams);
    let mut c = base.clone();
    c.conditioning.as_mut().unwrap().gcma = None; // w/o GCMA
    run(&c, 2, &cams);
    let mut c = base.clone();
    c.pfc = None; // w/o PFC
    run(&c, 1, &cams);
    let mut c = base.clone();
    c.conditioning.as_mut().unwrap().cues = Cues::SemanticOnly;
    run(&c, 1, &cams);
    let mut c = base.clone();
    c.conditioning.as_mut().unwrap().cues = Cues::DepthOnly;
    run(&c, 1, &cams);
    let mut c = base.clone();
    c.conditioning.as_mut().unwrap().num_views = 2; // multi-camera
    run(&c, 2, &[kitti_camera(), rear_camera()]);
    let mut c = base.clone();
    c.ray_features = None;
    c.num_res_blocks = 2;
    run(&c, 1, &cams);
}

fn roll_w(t: &Tensor, k: usize) -> Tensor {
    let w = t.dim(3).unwrap();
    Tensor::cat(
        &[
            t.narrow(3, w - k, k).unwrap(),
            t.narrow(3, 0, w - k).unwrap(),
        ],
        3,
    )
    .unwrap()
}

/// Rolling the input by `k` columns (a multiple of the total stride 2^(levels-1) = 8) rolls the output
/// of the unconditional network by `k`: ring padding, strided convs, nearest upsampling, GroupNorm and
/// PFC (no positional encoding) all commute with it. Summation orders differ, so equality is up to f32
/// rounding (tolerance 1e-5 relative to the output magnitude), not bitwise.
#[test]
fn unconditional_network_is_equivariant_to_azimuth_rolls() {
    let mut cfg = small_config().unconditional();
    cfg.ray_features = None;
    let (vm, net) = varmap_model(&cfg, 4);
    let mut r = rng(6);
    let x = rand_tensor(&mut r, &[2, 3, 16, 128]);
    let t = Tensor::new(&[0.2f32, 0.7], &Device::Cpu).unwrap();
    let y = net.forward(&x, &t, None).unwrap();
    let scale = y
        .abs()
        .unwrap()
        .max_all()
        .unwrap()
        .to_scalar::<f32>()
        .unwrap();
    for k in [8usize, 40, 120] {
        let y_rolled_in = net.forward(&roll_w(&x, k), &t, None).unwrap();
        let d = max_abs_diff(&y_rolled_in, &roll_w(&y, k));
        assert!(d <= 1e-5 * scale.max(1.0), "roll {k}: {d}");
    }

    // with ray-direction features the network sees absolute azimuth: rolling only x breaks equivariance,
    // rolling the ray features too restores it
    let mut cfg_rf = cfg.clone();
    cfg_rf.ray_features = small_config().ray_features;
    let (_, net_rf) = varmap_model(&cfg_rf, 4);
    let y = net_rf.forward(&x, &t, None).unwrap();
    let k = 40;
    let broken = max_abs_diff(
        &net_rf.forward(&roll_w(&x, k), &t, None).unwrap(),
        &roll_w(&y, k),
    );
    assert!(
        broken > 1e-3,
        "ray features should break pure input-roll equivariance ({broken})"
    );
    let mut net_rolled = net_rf.clone();
    net_rolled
        .set_ray_features(roll_w(net_rf.ray_features().unwrap(), k))
        .unwrap();
    let d = max_abs_diff(
        &net_rolled.forward(&roll_w(&x, k), &t, None).unwrap(),
        &roll_w(&y, k),
    );
    assert!(d <= 1e-5 * scale.max(1.0), "rolled ray features: {d}");
    drop(vm);
}

/// An untrained (zero-initialised) GCMA leaves the network exactly unchanged: the conditioned output
/// equals, bit for bit, the output without condition and the output of a network built without GCMA
/// from the same weights.
#[test]
fn zero_initialised_gcma_leaves_the_network_unchanged_bit_exactly() {
    let cfg = small_config();
    let (vm, net) = varmap_model(&cfg, 8);
    let dev = Device::Cpu;
    let geom = GcmaGeometry::new(&cfg, &[kitti_camera()], &epipolar(6), &dev).unwrap();
    let mut r = rng(12);
    let x = rand_tensor(&mut r, &[2, 3, 16, 128]);
    let t = Tensor::new(&[0.1f32, 0.6], &dev).unwrap();
    let (sem, dep) = rand_pyramids(&mut r, &cfg, 2);
    let input = ConditionInput {
        semantic: Some(sem),
        depth: Some(dep),
        keep: None,
    };
    let prepared = net.prepare_condition(&input, Some(&geom)).unwrap();
    let with = net
        .forward(&x, &t, Some(&prepared))
        .unwrap()
        .flatten_all()
        .unwrap()
        .to_vec1::<f32>()
        .unwrap();
    let without = net
        .forward(&x, &t, None)
        .unwrap()
        .flatten_all()
        .unwrap()
        .to_vec1::<f32>()
        .unwrap();
    // the same weights in a network whose config has no GCMA (and no conditioning at all)
    let mut plain_cfg = cfg.clone();
    plain_cfg.conditioning = None;
    let tensors: std::collections::HashMap<String, Tensor> = vm
        .data()
        .lock()
        .unwrap()
        .iter()
        .filter(|(k, _)| !k.contains("gcma") && !k.starts_with("cond."))
        .map(|(k, v)| (k.clone(), v.as_tensor().clone()))
        .collect();
    let plain = veila_nn::Denoiser::new(
        &plain_cfg,
        candle_nn::VarBuilder::from_tensors(tensors, DType::F32, &dev),
    )
    .unwrap();
    let plain_out = plain
        .forward(&x, &t, None)
        .unwrap()
        .flatten_all()
        .unwrap()
        .to_vec1::<f32>()
        .unwrap();
    assert!(with.iter().all(|v| v.is_finite()));
    assert!(
        with.iter()
            .zip(&without)
            .all(|(a, b)| a.to_bits() == b.to_bits())
    );
    assert!(
        with.iter()
            .zip(&plain_out)
            .all(|(a, b)| a.to_bits() == b.to_bits())
    );

    // control: once GCMA's output conv is non-zero the condition does change the output
    {
        let data = vm.data().lock().unwrap();
        let name = "down.0.gcma.out.weight";
        let shape = data[name].as_tensor().dims().to_vec();
        data[name].set(&rand_tensor(&mut r, &shape)).unwrap();
    }
    let changed = net.forward(&x, &t, Some(&prepared)).unwrap();
    let unchanged = net.forward(&x, &t, None).unwrap();
    assert!(max_abs_diff(&changed, &unchanged) > 1e-4);
    // and keep = 0 (classifier-free-guidance dropout) restores the unconditional output exactly
    let dropped = prepared
        .clone()
        .with_keep(Some(Tensor::new(&[0f32, 0.0], &dev).unwrap()));
    let d = net.forward(&x, &t, Some(&dropped)).unwrap();
    assert_eq!(max_abs_diff(&d, &unchanged), 0.0);
}

#[test]
fn gradients_reach_every_conditioning_branch() {
    let mut cfg = small_config();
    cfg.conditioning
        .as_mut()
        .unwrap()
        .gcma
        .as_mut()
        .unwrap()
        .decoder = false;
    let (vm, net) = varmap_model(&cfg, 9);
    // make GCMA's output conv non-zero so that gradients flow into its inner weights as well
    let mut r = rng(13);
    {
        let data = vm.data().lock().unwrap();
        for l in 0..4 {
            let name = format!("down.{l}.gcma.out.weight");
            let shape = data[&name].as_tensor().dims().to_vec();
            data[&name]
                .set(&rand_tensor(&mut r, &shape).affine(0.1, 0.0).unwrap())
                .unwrap();
        }
    }
    let dev = Device::Cpu;
    let geom = GcmaGeometry::new(&cfg, &[kitti_camera()], &epipolar(4), &dev).unwrap();
    let x = rand_tensor(&mut r, &[1, 3, 16, 128]);
    let t = Tensor::new(&[0.5f32], &dev).unwrap();
    let (sem, dep) = rand_pyramids(&mut r, &cfg, 1);
    let prepared = net
        .prepare_condition(
            &ConditionInput {
                semantic: Some(sem),
                depth: Some(dep),
                keep: None,
            },
            Some(&geom),
        )
        .unwrap();
    let loss = net
        .forward(&x, &t, Some(&prepared))
        .unwrap()
        .sqr()
        .unwrap()
        .mean_all()
        .unwrap();
    let grads = loss.backward().unwrap();
    let data = vm.data().lock().unwrap();
    for name in [
        "in_conv.weight",
        "mid.pfc.qkv.weight",
        "down.0.gcma.q.weight",
        "down.0.gcma.kv.weight",
        "down.0.gcma.pos.0.weight",
        "down.3.gcma.out.weight",
        "cond.fuse.0.proj_s.weight",
        "cond.fuse.0.conf_d.weight",
        "cond.fuse.3.proj_d.weight",
        "time.0.weight",
    ] {
        let g = grads
            .get(data[name].as_tensor())
            .unwrap_or_else(|| panic!("no gradient for {name}"));
        let n = g
            .abs()
            .unwrap()
            .sum_all()
            .unwrap()
            .to_scalar::<f32>()
            .unwrap();
        assert!(n > 0.0 && n.is_finite(), "{name}: {n}");
    }
}

#[test]
fn seeded_init_is_deterministic_and_seed_dependent() {
    let cfg = small_config().unconditional();
    let x = rand_tensor(&mut rng(1), &[1, 3, 16, 128]);
    let t = Tensor::new(&[0.4f32], &Device::Cpu).unwrap();
    let a = varmap_model(&cfg, 5).1.forward(&x, &t, None).unwrap();
    let b = varmap_model(&cfg, 5).1.forward(&x, &t, None).unwrap();
    let c = varmap_model(&cfg, 6).1.forward(&x, &t, None).unwrap();
    assert_eq!(max_abs_diff(&a, &b), 0.0);
    assert!(max_abs_diff(&a, &c) > 1e-3);
}

#[test]
fn bad_inputs_are_errors_not_panics() {
    let cfg = small_config();
    let (_, net) = varmap_model(&cfg, 1);
    let dev = Device::Cpu;
    let t = Tensor::new(&[0.4f32], &dev).unwrap();
    let x = Tensor::zeros((1, 3, 16, 64), DType::F32, &dev).unwrap();
    assert!(
        net.forward(&x, &t, None)
            .unwrap_err()
            .to_string()
            .contains("bad shape for x")
    );
    let x = Tensor::zeros((1, 3, 16, 128), DType::F32, &dev).unwrap();
    let t2 = Tensor::new(&[0.4f32, 0.1], &dev).unwrap();
    assert!(net.forward(&x, &t2, None).is_err());
    // GCMA model without geometry
    let (sem, dep) = rand_pyramids(&mut rng(1), &cfg, 1);
    let input = ConditionInput {
        semantic: Some(sem),
        depth: None,
        keep: None,
    };
    assert!(net.prepare_condition(&input, None).is_err());
    let input = ConditionInput {
        semantic: None,
        depth: Some(dep),
        keep: None,
    };
    assert!(net.prepare_condition(&input, None).is_err());
    // invalid configs
    let mut bad = cfg.clone();
    bad.channel_mults = vec![1, 2, 2, 2, 2, 2, 2, 2]; // 16 rows not divisible by 2^7
    assert!(bad.validate().is_err());
    let mut bad = cfg.clone();
    bad.conditioning
        .as_mut()
        .unwrap()
        .gcma
        .as_mut()
        .unwrap()
        .num_heads = 3;
    assert!(bad.validate().is_err());
}

#[test]
fn presets_validate_and_round_trip_through_json() {
    for cfg in [
        DenoiserConfig::tiny(),
        DenoiserConfig::paper(),
        DenoiserConfig::tiny().unconditional(),
        small_config(),
    ] {
        cfg.validate().unwrap();
        let json = serde_json::to_string(&cfg).unwrap();
        assert_eq!(DenoiserConfig::from_json(&json).unwrap(), cfg);
    }
    let mut v: serde_json::Value = serde_json::to_value(DenoiserConfig::tiny()).unwrap();
    v["unknown_field"] = serde_json::json!(1);
    assert!(DenoiserConfig::from_json(&v.to_string()).is_err());
}

#[test]
fn samples_of_different_rigs_attend_with_their_own_geometry() {
    let cfg = small_config();
    let (vm, net) = varmap_model(&cfg, 9);
    let dev = Device::Cpu;
    // GCMA's output convs non-zero, so the geometry shows in the output
    {
        let data = vm.data().lock().unwrap();
        let mut r = rng(21);
        for (_, var) in data.iter().filter(|(k, _)| k.contains("gcma.out.weight")) {
            let shape = var.as_tensor().dims().to_vec();
            var.set(&rand_tensor(&mut r, &shape)).unwrap();
        }
    }
    let front = GcmaGeometry::new(&cfg, &[kitti_camera()], &epipolar(4), &dev).unwrap();
    let rear = GcmaGeometry::new(&cfg, &[rear_camera()], &epipolar(4), &dev).unwrap();
    let mut r = rng(22);
    let b = 3;
    let x = rand_tensor(&mut r, &[b, 3, 16, 128]);
    let t = Tensor::new(&[0.2f32, 0.5, 0.8], &dev).unwrap();
    let (sem, dep) = rand_pyramids(&mut r, &cfg, b);
    let keep = Tensor::new(&[1f32, 0.0, 1.0], &dev).unwrap();
    let input = ConditionInput {
        semantic: Some(sem.clone()),
        depth: Some(dep.clone()),
        keep: Some(keep.clone()),
    };
    // samples 0 and 2 front, sample 1 rear
    let grouped = net
        .prepare_condition_per_sample(&input, &[&front, &rear, &front])
        .unwrap();
    assert_eq!(grouped.num_rigs(), 2);
    let out = net.forward(&x, &t, Some(&grouped)).unwrap();
    // each sample alone, with its own geometry
    let pick = |v: &Vec<Tensor>, i: usize| -> Vec<Tensor> {
        v.iter().map(|s| s.narrow(0, i, 1).unwrap()).collect()
    };
    for (i, geom) in [(0, &front), (1, &rear), (2, &front)] {
        let one = ConditionInput {
            semantic: Some(pick(&sem, i)),
            depth: Some(pick(&dep, i)),
            keep: Some(keep.narrow(0, i, 1).unwrap()),
        };
        let p = net.prepare_condition(&one, Some(geom)).unwrap();
        let want = net
            .forward(
                &x.narrow(0, i, 1).unwrap(),
                &t.narrow(0, i, 1).unwrap(),
                Some(&p),
            )
            .unwrap();
        let got = out.narrow(0, i, 1).unwrap();
        assert!(
            max_abs_diff(&got, &want) < 1e-5,
            "sample {i}: {}",
            max_abs_diff(&got, &want)
        );
    }
    // the rig matters: all-front differs for the rear sample (1), not for the front ones
    let shared = net
        .forward(
            &x,
            &t,
            Some(&net.prepare_condition(&input, Some(&front)).unwrap()),
        )
        .unwrap();
    let s1 = max_abs_diff(
        &shared.narrow(0, 0, 1).unwrap(),
        &out.narrow(0, 0, 1).unwrap(),
    );
    assert!(s1 < 1e-5, "front sample {s1}");
    // sample 1 is dropped (keep 0), so its GCMA branch is off too: use sample 2 for the rear check
    let grouped2 = net
        .prepare_condition_per_sample(&input, &[&front, &front, &rear])
        .unwrap();
    let out2 = net.forward(&x, &t, Some(&grouped2)).unwrap();
    let d = max_abs_diff(
        &shared.narrow(0, 2, 1).unwrap(),
        &out2.narrow(0, 2, 1).unwrap(),
    );
    assert!(d > 1e-4, "the rear rig changed nothing: {d}");
    // one rig for all: the shared path
    let same = net
        .prepare_condition_per_sample(&input, &[&front, &front, &front])
        .unwrap();
    assert_eq!(same.num_rigs(), 1);
    assert_eq!(
        max_abs_diff(&net.forward(&x, &t, Some(&same)).unwrap(), &shared),
        0.0
    );
    // one geometry per sample, or an error
    assert!(net.prepare_condition_per_sample(&input, &[&front]).is_err());
}
