//! Image-encoder benchmarks (time per image, batch 1, random weights, CPU).
//!
//! `cargo bench -p veila-nn --bench encoders_bench`. Sizes: 192x640 is KITTI's 376x1241 at half resolution (the size the
//! encoders see in training), 96x320 a quarter. Depth-Anything-V2-Small runs at 182x616 (13x44
//! patches of 14 px) only with `VEILA_BENCH_PAPER=1` (about a second per image on a small CPU); its
//! 98x322 case always runs. No speed/quality knob here: the table printed after the group lists
//! parameters and output sizes next to the measured mean time.

use std::hint::black_box;
use std::time::{Duration, Instant};

use candle_core::{DType, Device, Tensor};
use candle_nn::VarMap;
use criterion::{Criterion, criterion_group, criterion_main};
use veila_nn::encoders::depth_anything::{DepthAnythingV2Config, DepthAnythingV2Encoder};
use veila_nn::encoders::mit::{MitConfig, MitEncoder};
use veila_nn::encoders::small_cnn::{SmallCnn, SmallCnnConfig};
use veila_nn::encoders::{ImageEncoder, freeze_varmap};
use veila_nn::seeded_var_builder;

fn params(varmap: &VarMap) -> usize {
    varmap.all_vars().iter().map(|v| v.elem_count()).sum()
}

fn frozen(varmap: &VarMap) -> candle_nn::VarBuilder<'static> {
    freeze_varmap(varmap, DType::F32, &Device::Cpu).expect("freeze")
}

fn mean_ms(enc: &dyn ImageEncoder, img: &Tensor, reps: usize) -> f64 {
    let t = Instant::now();
    for _ in 0..reps {
        black_box(enc.forward(img).expect("forward"));
    }
    t.elapsed().as_secs_f64() * 1e3 / reps as f64
}

/// Name, encoder, parameter count, input size.
type Case = (String, Box<dyn ImageEncoder>, usize, (usize, usize));

/// The `encoders` criterion group.
pub fn bench_encoders(c: &mut Criterion) {
    let dev = Device::Cpu;
    let mut cases: Vec<Case> = Vec::new();

    let vm = VarMap::new();
    let mit = MitEncoder::new(
        &MitConfig::mit_b0(),
        seeded_var_builder(&vm, 0, DType::F32, &dev),
    )
    .expect("mit-b0");
    let mit_params = params(&vm);
    let mit: std::sync::Arc<MitEncoder> = std::sync::Arc::new(mit);
    for hw in [(96, 320), (192, 640)] {
        cases.push((
            format!("mit_b0/{}x{}", hw.0, hw.1),
            Box::new(mit.clone()),
            mit_params,
            hw,
        ));
    }

    let vm = VarMap::new();
    let cnn_cfg = SmallCnnConfig::default();
    SmallCnn::new(&cnn_cfg, seeded_var_builder(&vm, 1, DType::F32, &dev)).expect("small cnn");
    let cnn = SmallCnn::new(&cnn_cfg, frozen(&vm)).expect("small cnn");
    let cnn_params = params(&vm);
    let cnn = std::sync::Arc::new(cnn);
    for hw in [(96, 320), (192, 640)] {
        cases.push((
            format!("small_cnn/{}x{}", hw.0, hw.1),
            Box::new(cnn.clone()),
            cnn_params,
            hw,
        ));
    }

    let vm = VarMap::new();
    let da_cfg = DepthAnythingV2Config::small();
    DepthAnythingV2Encoder::new(&da_cfg, seeded_var_builder(&vm, 2, DType::F32, &dev))
        .expect("depth anything");
    let da = DepthAnythingV2Encoder::new(&da_cfg, frozen(&vm)).expect("depth anything");
    let da_params = params(&vm);
    let da = std::sync::Arc::new(da);
    let mut da_sizes = vec![(98, 322)];
    if std::env::var_os("VEILA_BENCH_PAPER").is_some() {
        da_sizes.push((182, 616));
    }
    for hw in da_sizes {
        cases.push((
            format!("depth_anything_v2_small/{}x{}", hw.0, hw.1),
            Box::new(da.clone()),
            da_params,
            hw,
        ));
    }

    let mut group = c.benchmark_group("encoders");
    group
        .sample_size(10)
        .warm_up_time(Duration::from_millis(500))
        .measurement_time(Duration::from_secs(3));
    let mut table = Vec::new();
    for (name, enc, n_params, (h, w)) in &cases {
        // deterministic, image-like input
        let img = Tensor::arange(0u32, (3 * h * w) as u32, &dev)
            .and_then(|t| t.to_dtype(DType::F32))
            .and_then(|t| (t * 0.001)?.sin())
            .and_then(|t| t.reshape((1, 3, *h, *w)))
            .expect("image");
        group.bench_function(name.as_str(), |b| {
            b.iter(|| black_box(enc.forward(&img).expect("forward")))
        });
        let ms = mean_ms(enc.as_ref(), &img, 3);
        table.push(format!(
            "{name:<34} params {:>9}  features {:?}  {ms:>8.1} ms/image",
            n_params,
            enc.feature_sizes(*h, *w)
        ));
    }
    group.finish();
    eprintln!("\nencoder                            parameters  feature sizes  time (3-run mean)");
    for line in table {
        eprintln!("{line}");
    }
}

criterion_group!(benches, bench_encoders);
criterion_main!(benches);
