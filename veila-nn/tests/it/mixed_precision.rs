//! Mixed precision: the denoiser runs in the dtype of its input. With f32 weights and bf16 (or
//! f16) activations every layer casts its weights to the activations' dtype at use, the
//! normalisations and softmaxes run in f32, and the gradients flow back through the casts into
//! the f32 master weights. Compared with the same network in f32.

use crate::common::*;
use candle_core::{DType, Device, Tensor};
use candle_nn::VarMap;
use veila_nn::{ConditionInput, Cues, DenoiserConfig, GcmaGeometry};

/// Relative L2 distance `|a - b| / |b|`, both read as f32.
fn rel_l2(a: &Tensor, b: &Tensor) -> f64 {
    let a = a.to_dtype(DType::F32).unwrap().flatten_all().unwrap();
    let b = b.to_dtype(DType::F32).unwrap().flatten_all().unwrap();
    let a = a.to_vec1::<f32>().unwrap();
    let b = b.to_vec1::<f32>().unwrap();
    assert_eq!(a.len(), b.len());
    let num: f64 = a
        .iter()
        .zip(&b)
        .map(|(x, y)| (f64::from(*x) - f64::from(*y)).powi(2))
        .sum();
    let den: f64 = b.iter().map(|y| f64::from(*y).powi(2)).sum();
    (num / den).sqrt()
}

struct Setup {
    vm: VarMap,
    net: veila_nn::Denoiser,
    geom: GcmaGeometry,
    input: ConditionInput,
    x: Tensor,
    t: Tensor,
    target: Tensor,
}

fn setup(cfg: &DenoiserConfig, b: usize) -> Setup {
    let (vm, net) = varmap_model(cfg, 3);
    wake_zero_branches(&vm, 4);
    let mut r = rng(5);
    let x = rand_tensor(&mut r, &[b, 3, 16, 128]);
    let target = rand_tensor(&mut r, &[b, 3, 16, 128]);
    let t = Tensor::new(&[0.3f32, 0.8][..b], &Device::Cpu).unwrap();
    let cc = cfg.conditioning.as_ref().expect("conditional config");
    let geom = GcmaGeometry::new(cfg, &[kitti_camera()], &epipolar(4), &Device::Cpu).unwrap();
    let (sem, dep) = rand_pyramids(&mut r, cfg, b);
    let input = ConditionInput {
        semantic: (cc.cues != Cues::DepthOnly).then_some(sem),
        depth: (cc.cues != Cues::SemanticOnly).then_some(dep),
        keep: None,
    };
    Setup {
        vm,
        net,
        geom,
        input,
        x,
        t,
        target,
    }
}

/// The output in `dtype` activations (weights and conditioning features stay f32) and the
/// gradients of an f32 MSE loss with respect to every variable, by name.
fn forward_backward(s: &Setup, dtype: DType) -> (Tensor, Vec<(String, Tensor)>) {
    let prepared = s.net.prepare_condition(&s.input, Some(&s.geom)).unwrap();
    let y = s
        .net
        .forward(&s.x.to_dtype(dtype).unwrap(), &s.t, Some(&prepared))
        .unwrap();
    assert_eq!(y.dtype(), dtype, "the output keeps the activations' dtype");
    let loss = (y.to_dtype(DType::F32).unwrap() - &s.target)
        .unwrap()
        .sqr()
        .unwrap()
        .mean_all()
        .unwrap();
    let grads = loss.backward().unwrap();
    let data = s.vm.data().lock().unwrap();
    let mut names: Vec<&String> = data.keys().collect();
    names.sort();
    let g = names
        .into_iter()
        .map(|n| {
            let v = &data[n];
            let g = grads
                .get(v.as_tensor())
                .unwrap_or_else(|| panic!("no gradient for {n}"));
            assert_eq!(g.dtype(), DType::F32, "{n}: the master gradient is f32");
            (n.clone(), g.clone())
        })
        .collect();
    (y, g)
}

fn flat_grads(g: &[(String, Tensor)]) -> Tensor {
    let parts: Vec<Tensor> = g.iter().map(|(_, t)| t.flatten_all().unwrap()).collect();
    Tensor::cat(&parts, 0).unwrap()
}

