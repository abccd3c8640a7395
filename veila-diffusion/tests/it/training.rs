//! Trainer behaviour: overfitting, exact resume, checkpoints, callbacks, non-finite steps.

use std::collections::HashMap;
use std::ops::ControlFlow;
use std::path::Path;

use candle_core::{Device, Tensor};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use veila_diffusion::app::nn::read_checkpoint_tensors;
use veila_diffusion::noise::randn;
use veila_diffusion::trainer::find_latest_checkpoint;
use veila_diffusion::{
    Batch, Denoiser, Diffusion, DiffusionConfig, Error, LossWeighting, Prediction, StepStats,
    TimeInput, TrainConfig, TrainLevels, TrainObserver, Trainer,
};

use crate::common::{TinyConfig, TinyNet};

const CFG: TinyConfig = TinyConfig {
    channels: 2,
    hidden: 12,
    cond_dim: 3,
    pos: None,
};

fn diffusion(pred: Prediction) -> Diffusion {
    Diffusion::new(DiffusionConfig {
        prediction: pred,
        time_input: TimeInput::Unit,
        loss_weighting: LossWeighting::MinSnr { gamma: 5.0 },
        ..DiffusionConfig::default()
    })
    .unwrap()
}

fn config(total: u64) -> TrainConfig {
    TrainConfig {
        seed: 17,
        lr: 3e-3,
        min_lr: 1e-4,
        warmup_steps: 3,
        total_steps: total,
        ema_decay: 0.9,
        grad_clip_norm: Some(1.0),
        cond_drop_prob: 0.25,
        checkpoint_every: None,
        keep_checkpoints: None,
        preview_every: None,
        ..TrainConfig::default()
    }
}

/// Step-indexed data: a fresh seeded batch per step, so resumed runs see the same data.
fn source(step: u64) -> veila_diffusion::Result<Batch<Tensor>> {
    let mut rng = ChaCha8Rng::seed_from_u64(1000 + step);
    let x0 = (randn(&mut rng, &[2, 2, 4, 8], &Device::Cpu)? * 0.5)?.tanh()?;
    let cond = randn(&mut rng, &[2, 3], &Device::Cpu)?;
    Ok(Batch {
        x0,
        cond: Some(cond),
        weight: None,
    })
}

fn flat(map: &HashMap<String, Tensor>) -> Vec<(String, Vec<f32>)> {
    let mut v: Vec<_> = map
        .iter()
        .map(|(k, t)| {
            (
                k.clone(),
                t.flatten_all().unwrap().to_vec1::<f32>().unwrap(),
            )
        })
        .collect();
    v.sort_by(|a, b| a.0.cmp(&b.0));
    v
}

#[derive(Default)]
struct Recorder {
    losses: Vec<f64>,
    previews: Vec<(u64, f32)>,
    checkpoints: Vec<u64>,
    stop_at: Option<u64>,
}

impl<M: Denoiser> TrainObserver<M> for Recorder {
    fn on_step(&mut self, s: &StepStats) -> ControlFlow<()> {
        assert!(s.samples_per_sec > 0.0 && s.lr > 0.0);
        self.losses.push(s.loss);
        if self.stop_at == Some(s.step) {
            ControlFlow::Break(())
        } else {
            ControlFlow::Continue(())
        }
    }
    fn on_preview(&mut self, step: u64, model: &M, _d: &Diffusion) -> veila_diffusion::Result<()> {
        let _ = model;
        self.previews.push((step, 0.0));
        Ok(())
    }
    fn on_checkpoint(&mut self, step: u64, path: &Path) {
        assert!(path.join("state.json").is_file());
        self.checkpoints.push(step);
    }
}

fn trainer(total: u64, tag: &str) -> Trainer<TinyNet> {
    let (net, vm) = TinyNet::build(CFG, tag);
    Trainer::new(net, vm, diffusion(Prediction::Epsilon), config(total)).unwrap()
}

