use super::*;
use candle_core::{DType, Device};
use candle_nn::Optimizer as _;
use rand::SeedableRng;

fn problem(seed: u64) -> (Vec<(String, Var)>, Tensor, Tensor) {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let w =
        Var::from_tensor(&crate::noise::randn(&mut rng, &[4, 3], &Device::Cpu).unwrap()).unwrap();
    let b = Var::from_tensor(&crate::noise::randn(&mut rng, &[3], &Device::Cpu).unwrap()).unwrap();
    let x = crate::noise::randn(&mut rng, &[16, 4], &Device::Cpu).unwrap();
    let y = crate::noise::randn(&mut rng, &[16, 3], &Device::Cpu).unwrap();
    (vec![("b".into(), b), ("w".into(), w)], x, y)
}

fn loss(vars: &[(String, Var)], x: &Tensor, y: &Tensor) -> Tensor {
    let pred = x
        .matmul(vars[1].1.as_tensor())
        .unwrap()
        .broadcast_add(vars[0].1.as_tensor())
        .unwrap();
    (pred - y).unwrap().sqr().unwrap().mean_all().unwrap()
}

fn values(vars: &[(String, Var)]) -> Vec<Vec<f32>> {
    vars.iter()
        .map(|(_, v)| {
            v.as_tensor()
                .flatten_all()
                .unwrap()
                .to_vec1::<f32>()
                .unwrap()
        })
        .collect()
}

#[test]
fn adamw_is_bit_identical_to_candle_nn_adamw() {
    let params = ParamsAdamW {
        lr: 0.05,
        weight_decay: 0.1,
        ..ParamsAdamW::default()
    };
    let (ours, x, y) = problem(1);
    let (theirs, _, _) = problem(1);
    let mut a = AdamW::new(ours.clone(), params.clone()).unwrap();
    let mut b =
        candle_nn::AdamW::new(theirs.iter().map(|(_, v)| v.clone()).collect(), params).unwrap();
    for step in 0..20 {
        let ga = loss(&ours, &x, &y).backward().unwrap();
        let gb = loss(&theirs, &x, &y).backward().unwrap();
        a.step(&ga, 1.0).unwrap();
        b.step(&gb).unwrap();
        assert_eq!(values(&ours), values(&theirs), "step {step}");
    }
    assert_eq!(a.step_count(), 20);
}

#[test]
fn adamw_runs_a_fused_update_where_it_accepts_and_the_plain_one_where_it_declines() {
    use std::sync::Arc;
    use std::sync::atomic::{AtomicUsize, Ordering};
    let params = ParamsAdamW {
        lr: 0.05,
        ..ParamsAdamW::default()
    };
    // a stand-in fused update that sees every slot and the step, sets each parameter to
    // step_t * grad_scale and accepts on odd steps only
    let calls = Arc::new(AtomicUsize::new(0));
    let seen = calls.clone();
    let fused: Arc<FusedAdamW> = Arc::new(move |slots, p, step_t, grad_scale| {
        seen.fetch_add(1, Ordering::SeqCst);
        assert_eq!(p.lr, 0.05);
        if step_t % 2 == 0 {
            return Ok(false);
        }
        for (var, g, _, _) in slots {
            assert_eq!(g.dims(), var.dims());
            var.set(&(var.zeros_like()? + step_t as f64 * grad_scale)?)?;
        }
        Ok(true)
    });
    let (ours, x, y) = problem(4);
    let (theirs, _, _) = problem(4);
    let mut a = AdamW::new(ours.clone(), params.clone()).unwrap();
    a.set_fused(Some(fused));
    let mut plain = AdamW::new(theirs.clone(), params).unwrap();
    // step 1: the fused update runs (every parameter becomes 1 * 0.5)
    a.step(&loss(&ours, &x, &y).backward().unwrap(), 0.5)
        .unwrap();
    assert!(values(&ours).iter().flatten().all(|v| *v == 0.5));
    // step 2: it declines, and the plain update runs on the same state as a plain optimizer
    for (_, v) in &theirs {
        v.set(&(v.zeros_like().unwrap() + 0.5).unwrap()).unwrap();
    }
    plain.load_state(&a.state_tensors(), 1).unwrap();
    a.step(&loss(&ours, &x, &y).backward().unwrap(), 1.0)
        .unwrap();
    plain
        .step(&loss(&theirs, &x, &y).backward().unwrap(), 1.0)
        .unwrap();
    assert_eq!(calls.load(Ordering::SeqCst), 2);
    assert!(values(&ours).iter().flatten().any(|v| *v != 0.5));
    assert_eq!(values(&ours), values(&theirs));
    assert_eq!(a.step_count(), 2);
}

