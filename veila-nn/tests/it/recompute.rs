//! Activation checkpointing (`veila_nn::recompute`): the network with every residual block, GCMA
//! and PFC layer recomputed in the backward pass gives the plain network's output and gradients,
//! on the CPU kernels (f32) and on the candle compositions every other device runs (f64 here, which
//! the kernels do not take, so the reference ops are what is compared).

use crate::common::*;
use candle_core::{DType, Device, Tensor};
use candle_nn::VarMap;
use veila_nn::{ConditionInput, GcmaGeometry};

struct Setup {
    vm: VarMap,
    net: veila_nn::Denoiser,
    geom: GcmaGeometry,
    input: ConditionInput,
    x: Tensor,
    t: Tensor,
    target: Tensor,
}

/// The small conditional network (CACM, GCMA on every level, PFC) at batch 2 in `dtype`, with the
/// zero-initialised branches woken so that every parameter gets a gradient.
fn setup(dtype: DType) -> Setup {
    let cfg = small_config();
    let vm = VarMap::new();
    let net = veila_nn::Denoiser::new(
        &cfg,
        veila_nn::seeded_var_builder(&vm, 3, dtype, &Device::Cpu),
    )
    .unwrap();
    wake_zero_branches(&vm, 4);
    let mut r = rng(5);
    let cast = |t: Tensor| t.to_dtype(dtype).unwrap();
    let x = cast(rand_tensor(&mut r, &[2, 3, 16, 128]));
    let target = cast(rand_tensor(&mut r, &[2, 3, 16, 128]));
    let t = cast(Tensor::new(&[0.3f32, 0.8], &Device::Cpu).unwrap());
    let geom = GcmaGeometry::new(&cfg, &[kitti_camera()], &epipolar(4), &Device::Cpu).unwrap();
    let (sem, dep) = rand_pyramids(&mut r, &cfg, 2);
    let input = ConditionInput {
        semantic: Some(sem.into_iter().map(cast).collect()),
        depth: Some(dep.into_iter().map(cast).collect()),
        // the second sample drops its image: the keep factor inside GCMA is recomputed too
        keep: Some(cast(Tensor::new(&[1.0f32, 0.0], &Device::Cpu).unwrap())),
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

/// The output and every variable's gradient (by name) of an MSE loss, with the tape merged.
fn forward_backward(s: &Setup, net: &veila_nn::Denoiser) -> (Tensor, Vec<(String, Tensor)>) {
    let prepared = net.prepare_condition(&s.input, Some(&s.geom)).unwrap();
    let y = net.forward(&s.x, &s.t, Some(&prepared)).unwrap();
    let loss = (&y - &s.target).unwrap().sqr().unwrap().mean_all().unwrap();
    let mut grads = loss.backward().unwrap();
    if let Some(tape) = net.recompute_tape() {
        assert!(
            !tape.is_empty().unwrap(),
            "the recomputed blocks left no gradient"
        );
        tape.merge_into(&mut grads).unwrap();
        assert!(tape.is_empty().unwrap(), "merging drains the tape");
    }
    let data = s.vm.data().lock().unwrap();
    let mut names: Vec<&String> = data.keys().collect();
    names.sort();
    let g = names
        .into_iter()
        .map(|n| {
            let g = grads
                .get(data[n].as_tensor())
                .unwrap_or_else(|| panic!("no gradient for {n}"));
            (n.clone(), g.to_dtype(DType::F64).unwrap())
        })
        .collect();
    (y.to_dtype(DType::F64).unwrap(), g)
}

/// Compares the checkpointed network with the plain one; returns the worst gradient difference
/// relative to its tensor's largest gradient.
fn compare(dtype: DType) -> f64 {
    let s = setup(dtype);
    assert!(!s.net.recomputes_blocks());
    let mut ckpt = s.net.clone();
    ckpt.set_recompute_blocks(true);
    assert!(ckpt.recomputes_blocks());
    let (y0, g0) = forward_backward(&s, &s.net);
    let (y1, g1) = forward_backward(&s, &ckpt);
    let dy = max_abs(&(&y1 - &y0).unwrap());
    assert!(
        dy <= 1e-6 * max_abs(&y0),
        "{dtype:?}: outputs differ by {dy}"
    );
    let mut worst = (0.0f64, String::new());
    let mut nonzero = 0;
    for ((n, a), (_, b)) in g1.iter().zip(&g0) {
        let scale = max_abs(b);
        if scale > 0.0 {
            nonzero += 1;
        }
        let d = max_abs(&(a - b).unwrap()) / scale.max(1e-30);
        if d > worst.0 {
            worst = (d, n.clone());
        }
    }
    // the comparison means something only if the gradients reach (nearly) every tensor
    assert!(
        nonzero + 2 >= g0.len(),
        "{dtype:?}: only {nonzero} of {} gradients are non-zero",
        g0.len()
    );
    eprintln!(
        "{dtype:?}: {} gradients, worst relative difference {:.2e} ({})",
        g0.len(),
        worst.0,
        worst.1
    );
    assert!(
        worst.0 <= 1e-6,
        "{dtype:?}: {} differs by {:.2e} of its largest gradient",
        worst.1,
        worst.0
    );
    worst.0
}

#[test]
fn checkpointed_blocks_give_the_plain_gradients_on_the_cpu_kernels() {
    compare(DType::F32);
}

#[test]
fn checkpointed_blocks_give_the_plain_gradients_on_the_reference_ops() {
    compare(DType::F64);
}

/// The whole network's training gradients on the CPU kernels (f32: fused residual blocks, group
/// norms, convolutions, each with a hand-written backward) against candle's plain compositions of
/// the same weights and inputs in f64 (which the kernels do not take): a wrong backward anywhere in
/// the kernels would train slowly rather than fail, so it is checked end to end here.
#[test]
fn the_cpu_kernels_give_the_reference_gradients_of_the_whole_network() {
    let fast = setup(DType::F32);
    let exact = setup(DType::F64);
    let (y32, g32) = forward_backward(&fast, &fast.net);
    let (y64, g64) = forward_backward(&exact, &exact.net);
    let dy = max_abs(&(&y32 - &y64).unwrap());
    assert!(dy <= 1e-4 * max_abs(&y64), "outputs differ by {dy}");
    assert_eq!(g32.len(), g64.len());
    let (mut worst, mut worst_name, mut nonzero) = (0.0f64, String::new(), 0);
    for ((n, a), (m, b)) in g32.iter().zip(&g64) {
        assert_eq!(n, m);
        let scale = max_abs(b);
        if scale > 0.0 {
            nonzero += 1;
        }
        let d = max_abs(&(a - b).unwrap()) / scale.max(1e-30);
        if d > worst {
            (worst, worst_name) = (d, n.clone());
        }
    }
    assert!(
        nonzero + 2 >= g64.len(),
        "only {nonzero} of {} gradients are non-zero",
        g64.len()
    );
    eprintln!(
        "{} gradients, worst relative difference {worst:.2e} ({worst_name})",
        g64.len()
    );
    assert!(
        worst <= 3e-3,
        "{worst_name} differs by {worst:.2e} of its largest gradient"
    );
}

#[test]
fn evaluation_without_a_graph_runs_the_blocks_directly() {
    // inputs and weights outside any graph: nothing to recompute, no node, nothing on the tape
    let s = setup(DType::F32);
    let mut ckpt = s.net.clone();
    ckpt.set_recompute_blocks(true);
    let vb = candle_nn::VarBuilder::from_tensors(
        s.vm.data()
            .lock()
            .unwrap()
            .iter()
            .map(|(n, v)| (n.clone(), v.as_tensor().detach()))
            .collect(),
        DType::F32,
        &Device::Cpu,
    );
    let mut frozen = veila_nn::Denoiser::new(&small_config(), vb).unwrap();
    frozen.set_recompute_blocks(true);
    let prepared = frozen.prepare_condition(&s.input, Some(&s.geom)).unwrap();
    let y = frozen.forward(&s.x, &s.t, Some(&prepared)).unwrap();
    assert!(!y.track_op(), "a frozen network's output keeps no graph");
    let plain = s
        .net
        .forward(
            &s.x,
            &s.t,
            Some(&s.net.prepare_condition(&s.input, Some(&s.geom)).unwrap()),
        )
        .unwrap();
    assert_eq!(max_abs_diff(&y, &plain), 0.0);
    assert!(frozen.recompute_tape().unwrap().is_empty().unwrap());
}

/// The value and the inputs' gradients of `sum(f(inputs) * probe)`.
fn value_and_grads(
    inputs: &[Tensor],
    probe: &Tensor,
    f: impl Fn(&[Tensor]) -> Tensor,
) -> (Tensor, Vec<Tensor>) {
    let vars: Vec<candle_core::Var> = inputs
        .iter()
        .map(|t| candle_core::Var::from_tensor(t).unwrap())
        .collect();
    let ts: Vec<Tensor> = vars.iter().map(|v| v.as_tensor().clone()).collect();
    let y = f(&ts);
    assert!(y.track_op(), "the op is part of the graph");
    let g = (&y * probe).unwrap().sum_all().unwrap().backward().unwrap();
    let grads = ts.iter().map(|t| g.get(t).unwrap().clone()).collect();
    (y, grads)
}

#[test]
fn lean_convolutions_and_group_norms_equal_the_compositions_they_recompute() {
    // f64 does not take the CPU kernels: the ops below run lean (recomputed in the backward
    // pass), the references keep their whole graph
    let dev = Device::Cpu;
    let mut r = rng(11);
    let f64t = |t: Tensor| t.to_dtype(DType::F64).unwrap();
    let x = f64t(rand_tensor(&mut r, &[2, 6, 5, 16]));
    let w = f64t(rand_tensor(&mut r, &[4, 6, 3, 3]));
    let b = f64t(rand_tensor(&mut r, &[4]));
    let probe = f64t(rand_tensor(&mut r, &[2, 4, 5, 16]));
    let spec = veila_nn::ops::Im2ColSpec {
        kernel: (3, 3),
        stride: (1, 1),
        pad_h: 1,
        pad_w: 1,
        ring: true,
        ones_row: false,
    };
    let inputs = [x.clone(), w.clone(), b.clone()];
    let (y1, g1) = value_and_grads(&inputs, &probe, |t| {
        veila_nn::ops::conv2d_im2col(&t[0], &t[1], Some(&t[2]), spec).unwrap()
    });
    let (y0, g0) = value_and_grads(&inputs, &probe, |t| {
        veila_nn::fused::conv2d_reference(&t[0], &t[1], Some(&t[2]), spec, (2, 5, 16)).unwrap()
    });
    assert!(max_abs(&(&y1 - &y0).unwrap()) <= 1e-12 * max_abs(&y0));
    for (name, (a, z)) in ["x", "weight", "bias"].iter().zip(g1.iter().zip(&g0)) {
        let d = max_abs(&(a - z).unwrap()) / max_abs(z);
        assert!(d <= 1e-12, "convolution, gradient of {name}: {d:e}");
    }
    // the lean path a few output rows at a time (one node, recomputed a tile at a time), at
    // stride 1 and 2: the same output and gradients as the whole layer's composition; without a
    // graph (detached inputs) the tiles give the same output too
    for stride in [1, 2] {
        let spec = veila_nn::ops::Im2ColSpec {
            stride: (stride, stride),
            ..spec
        };
        let (ho, wo) = spec.out_size(5, 16).unwrap();
        let probe = f64t(rand_tensor(&mut r, &[2, 4, ho, wo]));
        let (y0, g0) = value_and_grads(&inputs, &probe, |t| {
            veila_nn::fused::conv2d_reference(&t[0], &t[1], Some(&t[2]), spec, (2, ho, wo)).unwrap()
        });
        for rows in [1, 2] {
            assert!(rows < ho);
            let (y1, g1) = value_and_grads(&inputs, &probe, |t| {
                veila_nn::ops::conv2d_lean_tiles(&t[0], &t[1], Some(&t[2]), spec, Some(rows))
                    .unwrap()
            });
            assert!(max_abs(&(&y1 - &y0).unwrap()) <= 1e-12 * max_abs(&y0));
            for (name, (a, z)) in ["x", "weight", "bias"].iter().zip(g1.iter().zip(&g0)) {
                let d = max_abs(&(a - z).unwrap()) / max_abs(z);
                assert!(
                    d <= 1e-12,
                    "stride {stride}, {rows} rows a tile, gradient of {name}: {d:e}"
                );
            }
            let detached: Vec<Tensor> = inputs.iter().map(Tensor::detach).collect();
            let y2 = veila_nn::ops::conv2d_lean_tiles(
                &detached[0],
                &detached[1],
                Some(&detached[2]),
                spec,
                Some(rows),
            )
            .unwrap();
            assert!(!y2.track_op());
            assert!(max_abs(&(&y2 - &y0).unwrap()) <= 1e-12 * max_abs(&y0));
        }
    }
    // GroupNorm with a per-sample modulation and SiLU
    let sc = f64t(rand_tensor(&mut r, &[2, 6]));
    let sh = f64t(rand_tensor(&mut r, &[2, 6]));
    let probe = f64t(rand_tensor(&mut r, &[2, 6, 5, 16]));
    let vm = VarMap::new();
    let gn = veila_nn::ops::group_norm(
        3,
        6,
        candle_nn::VarBuilder::from_varmap(&vm, DType::F64, &dev),
    )
    .unwrap();
    let inputs = [x, sc, sh];
    let (y1, g1) = value_and_grads(&inputs, &probe, |t| {
        gn.forward_modulated_silu(&t[0], &t[1], &t[2]).unwrap()
    });
    let (y0, g0) = value_and_grads(&inputs, &probe, |t| {
        // GroupNorm's own weights are 1 and 0 here: the modulation is all of the affine part
        let one_s = (&t[1] + 1.0).unwrap();
        veila_nn::fused::group_norm_act_reference(&t[0], &one_s, &t[2], 3, 1e-5, true).unwrap()
    });
    assert!(max_abs(&(&y1 - &y0).unwrap()) <= 1e-12 * max_abs(&y0));
    for (name, (a, z)) in ["x", "scale", "shift"].iter().zip(g1.iter().zip(&g0)) {
        let d = max_abs(&(a - z).unwrap()) / max_abs(z);
        assert!(d <= 1e-12, "group norm, gradient of {name}: {d:e}");
    }
}

/// GroupNorm + scale/shift (+ SiLU)'s hand-written gradient (what the lean node's backward pass
/// runs off the CPU kernels) against candle's backward pass through the composition: f64 to
/// 1e-12, bf16 (f32 statistics) to its rounding, and a constant group (zero variance) finite.
#[test]
fn the_group_norm_gradient_by_hand_equals_the_compositions() {
    let mut r = rng(12);
    let f64t = |t: Tensor| t.to_dtype(DType::F64).unwrap();
    for (shape, groups) in [(vec![2, 6, 5, 16], 3), (vec![3, 8, 40], 4)] {
        let (b, c) = (shape[0], shape[1]);
        let x = f64t(rand_tensor(&mut r, &shape));
        let sc = f64t(rand_tensor(&mut r, &[b, c]));
        let sh = f64t(rand_tensor(&mut r, &[b, c]));
        let probe = f64t(rand_tensor(&mut r, &shape));
        for silu in [true, false] {
            let inputs = [x.clone(), sc.clone(), sh.clone()];
            let (_, want) = value_and_grads(&inputs, &probe, |t| {
                veila_nn::fused::group_norm_act_reference(&t[0], &t[1], &t[2], groups, 1e-5, silu)
                    .unwrap()
            });
            let (gx, gs, gt) =
                veila_nn::fused::group_norm_act_grad(&x, &sc, &sh, groups, 1e-5, silu, &probe)
                    .unwrap();
            for (name, (a, z)) in ["x", "scale", "shift"]
                .iter()
                .zip([&gx, &gs, &gt].into_iter().zip(&want))
            {
                assert_eq!(a.dims(), z.dims());
                let d = max_abs(&(a - z).unwrap()) / max_abs(z);
                assert!(
                    d <= 1e-12,
                    "{shape:?} silu {silu}, gradient of {name}: {d:e}"
                );
            }
            // bf16 inputs: statistics and gradients in f32, returned in bf16
            let bf = |t: &Tensor| t.to_dtype(DType::BF16).unwrap();
            let (gx, gs, gt) = veila_nn::fused::group_norm_act_grad(
                &bf(&x),
                &bf(&sc),
                &bf(&sh),
                groups,
                1e-5,
                silu,
                &bf(&probe),
            )
            .unwrap();
            assert_eq!(gx.dtype(), DType::BF16);
            let rounded: Vec<Tensor> = [&x, &sc, &sh].iter().map(|t| f64t(bf(t))).collect();
            let (_, want) = value_and_grads(&rounded, &f64t(bf(&probe)), |t| {
                veila_nn::fused::group_norm_act_reference(&t[0], &t[1], &t[2], groups, 1e-5, silu)
                    .unwrap()
            });
            for (name, (a, z)) in ["x", "scale", "shift"]
                .iter()
                .zip([&gx, &gs, &gt].into_iter().zip(&want))
            {
                let d = max_abs(&(&f64t(a.clone()) - z).unwrap()) / max_abs(z);
                assert!(
                    d <= 1e-2,
                    "bf16 {shape:?} silu {silu}, gradient of {name}: {d:e}"
                );
            }
        }
    }
    // a constant input: every group has zero variance, the gradients stay finite
    let x = Tensor::full(0.5f64, (1, 4, 3, 3), &Device::Cpu).unwrap();
    let s = Tensor::ones((1, 4), DType::F64, &Device::Cpu).unwrap();
    let g = f64t(rand_tensor(&mut r, &[1, 4, 3, 3]));
    let (gx, gs, gt) =
        veila_nn::fused::group_norm_act_grad(&x, &s, &s.zeros_like().unwrap(), 2, 1e-5, true, &g)
            .unwrap();
    for t in [gx, gs, gt] {
        let v = t.flatten_all().unwrap().to_vec1::<f64>().unwrap();
        assert!(v.iter().all(|x| x.is_finite()), "{v:?}");
    }
}