#[test]
fn tiny_model_overfits_one_sample() {
    let cfg = TinyConfig {
        channels: 2,
        hidden: 16,
        cond_dim: 0,
        pos: Some((8, 32)),
    };
    let (net, vm) = TinyNet::build(cfg, "net");
    let d = Diffusion::new(DiffusionConfig {
        prediction: Prediction::Sample,
        loss_weighting: LossWeighting::Uniform,
        ..DiffusionConfig::default()
    })
    .unwrap();
    let mut t = Trainer::new(
        net,
        vm,
        d,
        TrainConfig {
            lr: 1e-2,
            min_lr: 1e-3,
            warmup_steps: 10,
            total_steps: 150,
            ema_decay: 0.0,
            cond_drop_prob: 0.0,
            checkpoint_every: None,
            ..TrainConfig::default()
        },
    )
    .unwrap();
    // one range-image-like sample: smooth rows plus a ray-drop channel, batch of 8 copies
    let x: Vec<f32> = (0..2 * 8 * 32)
        .map(|i| {
            let (c, r, col) = (i / 256, (i / 32) % 8, i % 32);
            if c == 0 {
                ((r as f32 * 0.7 + col as f32 * 0.2).sin()) * 0.8
            } else if (r + col) % 5 == 0 {
                -1.0
            } else {
                1.0
            }
        })
        .collect();
    let x0 = Tensor::from_vec(x, (1, 2, 8, 32), &Device::Cpu)
        .unwrap()
        .repeat((4, 1, 1, 1))
        .unwrap();
    let mut rec = Recorder::default();
    let mut src = |_step: u64| -> veila_diffusion::Result<Batch<Tensor>> {
        Ok(Batch {
            x0: x0.clone(),
            cond: None,
            weight: None,
        })
    };
    let summary = t.fit(&mut src, None, &mut rec).unwrap();
    assert_eq!(summary.steps_run, 150);
    let first: f64 = rec.losses[..10].iter().sum::<f64>() / 10.0;
    let last: f64 = rec.losses[rec.losses.len() - 10..].iter().sum::<f64>() / 10.0;
    eprintln!(
        "overfit: loss {first:.4} -> {last:.5} ({:.0}x)",
        first / last
    );
    assert!(first / last > 20.0, "loss fell only from {first} to {last}");
}

#[test]
fn resume_is_exact() {
    let dir = tempfile::tempdir().unwrap();
    // straight: 6 steps
    let mut a = trainer(6, "net");
    let mut rec_a = Recorder::default();
    a.fit(&mut source, None, &mut rec_a).unwrap();

    // 3 steps, checkpoint, new trainer with different initial weights, load, 3 more
    let mut b = trainer(6, "net");
    let mut rec_b = Recorder {
        stop_at: Some(3),
        ..Default::default()
    };
    b.fit(&mut source, Some(dir.path()), &mut rec_b).unwrap();
    assert_eq!(rec_b.checkpoints, vec![3]);
    let ckpt = find_latest_checkpoint(dir.path()).unwrap().unwrap();
    let mut c = trainer(6, "other_init");
    // different names: loading must fail and say which tensors do not match
    let err = c
        .load_checkpoint(&ckpt, read_checkpoint_tensors)
        .unwrap_err();
    assert!(matches!(err, Error::Checkpoint { .. }), "{err}");
    assert!(err.to_string().contains("missing [other_init."), "{err}");
    let (net, vm) = TinyNet::build_seeded(CFG, "net", 99);
    let mut c = Trainer::new(net, vm, diffusion(Prediction::Epsilon), config(6)).unwrap();
    assert_ne!(
        flat(&c.weights().unwrap()),
        flat(&b.weights().unwrap()),
        "fresh trainer starts elsewhere"
    );
    assert_eq!(
        c.resume_latest(dir.path(), read_checkpoint_tensors)
            .unwrap(),
        Some(ckpt.clone())
    );
    assert_eq!(c.step(), 3);
    let mut rec_c = Recorder::default();
    c.fit(&mut source, None, &mut rec_c).unwrap();

    assert_eq!(c.step(), 6);
    assert_eq!(&rec_a.losses[..3], &rec_b.losses[..]);
    assert_eq!(
        &rec_a.losses[3..],
        &rec_c.losses[..],
        "same losses after resume"
    );
    assert_eq!(
        flat(&a.weights().unwrap()),
        flat(&c.weights().unwrap()),
        "identical weights"
    );
    assert_eq!(
        flat(&a.ema_weights()),
        flat(&c.ema_weights()),
        "identical EMA"
    );
    // and the EMA is not simply the weights
    assert_ne!(flat(&a.weights().unwrap()), flat(&a.ema_weights()));
}

