//! veila-nn benchmarks: denoiser forward time per step and GCMA cost against the number of epipolar
//! samples K (with the output difference to K = 32 printed next to the time).
//!
//! `cargo bench -p veila-nn` (set `VEILA_BENCH_PAPER=1` to include the paper-sized model, which takes
//! several seconds per step on a small CPU).
#![allow(clippy::excessive_precision)]

use std::hint::black_box;
use std::time::{Duration, Instant};

use candle_core::{DType, Device, Tensor};
use candle_nn::VarMap;
use criterion::{Criterion, criterion_group, criterion_main};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use veila_geom::{DepthSpacing, EpipolarConfig, LidarSensor, PinholeCamera};
use veila_nn::{
    ConditionInput, Cues, Denoiser, DenoiserConfig, Gcma, GcmaGeometry, seeded_var_builder,
};

fn kitti_camera(w: u32, h: u32) -> PinholeCamera {
    let (sx, sy) = (w as f32 / 1241.0, h as f32 / 376.0);
    let p2 = [
        [718.856 * sx, 0.0, 607.1928 * sx, 45.38225 * sx],
        [0.0, 718.856 * sy, 185.2157 * sy, -0.1130887 * sy],
        [0.0, 0.0, 1.0, 0.003779761],
    ];
    let tr = [
        [4.276802e-04, -9.999672e-01, -8.084492e-03, -1.198460e-02],
        [-7.210627e-03, 8.081198e-03, -9.999413e-01, -5.403985e-02],
        [9.999739e-01, 4.859486e-04, -7.206934e-03, -2.921969e-01],
    ];
    PinholeCamera::from_kitti_odometry(p2, tr, w, h).expect("camera")
}

fn epi(k: usize) -> EpipolarConfig {
    EpipolarConfig {
        num_samples: k,
        near_m: 2.0,
        far_m: 80.0,
        spacing: DepthSpacing::Log,
        tau_m: 40.0,
    }
}

fn rand_t(rng: &mut ChaCha8Rng, shape: &[usize]) -> Tensor {
    let n: usize = shape.iter().product();
    Tensor::from_vec(
        (0..n)
            .map(|_| rng.random_range(-1.0f32..1.0))
            .collect::<Vec<_>>(),
        shape,
        &Device::Cpu,
    )
    .expect("tensor")
}

/// Image size whose pyramid is `cfg`'s feature sizes (stride-4 level times 4).
fn image_size(cfg: &DenoiserConfig) -> (u32, u32) {
    let [h, w] = cfg
        .conditioning
        .as_ref()
        .expect("conditional")
        .feature_sizes[0];
    ((w * 4) as u32, (h * 4) as u32)
}

struct Setup {
    net: Denoiser,
    geom: Option<GcmaGeometry>,
    input: Option<ConditionInput>,
    x: Tensor,
    t: Tensor,
}

fn setup(cfg: &DenoiserConfig, k: usize) -> Setup {
    let dev = Device::Cpu;
    let vm = VarMap::new();
    let net = Denoiser::new(cfg, seeded_var_builder(&vm, 0, DType::F32, &dev)).expect("model");
    let mut rng = ChaCha8Rng::seed_from_u64(1);
    let x = rand_t(&mut rng, &[1, cfg.in_channels, cfg.height(), cfg.width()]);
    let t = Tensor::new(&[0.5f32], &dev).expect("t");
    let (geom, input) = match &cfg.conditioning {
        None => (None, None),
        Some(cc) => {
            let (w, h) = image_size(cfg);
            let geom = cc.gcma.as_ref().map(|_| {
                GcmaGeometry::new(cfg, &[kitti_camera(w, h)], &epi(k), &dev).expect("geom")
            });
            let sem = (0..cc.num_scales())
                .map(|i| {
                    rand_t(
                        &mut rng,
                        &[
                            1,
                            cc.semantic_channels[i],
                            cc.feature_sizes[i][0],
                            cc.feature_sizes[i][1],
                        ],
                    )
                })
                .collect();
            let dep = (0..cc.num_scales())
                .map(|i| {
                    rand_t(
                        &mut rng,
                        &[
                            1,
                            cc.depth_channels[i],
                            cc.feature_sizes[i][0],
                            cc.feature_sizes[i][1],
                        ],
                    )
                })
                .collect();
            let input = ConditionInput {
                semantic: (cc.cues != Cues::DepthOnly).then_some(sem),
                depth: (cc.cues != Cues::SemanticOnly).then_some(dep),
                keep: None,
            };
            (geom, Some(input))
        }
    };
    Setup {
        net,
        geom,
        input,
        x,
        t,
    }
}

fn at_resolution(mut cfg: DenoiserConfig, rows: u32, cols: u32) -> DenoiserConfig {
    cfg.sensor = LidarSensor {
        rows,
        cols,
        ..cfg.sensor
    };
    cfg
}