#[test]
fn adamw_grad_scale_equals_scaling_the_gradients() {
    let params = ParamsAdamW {
        lr: 0.05,
        eps: 0.3, // large eps: Adam is no longer scale invariant, so scaling shows
        ..ParamsAdamW::default()
    };
    let (ours, x, y) = problem(2);
    let (theirs, _, _) = problem(2);
    let mut a = AdamW::new(ours.clone(), params.clone()).unwrap();
    let mut b =
        candle_nn::AdamW::new(theirs.iter().map(|(_, v)| v.clone()).collect(), params).unwrap();
    let before = values(&ours);
    for _ in 0..5 {
        let ga = loss(&ours, &x, &y).backward().unwrap();
        let mut gb = loss(&theirs, &x, &y).backward().unwrap();
        for (_, v) in &theirs {
            let g = gb.get(v.as_tensor()).unwrap().clone();
            gb.insert(v.as_tensor(), (g * 0.25).unwrap());
        }
        a.step(&ga, 0.25).unwrap();
        b.step(&gb).unwrap();
    }
    let (va, vb) = (values(&ours), values(&theirs));
    for (ra, rb) in va.iter().zip(&vb) {
        for (p, q) in ra.iter().zip(rb) {
            assert!((p - q).abs() <= 1e-6 * p.abs().max(1.0));
        }
    }
    assert_ne!(va, before);
}

#[test]
fn adamw_state_round_trips() {
    let (vars, x, y) = problem(3);
    let mut a = AdamW::new(vars.clone(), ParamsAdamW::default()).unwrap();
    a.step(&loss(&vars, &x, &y).backward().unwrap(), 1.0)
        .unwrap();
    let st = a.state_tensors();
    assert_eq!(st.len(), 4);
    let (vars2, _, _) = problem(3);
    let mut b = AdamW::new(vars2, ParamsAdamW::default()).unwrap();
    b.load_state(&st, 1).unwrap();
    for (k, t) in b.state_tensors() {
        let want = st[&k].flatten_all().unwrap().to_vec1::<f32>().unwrap();
        assert_eq!(
            t.flatten_all().unwrap().to_vec1::<f32>().unwrap(),
            want,
            "{k}"
        );
    }
    let mut partial = st.clone();
    partial.remove("m.w");
    assert!(b.load_state(&partial, 1).is_err());
}

#[test]
fn lr_schedule_warmup_then_cosine() {
    let s = LrSchedule {
        base_lr: 1e-3,
        warmup_steps: 10,
        total_steps: 110,
        min_lr: 1e-5,
    };
    assert!((s.lr_at(0) - 1e-4).abs() < 1e-15);
    assert!((s.lr_at(4) - 5e-4).abs() < 1e-15);
    assert!(
        (s.lr_at(10) - 1e-3).abs() < 1e-15,
        "peak right after warm-up"
    );
    // halfway through the cosine: the mean of peak and floor
    assert!((s.lr_at(60) - (1e-3 + 1e-5) / 2.0).abs() < 1e-15);
    let q = 1e-5 + (1e-3 - 1e-5) * 0.5 * (1.0 + (std::f64::consts::PI * 0.25).cos());
    assert!((s.lr_at(35) - q).abs() < 1e-15);
    assert!((s.lr_at(110) - 1e-5).abs() < 1e-15);
    assert!((s.lr_at(10_000) - 1e-5).abs() < 1e-15);
    let no_warm = LrSchedule {
        warmup_steps: 0,
        ..s
    };
    assert!((no_warm.lr_at(0) - 1e-3).abs() < 1e-15);
}

#[test]
fn rng_state_round_trips_mid_stream() {
    use rand::Rng;
    let mut rng = ChaCha8Rng::seed_from_u64(42);
    for _ in 0..37 {
        let _: u32 = rng.random();
    }
    let st = RngState::capture(&rng);
    let mut back = st.restore().unwrap();
    let a: Vec<u64> = (0..10).map(|_| rng.random()).collect();
    let b: Vec<u64> = (0..10).map(|_| back.random()).collect();
    assert_eq!(a, b);
    let json = serde_json::to_string(&st).unwrap();
    let st2: RngState = serde_json::from_str(&json).unwrap();
    assert_eq!(st, st2);
    assert!(
        RngState {
            seed_hex: "zz".into(),
            ..st
        }
        .restore()
        .is_none()
    );
}