/// A checkpoint resumes under another loss weighting or other training levels (they only say
/// where updates go), and is refused under another process: a network trained to predict ε does
/// not resume as one predicting `v`.
#[test]
fn a_run_goes_on_with_other_training_levels_but_not_another_process() {
    let dir = tempfile::tempdir().unwrap();
    let mut a = trainer(6, "net");
    let mut rec = Recorder {
        stop_at: Some(3),
        ..Default::default()
    };
    a.fit(&mut source, Some(dir.path()), &mut rec).unwrap();
    let ckpt = find_latest_checkpoint(dir.path()).unwrap().unwrap();
    let with = |cfg: DiffusionConfig| {
        let (net, vm) = TinyNet::build_seeded(CFG, "net", 99);
        Trainer::new(net, vm, Diffusion::new(cfg).unwrap(), config(6)).unwrap()
    };
    let base = diffusion(Prediction::Epsilon).config().clone();

    let mut clean = with(DiffusionConfig {
        loss_weighting: LossWeighting::Uniform,
        train_levels: TrainLevels::clean_share(0.5),
        ..base.clone()
    });
    clean
        .load_checkpoint(&ckpt, read_checkpoint_tensors)
        .unwrap();
    assert_eq!(clean.step(), 3);
    assert_eq!(flat(&clean.weights().unwrap()), flat(&a.weights().unwrap()));
    // it trains on under its own levels, and its next checkpoint records them
    let mut rec_c = Recorder::default();
    clean.fit(&mut source, None, &mut rec_c).unwrap();
    assert_eq!(clean.step(), 6);
    assert_eq!(
        clean.diffusion().config().train_levels,
        TrainLevels::clean_share(0.5)
    );

    for (what, cfg) in [
        (
            "prediction",
            DiffusionConfig {
                prediction: Prediction::V,
                ..base.clone()
            },
        ),
        (
            "time input",
            DiffusionConfig {
                time_input: TimeInput::LogSnr,
                ..base.clone()
            },
        ),
    ] {
        let mut other = with(cfg);
        let before = flat(&other.weights().unwrap());
        let err = other
            .load_checkpoint(&ckpt, read_checkpoint_tensors)
            .unwrap_err();
        assert!(
            err.to_string().contains("diffusion process"),
            "{what}: {err}"
        );
        assert_eq!(other.step(), 0, "{what}");
        assert_eq!(
            flat(&other.weights().unwrap()),
            before,
            "{what}: nothing loaded"
        );
    }
}

/// The training clock counts batch assembly and updates (not what observers do), travels in
/// the checkpoints, and after a checkpoint from a build without a clock counts from that step.
#[test]
fn the_training_clock_survives_resume_and_skips_observer_time() {
    struct Slow(u64);
    impl<M: Denoiser> TrainObserver<M> for Slow {
        fn on_step(&mut self, s: &StepStats) -> ControlFlow<()> {
            std::thread::sleep(std::time::Duration::from_millis(400));
            if s.step == self.0 {
                ControlFlow::Break(())
            } else {
                ControlFlow::Continue(())
            }
        }
    }
    let nap = std::time::Duration::from_millis(30);
    let mut slow_source = |step: u64| {
        std::thread::sleep(nap);
        source(step)
    };
    let dir = tempfile::tempdir().unwrap();
    let mut b = trainer(4, "net");
    let s = b
        .fit(&mut slow_source, Some(dir.path()), &mut Slow(2))
        .unwrap();
    assert_eq!(s.clock.from_step, 0);
    // two batches took at least 2 naps; the observer's 2 x 400 ms are not training time
    assert!(s.clock.seconds >= 0.06, "{:?}", s.clock);
    assert!(
        s.clock.seconds < 0.8,
        "observer time counted: {:?}",
        s.clock
    );
    let ckpt = find_latest_checkpoint(dir.path()).unwrap().unwrap();
    let state: serde_json::Value =
        serde_json::from_slice(&std::fs::read(ckpt.join("state.json")).unwrap()).unwrap();
    assert_eq!(state["train_seconds"].as_f64(), Some(s.clock.seconds));

    let mut c = trainer(4, "net");
    c.resume_latest(dir.path(), read_checkpoint_tensors)
        .unwrap();
    assert_eq!(c.clock(), s.clock, "the clock is restored");
    let s2 = c.fit(&mut slow_source, None, &mut ()).unwrap();
    assert!(s2.clock.seconds >= s.clock.seconds + 0.06, "{:?}", s2.clock);
    assert_eq!(s2.clock.from_step, 0);

    // a checkpoint without the clock fields (an older build): counting starts at its step
    let mut state = state;
    let obj = state.as_object_mut().unwrap();
    obj.remove("train_seconds");
    obj.remove("clock_from_step");
    std::fs::write(ckpt.join("state.json"), serde_json::to_vec(&state).unwrap()).unwrap();
    let mut d = trainer(4, "net");
    d.resume_latest(dir.path(), read_checkpoint_tensors)
        .unwrap();
    assert_eq!(d.clock().from_step, 2);
    assert_eq!(d.clock().seconds, 0.0);
    let s3 = d.fit(&mut slow_source, None, &mut ()).unwrap();
    assert_eq!(s3.clock.from_step, 2);
    assert!(s3.clock.seconds >= 0.06, "{:?}", s3.clock);
}

