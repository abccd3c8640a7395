//! One row of `veila bench` measured in this process: the network, its seeded inputs, the
//! training updates and evaluations, and the row's peak memory (host `VmHWM` or the device's used
//! memory from `nvidia-smi`).

use std::time::Instant;

use anyhow::{Context, Result};
use candle_core::{DType, Device, Tensor};
use candle_nn::{VarBuilder, VarMap};
use rand::{Rng, SeedableRng};
use veila_diffusion::app::{CameraView, GenerateOptions};
use veila_diffusion::trainer::{AdamW, ParamsAdamW};
use veila_geom::{EpipolarConfig, PinholeCamera};
use veila_nn::{ConditionInput, Cues, DenoiserConfig, GcmaGeometry};

use super::args::{BenchArgs, GenerateRow, Row, Spec};
use crate::model;

pub(super) fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

/// A KITTI-like front camera (KITTI object 000000's intrinsics, 1242 x 375) resized to `w x h`.
pub(super) fn kitti_camera(w: usize, h: usize) -> Result<PinholeCamera> {
    let k = [
        [721.54, 0.0, 609.56, 44.86],
        [0.0, 721.54, 172.85, 0.22],
        [0.0, 0.0, 1.0, 0.003],
    ];
    // LiDAR x forward, y left, z up -> camera x right, y down, z forward, 8 cm behind, 27 cm below
    let cam_from_lidar = glam::Mat4::from_cols_array_2d(&[
        [0.0, 0.0, 1.0, 0.0],
        [-1.0, 0.0, 0.0, 0.0],
        [0.0, -1.0, 0.0, 0.0],
        [0.0, -0.08, -0.27, 1.0],
    ]);
    let cam = PinholeCamera::new(k, cam_from_lidar, 1242, 375)
        .context("the benchmark's KITTI-like camera")?;
    cam.resized(w as u32, h as u32)
        .with_context(|| format!("resizing the benchmark's camera to {w} x {h}"))
}

pub(super) fn rand_tensor(
    rng: &mut rand_chacha::ChaCha8Rng,
    shape: &[usize],
    dev: &Device,
) -> Result<Tensor> {
    let n: usize = shape.iter().product();
    let v: Vec<f32> = (0..n).map(|_| rng.random_range(-1.0f32..1.0)).collect();
    Ok(Tensor::from_vec(v, shape, dev)?)
}

/// Random encoder features for `cfg` at batch `b`.
pub(super) fn features(
    cfg: &DenoiserConfig,
    b: usize,
    rng: &mut rand_chacha::ChaCha8Rng,
    dev: &Device,
) -> Result<ConditionInput> {
    let Some(cc) = cfg.conditioning.as_ref() else {
        return Ok(ConditionInput::default());
    };
    let n = b * cc.num_views;
    let (mut sem, mut dep) = (Vec::new(), Vec::new());
    for i in 0..cc.num_scales() {
        let [h, w] = cc.feature_sizes[i];
        sem.push(rand_tensor(rng, &[n, cc.semantic_channels[i], h, w], dev)?);
        dep.push(rand_tensor(rng, &[n, cc.depth_channels[i], h, w], dev)?);
    }
    Ok(ConditionInput {
        semantic: (cc.cues != Cues::DepthOnly).then_some(sem),
        depth: (cc.cues != Cues::SemanticOnly).then_some(dep),
        keep: None,
    })
}

/// The process's resident high-water mark in MiB (`VmHWM`; Linux only).
pub(super) fn vm_hwm_mib() -> Option<f64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let kb = status
        .lines()
        .find_map(|l| l.strip_prefix("VmHWM:"))?
        .trim()
        .trim_end_matches("kB")
        .trim()
        .parse::<f64>()
        .ok()?;
    Some(kb / 1024.0)
}

/// Resets `VmHWM` to the current resident size (Linux 4.0 and later); false where it cannot.
pub(super) fn reset_hwm() -> bool {
    std::fs::write("/proc/self/clear_refs", "5").is_ok()
}

/// The device's used memory, sampled by `nvidia-smi` every 10 ms in a child process until
/// [`Self::stop`]; the maximum in MiB.
pub(super) struct DeviceMemory {
    child: std::process::Child,
    reader: std::thread::JoinHandle<Option<f64>>,
}