#[test]
fn train_config_validation() {
    assert!(TrainConfig::default().validate().is_ok());
    for bad in [
        TrainConfig {
            lr: 0.0,
            ..TrainConfig::default()
        },
        TrainConfig {
            min_lr: 1.0,
            ..TrainConfig::default()
        },
        TrainConfig {
            ema_decay: 1.0,
            ..TrainConfig::default()
        },
        TrainConfig {
            grad_clip_norm: Some(-1.0),
            ..TrainConfig::default()
        },
        TrainConfig {
            cond_drop_prob: 1.5,
            ..TrainConfig::default()
        },
        TrainConfig {
            checkpoint_every: Some(0),
            ..TrainConfig::default()
        },
    ] {
        assert!(bad.validate().is_err(), "{bad:?}");
    }
    let _ = DType::F32;
}

#[test]
fn a_checkpoint_folder_belongs_to_one_run() {
    use crate::trainer::{RUN_RECORD_FILE, claim_checkpoint_dir};
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("ck");
    // values whose JSON text does not parse back to the same float bits must still match
    let settings = serde_json::json!({ "lr": 1e-3, "delta": 1e-6f32, "steps": 7 });
    claim_checkpoint_dir(&dir, &settings).unwrap();
    assert!(dir.join(RUN_RECORD_FILE).is_file());
    claim_checkpoint_dir(&dir, &settings).unwrap();
    let other = serde_json::json!({ "lr": 1e-3, "delta": 1e-6f32, "steps": 8 });
    let e = claim_checkpoint_dir(&dir, &other).unwrap_err().to_string();
    assert!(e.contains("other settings"), "{e}");
    // the record is not replaced by the refused settings
    claim_checkpoint_dir(&dir, &settings).unwrap();
}

/// The core reads its checkpoint JSON itself (it does not depend on `veila-data`), with the same
/// discipline: a folder, an oversized (sparse) file or a FIFO where the run record should be is
/// refused before it is read, naming the file, and nothing is written over it.
#[test]
fn checkpoint_json_is_read_only_from_a_small_regular_file() {
    use crate::trainer::{RUN_RECORD_FILE, checkpoint::MAX_STATE_JSON_BYTES, claim_checkpoint_dir};
    let settings = serde_json::json!({ "steps": 7 });
    let tmp = tempfile::tempdir().unwrap();

    let dir = tmp.path().join("folder");
    std::fs::create_dir_all(dir.join(RUN_RECORD_FILE)).unwrap();
    let e = claim_checkpoint_dir(&dir, &settings)
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("not a regular file") && e.contains(RUN_RECORD_FILE),
        "{e}"
    );
    assert!(dir.join(RUN_RECORD_FILE).is_dir());

    let dir = tmp.path().join("huge");
    std::fs::create_dir_all(&dir).unwrap();
    let f = std::fs::File::create(dir.join(RUN_RECORD_FILE)).unwrap();
    f.set_len(MAX_STATE_JSON_BYTES + 1).unwrap();
    let e = claim_checkpoint_dir(&dir, &settings)
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("more than the cap") && e.contains(RUN_RECORD_FILE),
        "{e}"
    );
    assert_eq!(f.metadata().unwrap().len(), MAX_STATE_JSON_BYTES + 1);

    // a FIFO would block a plain read forever (mkfifo may be missing: then that case is skipped)
    let dir = tmp.path().join("fifo");
    std::fs::create_dir_all(&dir).unwrap();
    let fifo = dir.join(RUN_RECORD_FILE);
    if std::process::Command::new("mkfifo")
        .arg(&fifo)
        .status()
        .is_ok_and(|s| s.success())
    {
        let e = claim_checkpoint_dir(&dir, &settings)
            .unwrap_err()
            .to_string();
        assert!(e.contains("not a regular file"), "{e}");
    } else {
        eprintln!("skipped the FIFO case: `mkfifo` is not available");
    }
}