#[test]
fn bf16_activations_on_f32_weights_track_the_f32_network_forward_and_backward() {
    let s = setup(&small_config(), 2);
    let (y32, g32) = forward_backward(&s, DType::F32);
    let (y16, g16) = forward_backward(&s, DType::BF16);
    let fwd = rel_l2(&y16, &y32);
    // bf16 keeps 8 significant bits (relative rounding 2^-9 = 2e-3 per value): a few of those
    // through the network, far below the output's own scale
    assert!(fwd < 3e-2, "forward relative L2 {fwd}");
    // and it did run in bf16: an f32 path would agree to ~1e-6
    assert!(
        fwd > 1e-4,
        "forward relative L2 {fwd}: not computed in bf16?"
    );
    let bwd = rel_l2(&flat_grads(&g16), &flat_grads(&g32));
    assert!(bwd < 6e-2, "gradient relative L2 {bwd}");
    assert!(bwd > 1e-4, "gradient relative L2 {bwd}");
    // every parameter tensor gets a gradient of its own size and direction
    let mut worst = (0.0f64, String::new());
    for ((n, a), (_, b)) in g16.iter().zip(&g32) {
        let nb = b
            .sqr()
            .unwrap()
            .sum_all()
            .unwrap()
            .to_scalar::<f32>()
            .unwrap();
        if nb > 1e-20 {
            let r = rel_l2(a, b);
            assert!(r < 0.15, "{n}: gradient relative L2 {r}");
            if r > worst.0 {
                worst = (r, n.clone());
            }
        }
    }
    eprintln!(
        "bf16 vs f32: output {fwd:.2e}, gradients {bwd:.2e}, worst tensor {} {:.2e}",
        worst.1, worst.0
    );
}

#[test]
fn f16_activations_run_with_f32_statistics() {
    // f16's range ends at 65504: the masked softmax's -3e38 fill and the GroupNorm sums must not
    // run in it
    let s = setup(&small_config(), 1);
    let (y32, _) = forward_backward(&s, DType::F32);
    let (y16, _) = forward_backward(&s, DType::F16);
    let fwd = rel_l2(&y16, &y32);
    assert!(all_finite(&y16.to_dtype(DType::F32).unwrap()));
    assert!(fwd < 1e-2, "forward relative L2 {fwd}");
}

#[test]
fn bf16_weights_and_activations_run_the_whole_network() {
    // inference with the weights themselves in bf16 (the cast at use is then free)
    let s = setup(&small_config(), 1);
    let vb = candle_nn::VarBuilder::from_varmap(&s.vm, DType::BF16, &Device::Cpu);
    let net16 = veila_nn::Denoiser::new(&small_config(), vb).unwrap();
    let forward = |net: &veila_nn::Denoiser, dtype: DType| {
        let prepared = net.prepare_condition(&s.input, Some(&s.geom)).unwrap();
        net.forward(&s.x.to_dtype(dtype).unwrap(), &s.t, Some(&prepared))
            .unwrap()
    };
    let y32 = forward(&s.net, DType::F32);
    let y16 = forward(&net16, DType::BF16);
    assert_eq!(y16.dtype(), DType::BF16);
    let d = rel_l2(&y16, &y32);
    assert!(d < 3e-2 && d > 1e-4, "relative L2 {d}");
}

#[test]
fn masked_softmax_of_half_logits_matches_f32_and_empty_rows_stay_zero() {
    let dev = Device::Cpu;
    let logits = Tensor::new(&[[1.0f32, 2.0, 3.0, -1.0], [0.5, 0.25, 9.0, 4.0]], &dev).unwrap();
    let log_w = Tensor::new(&[[0.0f32, -0.5, -1.0, 0.0], [0.0, 0.0, 0.0, 0.0]], &dev).unwrap();
    let valid = Tensor::new(&[[1u8, 1, 0, 1], [0, 0, 0, 0]], &dev).unwrap();
    let a32 = veila_nn::ops::masked_softmax_last_dim(&logits, &log_w, &valid).unwrap();
    for dt in [DType::F16, DType::BF16] {
        let a =
            veila_nn::ops::masked_softmax_last_dim(&logits.to_dtype(dt).unwrap(), &log_w, &valid)
                .unwrap();
        assert_eq!(a.dtype(), dt);
        let a = a.to_dtype(DType::F32).unwrap().to_vec2::<f32>().unwrap();
        let b = a32.to_vec2::<f32>().unwrap();
        // closed form of the valid row: softmax of (1, 1.5, -1) over entries 0, 1, 3
        let z = [1.0f64, 1.5, -1.0].map(f64::exp);
        let sum: f64 = z.iter().sum();
        let want = [z[0] / sum, z[1] / sum, 0.0, z[2] / sum];
        for j in 0..4 {
            assert!((f64::from(b[0][j]) - want[j]).abs() < 1e-6, "f32 {j}");
            assert!((f64::from(a[0][j]) - want[j]).abs() < 4e-3, "{dt:?} {j}");
            assert_eq!(a[1][j], 0.0, "{dt:?}: a row without valid entries is zero");
        }
    }
}