impl DeviceMemory {
    /// Starts sampling the GPU of `dev` (`None` for the CPU, or without `nvidia-smi`).
    fn start(dev: &Device) -> Option<Self> {
        use std::io::BufRead;
        let candle_core::DeviceLocation::Cuda { gpu_id } = dev.location() else {
            return None;
        };
        let mut child = std::process::Command::new("nvidia-smi")
            .args([
                "--query-gpu=memory.used",
                "--format=csv,noheader,nounits",
                "-lms",
                "10",
            ])
            .arg(format!("--id={gpu_id}"))
            .stdin(std::process::Stdio::null())
            .stdout(std::process::Stdio::piped())
            .stderr(std::process::Stdio::null())
            .spawn()
            .ok()?;
        let stdout = child.stdout.take()?;
        let reader = std::thread::spawn(move || {
            std::io::BufReader::new(stdout)
                .lines()
                .map_while(std::result::Result::ok)
                .filter_map(|l| l.trim().parse::<f64>().ok())
                .reduce(f64::max)
        });
        // the first sample is the memory before the row
        std::thread::sleep(std::time::Duration::from_millis(50));
        Some(Self { child, reader })
    }

    fn stop(mut self) -> Option<f64> {
        // a last sample after the row's final synchronisation
        std::thread::sleep(std::time::Duration::from_millis(30));
        let _ = self.child.kill();
        let _ = self.child.wait();
        self.reader.join().ok().flatten()
    }
}

/// The network on detached copies of `vm`'s weights: evaluating it builds no graph (as sampling
/// runs), and shares the weights' storage.
pub(super) fn detached_network(
    cfg: &DenoiserConfig,
    vm: &VarMap,
    dev: &Device,
) -> Result<veila_nn::Denoiser> {
    let tensors = vm
        .data()
        .lock()
        .map_err(|_| anyhow::anyhow!("the benchmark's weights are poisoned"))?
        .iter()
        .map(|(n, v)| (n.clone(), v.as_tensor().detach()))
        .collect();
    Ok(veila_nn::Denoiser::new(
        cfg,
        VarBuilder::from_tensors(tensors, DType::F32, dev),
    )?)
}

/// Measures one row (`image_hw`: the encoders' input size its feature sizes come from).
pub(super) fn bench_row(
    cfg: &DenoiserConfig,
    image_hw: (usize, usize),
    spec: Spec<'_>,
    args: &BenchArgs,
    dev: &Device,
) -> Result<Row> {
    let name = spec.model;
    let vm = VarMap::new();
    let mut net = veila_nn::Denoiser::new(
        cfg,
        veila_nn::seeded_var_builder(&vm, args.seed, DType::F32, dev),
    )
    .with_context(|| format!("building the {name} network"))?;
    net.set_recompute_blocks(spec.checkpointing == veila_diffusion::ActivationCheckpointing::Block);
    let params: usize = vm.all_vars().iter().map(|v| v.elem_count()).sum();
    let geom = match cfg.conditioning.as_ref().and_then(|c| c.gcma.as_ref()) {
        Some(_) => {
            let views = cfg.conditioning.as_ref().map_or(1, |c| c.num_views);
            let cams = vec![kitti_camera(image_hw.1, image_hw.0)?; views];
            Some(GcmaGeometry::new(
                cfg,
                &cams,
                &EpipolarConfig::default(),
                dev,
            )?)
        }
        None => None,
    };
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(args.seed);
    let (c, h, w) = (cfg.in_channels, cfg.height(), cfg.width());
    let b = spec.batch;
    let dt = spec.precision.dtype();
    let x = rand_tensor(&mut rng, &[b, c, h, w], dev)?.to_dtype(dt)?;
    let target = rand_tensor(&mut rng, &[b, cfg.out_channels, h, w], dev)?;
    let t = rand_tensor(&mut rng, &[b], dev)?.affine(0.45, 0.5)?;
    let cond = features(cfg, b, &mut rng, dev)?;
    let conditional = cfg.conditioning.is_some();
    // the trainer's optimizer, as `veila train` sets it up (one fused launch on a GPU)
    let named: Vec<(String, candle_core::Var)> = vm
        .data()
        .lock()
        .map_err(|_| anyhow::anyhow!("the VarMap lock is poisoned"))?
        .iter()
        .map(|(k, v)| (k.clone(), v.clone()))
        .collect();
    let mut opt = AdamW::new(
        named,
        ParamsAdamW {
            lr: 1e-5,
            ..ParamsAdamW::default()
        },
    )?;
    opt.set_fused(Some(veila_diffusion::app::nn::fused_adamw()));
    dev.synchronize()?;
    // from here on the row's own memory: weights, optimizer state, inputs and the updates
    let host_peak = !dev.is_cuda() && reset_hwm();
    let sampler = DeviceMemory::start(dev);
    let mut train = Vec::new();
    for i in 0..args.train_runs + 2 {
        dev.synchronize()?;
        let start = Instant::now();
        let prepared = conditional
            .then(|| net.prepare_condition(&cond, geom.as_ref()))
            .transpose()?;
        let y = net.forward(&x, &t, prepared.as_ref())?;
        let loss = (y.to_dtype(DType::F32)? - &target)?.sqr()?.mean_all()?;
        let mut grads = loss.backward()?;
        if let Some(tape) = net.recompute_tape() {
            tape.merge_into(&mut grads)?;
        }
        opt.step(&grads, 1.0)?;
        dev.synchronize()?;
        if i >= 2 {
            train.push(start.elapsed().as_secs_f64());
        }
    }
    let eval_s = if args.no_eval {
        None
    } else {
        let frozen = detached_network(cfg, &vm, dev)?;
        let cond2 = features(cfg, 2, &mut rng, dev)?;
        let x2 = rand_tensor(&mut rng, &[2, c, h, w], dev)?.to_dtype(dt)?;
        let t2 = Tensor::new(&[0.5f32, 0.5], dev)?;
        let prepared = conditional
            .then(|| frozen.prepare_condition(&cond2, geom.as_ref()))
            .transpose()?;
        let mut eval = Vec::new();
        for i in 0..args.forward_runs + 2 {
            dev.synchronize()?;
            let start = Instant::now();
            let y = frozen.forward(&x2, &t2, prepared.as_ref())?;
            dev.synchronize()?;
            drop(y);
            if i >= 2 {
                eval.push(start.elapsed().as_secs_f64());
            }
        }
        Some(median(eval))
    };
    let device_peak = sampler.and_then(DeviceMemory::stop);
    let (peak_memory_mib, peak_memory_source) = match (device_peak, host_peak) {
        (Some(p), _) => (Some(p), "nvidia-smi"),
        (None, true) => (vm_hwm_mib(), "VmHWM"),
        (None, false) => (None, "unavailable"),
    };
    let train_s = median(train);
    Ok(Row {
        model: name.to_string(),
        precision: spec.precision.name().to_string(),
        activation_checkpointing: spec.checkpointing.name().to_string(),
        grid: [h, w],
        params,
        batch: b,
        train_step_ms: train_s * 1e3,
        train_samples_per_s: b as f64 / train_s,
        eval_b2_ms: eval_s.map(|s| s * 1e3),
        sample_s_per_scan: eval_s.map_or_else(Vec::new, |e| {
            args.sample_steps
                .iter()
                .map(|&n| (n, n as f64 * e))
                .collect()
        }),
        peak_memory_mib,
        peak_memory_source: peak_memory_source.to_string(),
    })
}