#[test]
fn an_f32_run_record_is_the_one_written_before_precision_existed() {
    use crate::trainer::{Precision, claim_checkpoint_dir};
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("ck");
    let tc = TrainConfig::default();
    let json = serde_json::to_value(&tc).unwrap();
    // a run record from before the field: the same settings without "precision"
    let mut old = json.clone();
    old.as_object_mut().unwrap().remove("precision");
    // (run keys are JSON values, as `train-default` builds them)
    claim_checkpoint_dir(&dir, &serde_json::json!({ "train": old })).unwrap();
    claim_checkpoint_dir(&dir, &serde_json::json!({ "train": tc })).unwrap();
    // bf16 is recorded, so it does not resume an f32 run's folder
    let bf16 = TrainConfig {
        precision: Precision::Bf16,
        ..TrainConfig::default()
    };
    let e = claim_checkpoint_dir(&dir, &serde_json::json!({ "train": bf16 }))
        .unwrap_err()
        .to_string();
    assert!(e.contains("other settings"), "{e}");
    // both read back
    for c in [&tc, &bf16] {
        let back: TrainConfig = serde_json::from_str(&serde_json::to_string(c).unwrap()).unwrap();
        assert_eq!(back.precision, c.precision);
    }
}

/// A per-pixel offset plus a scale of the input: enough parameters to see gradients differ.
struct Offset {
    scale: Tensor,
    bias: Tensor,
}

impl Denoiser for Offset {
    type Cond = ();
    fn forward(&self, x: &Tensor, _t: &Tensor, _c: Option<&()>) -> candle_core::Result<Tensor> {
        x.broadcast_mul(&self.scale)?.broadcast_add(&self.bias)
    }
}

fn offset_trainer(objective: crate::Objective, total: u64) -> Trainer<Offset> {
    let varmap = VarMap::new();
    let vb = candle_nn::VarBuilder::from_varmap(&varmap, DType::F32, &Device::Cpu);
    let model = Offset {
        scale: vb
            .get_with_hints(1, "scale", candle_nn::Init::Const(0.5))
            .unwrap(),
        bias: vb
            .get_with_hints((1, 2, 2, 4), "bias", candle_nn::Init::Const(0.1))
            .unwrap(),
    };
    let diffusion = Diffusion::new(crate::DiffusionConfig {
        objective,
        ..crate::DiffusionConfig::default()
    })
    .unwrap();
    let config = TrainConfig {
        total_steps: total,
        warmup_steps: 1,
        lr: 0.05,
        // a large eps keeps Adam's first steps from turning rounding-level gradients (an L1
        // gradient whose signs cancel) into full-size moves
        adam_eps: 0.1,
        checkpoint_every: None,
        ..TrainConfig::default()
    };
    Trainer::new(model, varmap, diffusion, config).unwrap()
}

/// The global batch of update `step`: 6 examples whose values depend on the step.
fn global_batch(step: u64) -> Vec<Tensor> {
    (0..6)
        .map(|i| {
            let v: Vec<f32> = (0..16)
                .map(|k| ((i * 16 + k) as f32 * 0.37 + step as f32).sin() * 3.0)
                .collect();
            Tensor::from_vec(v, (1, 2, 2, 4), &Device::Cpu).unwrap()
        })
        .collect()
}

fn weights_of(t: &Trainer<Offset>) -> Vec<f32> {
    let w = t.weights().unwrap();
    let mut names: Vec<&String> = w.keys().collect();
    names.sort();
    names
        .into_iter()
        .flat_map(|n| w[n].flatten_all().unwrap().to_vec1::<f32>().unwrap())
        .collect()
}

/// Runs `world` ranks as threads, each on its shard of every global batch, and returns each
/// rank's weights.
fn data_parallel(objective: crate::Objective, world: usize, steps: u64) -> Vec<Vec<f32>> {
    use distributed::Communicator as _;
    let comms = distributed::InProcessGroup::new(world);
    let handles: Vec<_> = comms
        .into_iter()
        .map(|comm| {
            std::thread::spawn(move || {
                let rank = comm.rank();
                let mut trainer = offset_trainer(objective, steps);
                trainer.set_communicator(Box::new(comm));
                let group = distributed::ProcessGroup {
                    rank,
                    world_size: world,
                    local_rank: rank,
                    master: None,
                };
                let mut data = |step: u64| -> Result<Batch<()>> {
                    let all = global_batch(step);
                    Ok(Batch {
                        x0: Tensor::cat(group.shard(&all), 0)?,
                        cond: None,
                        weight: None,
                    })
                };
                trainer.fit(&mut data, None, &mut ()).unwrap();
                weights_of(&trainer)
            })
        })
        .collect();
    handles.into_iter().map(|h| h.join().unwrap()).collect()
}