#[test]
fn checkpoints_are_atomic_complete_and_pruned() {
    let dir = tempfile::tempdir().unwrap();
    let (net, vm) = TinyNet::build(CFG, "net");
    let mut cfg = config(7);
    cfg.checkpoint_every = Some(2);
    cfg.keep_checkpoints = Some(2);
    cfg.preview_every = Some(3);
    let mut t = Trainer::new(net, vm, diffusion(Prediction::V), cfg).unwrap();
    let mut rec = Recorder::default();
    let summary = t.fit(&mut source, Some(dir.path()), &mut rec).unwrap();
    assert_eq!(
        rec.checkpoints,
        vec![2, 4, 6, 7],
        "every 2 steps and at the end"
    );
    assert_eq!(summary.checkpoints.len(), 4);
    assert_eq!(
        rec.previews.iter().map(|p| p.0).collect::<Vec<_>>(),
        vec![3, 6]
    );
    let mut names: Vec<String> = std::fs::read_dir(dir.path())
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    names.sort();
    assert_eq!(
        names,
        vec!["step-0000000006", "step-0000000007"],
        "pruned, no temporaries left"
    );
    let last = dir.path().join("step-0000000007");
    for f in [
        "model.safetensors",
        "ema.safetensors",
        "optimizer.safetensors",
        "state.json",
    ] {
        assert!(last.join(f).is_file(), "{f}");
    }
    // leftovers of an interrupted save are never taken for a checkpoint
    let tmp = dir.path().join(".step-0000000099.tmp-1");
    std::fs::create_dir(&tmp).unwrap();
    std::fs::write(tmp.join("state.json"), b"{}").unwrap();
    std::fs::create_dir(dir.path().join("step-0000000098")).unwrap();
    assert_eq!(
        find_latest_checkpoint(dir.path()).unwrap(),
        Some(last.clone())
    );
    // the EMA file loads straight into a VarMap of the same model
    let (_net2, mut vm2) = TinyNet::build(CFG, "net");
    vm2.load(last.join("ema.safetensors")).unwrap();

    // broken checkpoints are reported with the file, and leave the trainer untouched
    let before = flat(&t.weights().unwrap());
    std::fs::write(last.join("state.json"), b"{ not json").unwrap();
    let err = t
        .load_checkpoint(&last, read_checkpoint_tensors)
        .unwrap_err();
    assert!(err.to_string().contains("state.json"), "{err}");
    let six = dir.path().join("step-0000000006");
    std::fs::remove_file(six.join("optimizer.safetensors")).unwrap();
    let err = t
        .load_checkpoint(&six, read_checkpoint_tensors)
        .unwrap_err();
    assert!(err.to_string().contains("optimizer.safetensors"), "{err}");
    assert_eq!(flat(&t.weights().unwrap()), before);
    // a model of another shape: mis-shaped tensors are named
    let (net3, vm3) = TinyNet::build(TinyConfig { hidden: 5, ..CFG }, "net");
    let mut t3 = Trainer::new(net3, vm3, diffusion(Prediction::V), config(7)).unwrap();
    let t_good = {
        let (n, v) = TinyNet::build(CFG, "net");
        Trainer::new(n, v, diffusion(Prediction::V), config(7)).unwrap()
    };
    let good = t_good.save_checkpoint(&dir.path().join("other")).unwrap();
    let err = t3
        .load_checkpoint(&good, read_checkpoint_tensors)
        .unwrap_err();
    assert!(
        err.to_string()
            .contains("mis-shaped [net.cond.bias [24] (model [10])"),
        "{err}"
    );
    // a different diffusion process is refused
    let (n4, v4) = TinyNet::build(CFG, "net");
    let mut t4 = Trainer::new(n4, v4, diffusion(Prediction::Epsilon), config(7)).unwrap();
    assert!(
        t4.load_checkpoint(&good, read_checkpoint_tensors)
            .unwrap_err()
            .to_string()
            .contains("diffusion process")
    );
}