/// The network and image size of a row.
pub(super) fn network(
    spec: Spec<'_>,
    args: &BenchArgs,
    dev: &Device,
) -> Result<(DenoiserConfig, (usize, usize))> {
    if spec.model == "bundled" {
        let bundle = model::load_bundle(args.model.as_deref(), dev)?;
        let hw = (bundle.config.image_height, bundle.config.image_width);
        Ok((bundle.config.denoiser, hw))
    } else {
        Ok((DenoiserConfig::paper(), (384, 1248)))
    }
}

/// `Bundle::generate` end to end at each step count.
pub(super) fn bench_generate(
    bundle: &veila_diffusion::app::bundle::Bundle,
    args: &BenchArgs,
    dev: &Device,
) -> Result<Vec<GenerateRow>> {
    let (ih, iw) = (bundle.config.image_height, bundle.config.image_width);
    let cam = kitti_camera(iw, ih)?;
    let rgb: Vec<u8> = (0..ih * iw * 3)
        .map(|i| ((i * 7 + i / (iw * 3) * 13) % 256) as u8)
        .collect();
    let views = vec![
        CameraView {
            rgb: &rgb,
            camera: &cam,
        };
        bundle
            .config
            .denoiser
            .conditioning
            .as_ref()
            .map_or(1, |c| c.num_views)
    ];
    let mut out = Vec::new();
    for &steps in &args.sample_steps {
        let mut sampler = bundle.config.sampler.clone();
        sampler.steps = steps;
        let mut opts = GenerateOptions::new(sampler);
        opts.seed = args.seed;
        let mut times = Vec::new();
        for i in 0..3 {
            dev.synchronize()?;
            let start = Instant::now();
            bundle.generate(&views, &opts, |_, _| {})?;
            dev.synchronize()?;
            if i >= 1 {
                times.push(start.elapsed().as_secs_f64());
            }
        }
        out.push(GenerateRow {
            steps,
            seconds_per_scan: median(times),
        });
    }
    Ok(out)
}