#[test]
fn data_parallel_ranks_take_the_single_process_step() {
    use distributed::Communicator as _;
    // regression draws no noise: two or three ranks on shares of the batch must give the weights
    // of one process on the whole batch (the mean of equal shares' mean gradients is the mean)
    let steps = 6;
    let mut single = offset_trainer(crate::Objective::Regression, steps);
    let mut data = |step: u64| -> Result<Batch<()>> {
        Ok(Batch {
            x0: Tensor::cat(&global_batch(step), 0)?,
            cond: None,
            weight: None,
        })
    };
    single.fit(&mut data, None, &mut ()).unwrap();
    let want = weights_of(&single);
    let init = weights_of(&offset_trainer(crate::Objective::Regression, steps));
    assert!(
        want.iter().zip(&init).any(|(a, b)| (a - b).abs() > 1e-3),
        "training moved nothing"
    );
    for world in [2, 3] {
        let ranks = data_parallel(crate::Objective::Regression, world, steps);
        for (r, w) in ranks.iter().enumerate() {
            let err = w
                .iter()
                .zip(&want)
                .map(|(a, b)| (a - b).abs())
                .fold(0f32, f32::max);
            assert!(err < 1e-5, "world {world} rank {r}: max |diff| {err}");
        }
    }
    // with noise (diffusion), ranks draw different noise but stay in step with each other
    let ranks = data_parallel(crate::Objective::Diffusion, 2, steps);
    assert_eq!(ranks[0], ranks[1]);
    // a world of one is the plain trainer
    let mut t = offset_trainer(crate::Objective::Regression, steps);
    let solo = distributed::InProcessGroup::new(1).pop().unwrap();
    assert_eq!(solo.world_size(), 1);
    t.set_communicator(Box::new(solo));
    t.fit(&mut data, None, &mut ()).unwrap();
    assert_eq!(weights_of(&t), want);
}

#[test]
fn part_ranges_tile_the_batch() {
    for b in 1..12 {
        for parts in 1..=b {
            let mut next = 0;
            let mut sizes = Vec::new();
            for k in 0..parts {
                let (start, len) = part_range(b, k, parts).unwrap();
                assert_eq!(start, next, "b {b} parts {parts} part {k}");
                next += len;
                sizes.push(len);
            }
            assert_eq!(next, b);
            let (lo, hi) = (sizes.iter().min().unwrap(), sizes.iter().max().unwrap());
            assert!(*lo >= 1 && hi - lo <= 1, "b {b} parts {parts}: {sizes:?}");
        }
        assert!(part_range(b, 0, b + 1).is_err());
        assert!(part_range(b, b, b).is_err());
    }
}

/// Trains `steps` updates of the offset model on the 6-example global batches with per-element
/// loss weights, accumulating over `parts` parts (optionally on `world` thread ranks, each
/// accumulating over its share); returns rank 0's weights.
fn accumulated(objective: crate::Objective, parts: u64, world: usize, steps: u64) -> Vec<f32> {
    use distributed::Communicator as _;
    let weight_of = |step: u64, x0: &Tensor| -> Tensor {
        // zero weight on some elements, so the parts' weight sums differ
        let v: Vec<f32> = (0..x0.elem_count())
            .map(|k| {
                if (k as u64 + step).is_multiple_of(3) {
                    0.0
                } else {
                    1.0
                }
            })
            .collect();
        Tensor::from_vec(v, x0.shape(), &Device::Cpu).unwrap()
    };
    let run = move |comm: Option<distributed::InProcessGroup>| {
        let mut trainer = offset_trainer(objective, steps);
        let mut config = trainer.config().clone();
        config.grad_accum_steps = parts;
        trainer.set_config(config).unwrap();
        let group = comm.as_ref().map(|c| distributed::ProcessGroup {
            rank: c.rank(),
            world_size: c.world_size(),
            local_rank: c.rank(),
            master: None,
        });
        if let Some(c) = comm {
            trainer.set_communicator(Box::new(c));
        }
        let mut data = |step: u64| -> Result<Batch<()>> {
            let all = global_batch(step);
            let x0 = match &group {
                Some(g) => Tensor::cat(g.shard(&all), 0)?,
                None => Tensor::cat(&all, 0)?,
            };
            let weight = Some(weight_of(step, &x0));
            Ok(Batch {
                x0,
                cond: None,
                weight,
            })
        };
        trainer.fit(&mut data, None, &mut ()).unwrap();
        weights_of(&trainer)
    };
    if world == 1 {
        return run(None);
    }
    let handles: Vec<_> = distributed::InProcessGroup::new(world)
        .into_iter()
        .map(|c| std::thread::spawn(move || run(Some(c))))
        .collect();
    let out: Vec<Vec<f32>> = handles.into_iter().map(|h| h.join().unwrap()).collect();
    assert!(out.iter().all(|w| *w == out[0]), "ranks out of step");
    out[0].clone()
}