/// `file` of the checkpoint `ckpt` rewritten with `edit` applied to its tensors.
fn tamper(ckpt: &Path, file: &str, edit: impl FnOnce(&mut HashMap<String, Tensor>)) {
    let p = ckpt.join(file);
    let mut t = candle_core::safetensors::load(&p, &Device::Cpu).unwrap();
    edit(&mut t);
    candle_core::safetensors::save(&t, &p).unwrap();
}

/// Checkpoint weights get the checks of a model bundle's (issue 58): a float dtype, finite values
/// within `MAX_ABS_WEIGHT`, a regular file under the cap, named in the error; the trainer is left
/// as it was.
#[test]
fn checkpoint_weights_are_checked_as_a_bundles_are() {
    let dir = tempfile::tempdir().unwrap();
    let t = trainer(4, "net");
    let good = t.save_checkpoint(dir.path()).unwrap();
    let copy = |name: &str| -> std::path::PathBuf {
        let to = dir.path().join(name);
        std::fs::create_dir_all(&to).unwrap();
        for e in std::fs::read_dir(&good).unwrap() {
            let e = e.unwrap();
            std::fs::copy(e.path(), to.join(e.file_name())).unwrap();
        }
        to
    };
    let name = "net.conv_in.weight";
    let mut fresh = trainer(4, "net");
    let before = flat(&fresh.weights().unwrap());
    let refused = |fresh: &mut Trainer<TinyNet>, ckpt: &Path, words: &[&str]| {
        let e = fresh
            .load_checkpoint(ckpt, read_checkpoint_tensors)
            .unwrap_err()
            .to_string();
        for w in words {
            assert!(e.contains(w), "`{w}` not in: {e}");
        }
    };
    // a NaN, a 3e38 and an integer tensor in the weights, the EMA and the optimizer state
    let nan = copy("nan");
    tamper(&nan, "model.safetensors", |m| {
        let w = m.get_mut(name).unwrap();
        *w = (w.ones_like().unwrap() * f64::NAN).unwrap();
    });
    refused(
        &mut fresh,
        &nan,
        &["model.safetensors", name, "must be finite"],
    );
    let huge = copy("huge");
    tamper(&huge, "ema.safetensors", |m| {
        let w = m.get_mut(name).unwrap();
        *w = (w.ones_like().unwrap() * 3e38).unwrap();
    });
    refused(
        &mut fresh,
        &huge,
        &["ema.safetensors", name, "beyond the limit"],
    );
    let ints = copy("ints");
    let moment = format!("v.{name}");
    tamper(&ints, "optimizer.safetensors", |m| {
        let w = m.get_mut(&moment).unwrap();
        *w = w.to_dtype(candle_core::DType::U8).unwrap();
    });
    refused(
        &mut fresh,
        &ints,
        &["optimizer.safetensors", &moment, "stored as U8"],
    );
    // an optimizer state with a tensor the model lacks is a mismatch, as the weights' are
    let extra = copy("extra");
    tamper(&extra, "optimizer.safetensors", |m| {
        let w = m[&moment].clone();
        m.insert("m.net.ghost".into(), w);
    });
    refused(
        &mut fresh,
        &extra,
        &["optimizer.safetensors", "unexpected [m.net.ghost]"],
    );
    // a link to /dev/zero is refused unread, at once
    #[cfg(unix)]
    {
        let zero = copy("zero");
        std::fs::remove_file(zero.join("ema.safetensors")).unwrap();
        std::os::unix::fs::symlink("/dev/zero", zero.join("ema.safetensors")).unwrap();
        let t0 = std::time::Instant::now();
        refused(&mut fresh, &zero, &["ema.safetensors", "regular file"]);
        assert!(t0.elapsed().as_secs() < 5);
    }
    assert_eq!(
        flat(&fresh.weights().unwrap()),
        before,
        "nothing was loaded"
    );
    fresh
        .load_checkpoint(&good, read_checkpoint_tensors)
        .unwrap();
    assert_eq!(flat(&fresh.weights().unwrap()), flat(&t.weights().unwrap()));
}