fn bench_forward(c: &mut Criterion) {
    let mut group = c.benchmark_group("denoiser_forward");
    group
        .sample_size(10)
        .warm_up_time(Duration::from_millis(500))
        .measurement_time(Duration::from_secs(3));
    let mut cases = vec![];
    for (rows, cols) in [(32u32, 512u32), (64, 1024)] {
        cases.push((
            format!("tiny_uncond_{rows}x{cols}"),
            at_resolution(DenoiserConfig::tiny().unconditional(), rows, cols),
        ));
        cases.push((
            format!("tiny_full_{rows}x{cols}"),
            at_resolution(DenoiserConfig::tiny(), rows, cols),
        ));
    }
    if std::env::var("VEILA_BENCH_PAPER").is_ok() {
        cases.push((
            "paper_uncond_64x1024".into(),
            DenoiserConfig::paper().unconditional(),
        ));
        cases.push(("paper_full_64x1024".into(), DenoiserConfig::paper()));
    }
    for (name, cfg) in cases {
        let k = 16;
        let s = setup(&cfg, k);
        let prepared = s.input.as_ref().map(|i| {
            s.net
                .prepare_condition(i, s.geom.as_ref())
                .expect("prepare")
        });
        let params = veila_nn::checkpoint::parameter_count(&cfg).expect("count");
        eprintln!("{name}: {:.2} M parameters, K = {k}", params as f64 / 1e6);
        group.bench_function(&name, |b| {
            b.iter(|| {
                black_box(
                    s.net
                        .forward(&s.x, &s.t, prepared.as_ref())
                        .expect("forward"),
                )
            })
        });
    }
    group.finish();
}

fn bench_gcma_k(c: &mut Criterion) {
    let cfg = DenoiserConfig::tiny();
    let cc = cfg.conditioning.clone().expect("conditional");
    let g = cc.gcma.clone().expect("gcma");
    let dev = Device::Cpu;
    let level = 0;
    let ch = cfg.level_channels(level);
    let fc = cc.cond_channels[0];
    let [fh, fw] = cc.feature_sizes[0];
    let (w, h) = image_size(&cfg);
    let gcma = Gcma::new(
        &g,
        ch,
        fc,
        cfg.norm_groups,
        seeded_var_builder(&VarMap::new(), 3, DType::F32, &dev),
    )
    .expect("gcma");
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    let r = rand_t(&mut rng, &[1, ch, cfg.height(), cfg.width()]);
    // smooth image features (a few low-frequency waves), so the K-dependence is a discretisation error
    let mut f = vec![0f32; fc * fh * fw];
    for c in 0..fc {
        let (a, b, p) = (
            rng.random_range(0.5f32..3.0),
            rng.random_range(0.5f32..3.0),
            rng.random_range(0.0f32..std::f32::consts::TAU),
        );
        for y in 0..fh {
            for x in 0..fw {
                f[(c * fh + y) * fw + x] = (a * x as f32 / fw as f32 * std::f32::consts::TAU
                    + b * y as f32 / fh as f32 * std::f32::consts::TAU
                    + p)
                    .sin();
            }
        }
    }
    let feat = Tensor::from_vec(f, (1, fc, fh, fw), &dev).expect("feat");
    let reference = {
        let geom = GcmaGeometry::new(&cfg, &[kitti_camera(w, h)], &epi(32), &dev).expect("geom");
        gcma.attend(&r, &feat, geom.level(level).expect("level"))
            .expect("attend")
    };
    let ref_norm = reference
        .sqr()
        .and_then(|t| t.sum_all())
        .and_then(|t| t.to_scalar::<f32>())
        .expect("norm")
        .sqrt();
    let mut group = c.benchmark_group("gcma_level0_32x512");
    group
        .sample_size(10)
        .warm_up_time(Duration::from_millis(300))
        .measurement_time(Duration::from_secs(2));
    eprintln!(
        "\nGCMA at level 0 of tiny (32x512 range, {fh}x{fw} features, d = {}):",
        g.attn_dim
    );
    eprintln!(
        "{:>4} {:>10} {:>14} {:>24}",
        "K", "active px", "ms/call", "rel. L2 diff vs K=32"
    );
    for k in [8usize, 16, 32] {
        let geom = GcmaGeometry::new(&cfg, &[kitti_camera(w, h)], &epi(k), &dev).expect("geom");
        let lg = geom.level(level).expect("level");
        let out = gcma.attend(&r, &feat, lg).expect("attend");
        let diff = (&out - &reference)
            .and_then(|d| d.sqr())
            .and_then(|d| d.sum_all())
            .and_then(|d| d.to_scalar::<f32>())
            .expect("diff")
            .sqrt();
        let t0 = Instant::now();
        let n = 5;
        for _ in 0..n {
            black_box(gcma.attend(&r, &feat, lg).expect("attend"));
        }
        let ms = t0.elapsed().as_secs_f64() * 1e3 / n as f64;
        eprintln!(
            "{k:>4} {:>10} {ms:>14.2} {:>24.4}",
            lg.num_active(),
            diff / ref_norm
        );
        group.bench_function(format!("K{k}"), |b| {
            b.iter(|| black_box(gcma.attend(&r, &feat, lg).expect("attend")))
        });
    }
    group.finish();
}

criterion_group!(benches, bench_forward, bench_gcma_k);
criterion_main!(benches);