#[test]
fn gradient_accumulation_takes_the_whole_batch_step() {
    // regression draws no noise, so accumulating the parts' size-weighted gradients must give the
    // update of the whole batch: 6 examples in 2 equal parts, in 4 unequal ones (2, 2, 1, 1),
    // and in 6 single examples
    let steps = 5;
    let want = accumulated(crate::Objective::Regression, 1, 1, steps);
    let init = weights_of(&offset_trainer(crate::Objective::Regression, steps));
    assert!(
        want.iter().zip(&init).any(|(a, b)| (a - b).abs() > 1e-3),
        "training moved nothing"
    );
    let max_diff = |w: &[f32]| {
        w.iter()
            .zip(&want)
            .map(|(a, b)| (a - b).abs())
            .fold(0f32, f32::max)
    };
    for parts in [2, 4, 6] {
        let got = accumulated(crate::Objective::Regression, parts, 1, steps);
        assert!(
            max_diff(&got) < 1e-5,
            "{parts} parts: max |diff| {}",
            max_diff(&got)
        );
    }
    // with data parallelism: 2 ranks of 3 examples, each in 3 parts of 1
    let got = accumulated(crate::Objective::Regression, 3, 2, steps);
    assert!(
        max_diff(&got) < 1e-5,
        "2 ranks x 3 parts: {}",
        max_diff(&got)
    );
    // diffusion draws noise per part, so it differs from the whole batch, but it trains, and
    // is deterministic
    let a = accumulated(crate::Objective::Diffusion, 2, 1, steps);
    assert!(a.iter().all(|v| v.is_finite()));
    assert_eq!(a, accumulated(crate::Objective::Diffusion, 2, 1, steps));
}

#[test]
fn gradient_accumulation_refuses_what_it_cannot_split() {
    let mut trainer = offset_trainer(crate::Objective::Regression, 2);
    let mut config = trainer.config().clone();
    config.grad_accum_steps = 4;
    trainer.set_config(config.clone()).unwrap();
    // a batch of 3 cannot be split into 4 parts
    let mut small = |_step: u64| -> Result<Batch<()>> {
        Ok(Batch {
            x0: Tensor::zeros((3, 2, 2, 4), DType::F32, &Device::Cpu)?,
            cond: None,
            weight: None,
        })
    };
    let err = trainer.fit(&mut small, None, &mut ()).unwrap_err();
    assert!(err.to_string().contains("grad_accum_steps"), "{err}");
    assert_eq!(trainer.step(), 0);
    config.grad_accum_steps = 0;
    assert!(trainer.set_config(config).is_err());
}

#[test]
fn checkpoint_floats_read_back_to_the_bit() {
    // 0.093989486 read back 1 ulp high with serde_json's default parser (a real training clock
    // of a test run); the workspace enables `float_roundtrip` so a resumed clock is the saved one
    let mut x = 0.093_989_486_f64;
    for _ in 0..2000 {
        let back: f64 = serde_json::from_str(&serde_json::to_string(&x).unwrap()).unwrap();
        assert_eq!(back.to_bits(), x.to_bits(), "{x:e}");
        x = x * 1.000_37 + 1.3e-7;
    }
}

#[test]
fn a_call_without_updates_prints_no_nan_loss() {
    let mut s = FitSummary {
        steps_run: 0,
        final_step: 12,
        mean_loss: f64::NAN,
        skipped: 0,
        stopped_early: false,
        checkpoints: Vec::new(),
        clock: Clock::default(),
    };
    assert_eq!(s.mean_loss_text(), "- (no update this run)");
    s.steps_run = 3;
    s.mean_loss = 0.123_456;
    assert_eq!(s.mean_loss_text(), "0.1235");
}