#[test]
fn previews_see_ema_weights_and_training_weights_come_back() {
    struct Check {
        seen: usize,
    }
    impl TrainObserver<TinyNet> for Check {
        fn on_preview(
            &mut self,
            _s: u64,
            model: &TinyNet,
            _d: &Diffusion,
        ) -> veila_diffusion::Result<()> {
            let _ = model;
            self.seen += 1;
            Ok(())
        }
    }
    let mut t = trainer(4, "net");
    t.fit(&mut source, None, &mut Check { seen: 0 }).unwrap();
    let w = flat(&t.weights().unwrap());
    let e = flat(&t.ema_weights());
    // inside with_ema_weights the variables hold the EMA
    let inside = t
        .with_ema_weights(|_| Ok(flat(&t.weights().unwrap())))
        .unwrap();
    assert_eq!(inside, e);
    assert_eq!(flat(&t.weights().unwrap()), w, "restored");
    // EMA math for one update without warm-up: e1 = d·w0 + (1 − d)·w1
    let (net, vm) = TinyNet::build(CFG, "net");
    let mut cfg = config(1);
    cfg.ema_warmup = false;
    cfg.ema_decay = 0.75;
    let mut t = Trainer::new(net, vm, diffusion(Prediction::Epsilon), cfg).unwrap();
    let w0 = flat(&t.weights().unwrap());
    t.train_step(&source(0).unwrap()).unwrap();
    let w1 = flat(&t.weights().unwrap());
    let e1 = flat(&t.ema_weights());
    for ((a, b), c) in w0.iter().zip(&w1).zip(&e1) {
        for i in 0..a.1.len() {
            let want = 0.75 * a.1[i] + 0.25 * b.1[i];
            assert!((c.1[i] - want).abs() < 1e-6);
        }
    }
}

#[test]
fn non_finite_steps_are_skipped_or_fail_and_early_stop_works() {
    let mut t = trainer(10, "net");
    let before = flat(&t.weights().unwrap());
    let nan = Batch {
        x0: Tensor::full(f32::NAN, (2, 2, 4, 8), &Device::Cpu).unwrap(),
        cond: None,
        weight: None,
    };
    let s = t.train_step(&nan).unwrap();
    assert!(s.skipped && !s.loss.is_finite());
    assert_eq!(t.skipped_steps(), 1);
    assert_eq!(
        flat(&t.weights().unwrap()),
        before,
        "no update on a NaN loss"
    );
    let mut cfg = config(10);
    cfg.skip_non_finite = false;
    let (net, vm) = TinyNet::build(CFG, "net");
    let mut strict = Trainer::new(net, vm, diffusion(Prediction::Epsilon), cfg).unwrap();
    assert!(matches!(
        strict.train_step(&nan),
        Err(Error::NonFinite { what: "loss", .. })
    ));

    let mut rec = Recorder {
        stop_at: Some(4),
        ..Default::default()
    };
    let sum = t.fit(&mut source, None, &mut rec).unwrap();
    assert!(sum.stopped_early);
    assert_eq!(t.step(), 4);
    // gradient clipping is reported against the true global norm
    let s = t.train_step(&source(4).unwrap()).unwrap();
    assert!(s.grad_norm.is_finite() && s.grad_norm > 0.0);
    assert_eq!(s.clipped, s.grad_norm > 1.0);
}
