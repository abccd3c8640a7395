//! The CPU kernels of `veila_nn::fused` against candle's own composition of the same formula (and, for
//! the convolution, candle's `conv2d`): outputs and gradients within 1e-5 relative.

use std::collections::HashMap;

use candle_core::{DType, Device, Tensor, Var};
use candle_nn::VarBuilder;
use veila_nn::fused::{
    Im2ColSpec, ResBlockParams, ResBlockSpec, add_scaled, conv2d, conv2d_reference, group_norm_act,
    group_norm_act_reference, im2col, im2col_reference, res_block,
};
use veila_nn::ops::{Conv1x1, RingConv2d, conv2d_zero_pad, group_norm, ring_pad};

fn seeded(shape: &[usize], seed: u64) -> Tensor {
    // a fixed pseudo-random pattern (no RNG dependency): values in about [-2, 2]
    let n: usize = shape.iter().product();
    let v: Vec<f32> = (0..n)
        .map(|i| {
            let k = (i as u64 + 1)
                .wrapping_mul(0x9E37_79B9_7F4A_7C15 ^ seed.wrapping_mul(0xBF58_476D_1CE4_E5B9));
            ((k >> 40) as f32 / (1u64 << 24) as f32) * 4.0 - 2.0
        })
        .collect();
    Tensor::from_vec(v, shape, &Device::Cpu).unwrap()
}

/// max |a - b| / max |b| (0 when both are 0).
fn rel_err(a: &Tensor, b: &Tensor) -> f32 {
    assert_eq!(a.dims(), b.dims());
    let a = a.flatten_all().unwrap().to_vec1::<f32>().unwrap();
    let b = b.flatten_all().unwrap().to_vec1::<f32>().unwrap();
    let scale = b.iter().fold(0f32, |m, v| m.max(v.abs()));
    let diff = a
        .iter()
        .zip(&b)
        .fold(0f32, |m, (x, y)| m.max((x - y).abs()));
    if scale == 0.0 { diff } else { diff / scale }
}

fn assert_close(a: &Tensor, b: &Tensor, what: &str) {
    let e = rel_err(a, b);
    assert!(e <= 1e-5, "{what}: relative error {e}");
}

fn specs() -> Vec<Im2ColSpec> {
    let s =
        |k: usize, st: (usize, usize), ph: usize, pw: usize, ring: bool, ones: bool| Im2ColSpec {
            kernel: (k, k),
            stride: st,
            pad_h: ph,
            pad_w: pw,
            ring,
            ones_row: ones,
        };
    vec![
        s(3, (1, 1), 1, 1, true, false),
        s(3, (2, 2), 1, 1, true, true),
        s(3, (1, 1), 1, 1, false, true),
        s(5, (2, 2), 2, 2, false, false),
        s(3, (1, 2), 0, 0, false, false),
        s(1, (1, 1), 0, 0, false, true),
        s(5, (1, 1), 2, 2, true, false),
    ]
}

#[test]
fn im2col_matches_the_composition_forward_and_backward() {
    for (i, spec) in specs().into_iter().enumerate() {
        let x = Var::from_tensor(&seeded(&[2, 3, 6, 7], 1)).unwrap();
        let (ho, wo) = spec.out_size(6, 7).unwrap();
        let fast = im2col(x.as_tensor(), spec).unwrap();
        let slow = im2col_reference(x.as_tensor(), spec, (2, 3, ho, wo)).unwrap();
        assert_close(&fast, &slow, &format!("im2col {i} {spec:?}"));
        let r = seeded(fast.dims(), 7);
        let gf = (&fast * &r).unwrap().sum_all().unwrap().backward().unwrap();
        let gs = (&slow * &r).unwrap().sum_all().unwrap().backward().unwrap();
        assert_close(
            gf.get(&x).unwrap(),
            gs.get(&x).unwrap(),
            &format!("col2im {i} {spec:?}"),
        );
    }
}

#[test]
fn im2col_rejects_kernels_that_do_not_fit() {
    let x = seeded(&[1, 2, 2, 2], 3);
    let spec = Im2ColSpec {
        kernel: (5, 5),
        stride: (1, 1),
        pad_h: 0,
        pad_w: 0,
        ring: false,
        ones_row: false,
    };
    assert!(im2col(&x, spec).is_err());
}

/// The gradients of `Σ fast · r` and `Σ slow · r` (the same fixed `r`) with respect to `vars`
/// agree within 1e-5 relative.
fn assert_grads_close(fast: &Tensor, slow: &Tensor, vars: &[&Var], what: &str) {
    let gf = conv_grads(fast, vars);
    let gs = conv_grads(slow, vars);
    for (k, (a, e)) in gf.iter().zip(&gs).enumerate() {
        assert_close(a, e, &format!("{what} gradient {k}"));
    }
}

fn conv_grads(y: &Tensor, vars: &[&Var]) -> Vec<Tensor> {
    let r = seeded(y.dims(), 11);
    let g = (y * &r).unwrap().sum_all().unwrap().backward().unwrap();
    vars.iter().map(|v| g.get(v).unwrap().clone()).collect()
}

#[test]
fn ring_conv_matches_candle_conv2d_with_gradients() {
    for stride in [1, 2] {
        let x = Var::from_tensor(&seeded(&[2, 4, 8, 12], 2)).unwrap();
        let w = Var::from_tensor(&(seeded(&[5, 4, 3, 3], 3) * 0.3).unwrap()).unwrap();
        let b = Var::from_tensor(&seeded(&[5], 4)).unwrap();
        let conv =
            RingConv2d::from_weights(w.as_tensor().clone(), Some(b.as_tensor().clone()), stride)
                .unwrap();
        let fast = conv.forward(x.as_tensor()).unwrap();
        let slow = ring_pad(x.as_tensor(), 1, 1)
            .unwrap()
            .conv2d(w.as_tensor(), 0, stride, 1, 1)
            .unwrap()
            .broadcast_add(&b.as_tensor().reshape((1, 5, 1, 1)).unwrap())
            .unwrap();
        assert_close(&fast, &slow, &format!("ring conv stride {stride}"));
        let gf = conv_grads(&fast, &[&x, &w, &b]);
        let gs = conv_grads(&slow, &[&x, &w, &b]);
        for (k, (a, e)) in gf.iter().zip(&gs).enumerate() {
            assert_close(a, e, &format!("ring conv stride {stride} gradient {k}"));
        }
    }
}

#[test]
fn zero_padded_conv_matches_candle_conv2d_with_gradients() {
    // sizes with (size + 2 padding - 3) divisible by the stride: candle's conv2d backward (the
    // reference) has no output padding for the others
    let x = Var::from_tensor(&seeded(&[2, 3, 9, 11], 5)).unwrap();
    let w = Var::from_tensor(&(seeded(&[4, 3, 3, 3], 6) * 0.3).unwrap()).unwrap();
    let b = Var::from_tensor(&seeded(&[4], 8)).unwrap();
    for (padding, stride) in [(1, 1), (1, 2), (0, 1)] {
        let fast = conv2d_zero_pad(
            x.as_tensor(),
            w.as_tensor(),
            Some(b.as_tensor()),
            padding,
            stride,
        )
        .unwrap();
        let slow = x
            .as_tensor()
            .conv2d(w.as_tensor(), padding, stride, 1, 1)
            .unwrap()
            .broadcast_add(&b.as_tensor().reshape((1, 4, 1, 1)).unwrap())
            .unwrap();
        assert_close(&fast, &slow, &format!("conv p{padding} s{stride}"));
        let gf = conv_grads(&fast, &[&x, &w, &b]);
        let gs = conv_grads(&slow, &[&x, &w, &b]);
        for (k, (a, e)) in gf.iter().zip(&gs).enumerate() {
            assert_close(a, e, &format!("conv p{padding} s{stride} gradient {k}"));
        }
    }
}

#[test]
fn fused_convolution_matches_im2col_and_matmul_with_gradients() {
    // every padding, stride and kernel shape of `specs()`, with and without a bias, batch 3
    for spec in specs() {
        for with_bias in [false, true] {
            let x = Var::from_tensor(&seeded(&[3, 4, 7, 10], 21)).unwrap();
            let (kh, kw) = spec.kernel;
            let w = Var::from_tensor(&(seeded(&[5, 4, kh, kw], 22) * 0.3).unwrap()).unwrap();
            let b = Var::from_tensor(&seeded(&[5], 23)).unwrap();
            let bias = with_bias.then(|| b.as_tensor());
            let Some((ho, wo)) = spec.out_size(7, 10) else {
                continue;
            };
            let fast = conv2d(x.as_tensor(), w.as_tensor(), bias, spec).unwrap();
            let slow =
                conv2d_reference(x.as_tensor(), w.as_tensor(), bias, spec, (3, ho, wo)).unwrap();
            let what = format!("{spec:?} bias {with_bias}");
            assert_eq!(fast.dims(), [3, 5, ho, wo], "{what}");
            assert_close(&fast, &slow, &what);
            let vars: Vec<&Var> = if with_bias {
                vec![&x, &w, &b]
            } else {
                vec![&x, &w]
            };
            let gf = conv_grads(&fast, &vars);
            let gs = conv_grads(&slow, &vars);
            for (k, (a, e)) in gf.iter().zip(&gs).enumerate() {
                assert_close(a, e, &format!("{what} gradient {k}"));
            }
        }
    }
}

#[test]
fn fused_convolution_of_one_sample_matches_im2col_and_matmul() {
    // a batch of one runs each product over all threads (larger batches run their samples in
    // parallel, one thread each: the test above): the other path of the op, on a larger layer; and
    // a 1x1 kernel at stride 1 without padding, which skips the column buffer (forward) and writes
    // the input gradient directly (backward) on this path too (`specs()` covers it at batch 3)
    for (spec, k) in [(specs()[0], 3), (Im2ColSpec::POINTWISE, 1)] {
        let x = Var::from_tensor(&seeded(&[1, 8, 64, 128], 31)).unwrap();
        let w = Var::from_tensor(&(seeded(&[16, 8, k, k], 32) * 0.2).unwrap()).unwrap();
        let b = Var::from_tensor(&seeded(&[16], 33)).unwrap();
        let fast = conv2d(x.as_tensor(), w.as_tensor(), Some(b.as_tensor()), spec).unwrap();
        let slow = conv2d_reference(
            x.as_tensor(),
            w.as_tensor(),
            Some(b.as_tensor()),
            spec,
            (1, 64, 128),
        )
        .unwrap();
        let what = format!("large layer, {k}x{k}");
        assert_close(&fast, &slow, &what);
        assert_grads_close(&fast, &slow, &[&x, &w, &b], &what);
    }
}

#[test]
fn conv1x1_layer_matches_the_per_pixel_product_with_gradients() {
    // the layer takes the fused convolution on CPU f32 input; the reference is the plain per-pixel
    // product `W x + b` (a batch-broadcast matrix product), for 4-d and 3-d inputs
    for shape in [vec![3, 5, 4, 9], vec![2, 5, 11]] {
        let vm = candle_nn::VarMap::new();
        let vb = VarBuilder::from_varmap(&vm, DType::F32, &Device::Cpu);
        let layer = Conv1x1::new(5, 4, true, vb).unwrap();
        let vars = vm.data().lock().unwrap().clone();
        let (w, b) = (&vars["weight"], &vars["bias"]);
        let x = Var::from_tensor(&seeded(&shape, 51)).unwrap();
        let fast = layer.forward(x.as_tensor()).unwrap();
        let n: usize = shape[2..].iter().product();
        let slow = w
            .as_tensor()
            .reshape((1, 4, 5))
            .unwrap()
            .broadcast_matmul(&x.as_tensor().reshape((shape[0], 5, n)).unwrap())
            .unwrap()
            .broadcast_add(&b.as_tensor().reshape((1, 4, 1)).unwrap())
            .unwrap();
        let mut out = shape.clone();
        out[1] = 4;
        let slow = slow.reshape(out.as_slice()).unwrap();
        let what = format!("conv1x1 {shape:?}");
        assert_eq!(fast.dims(), slow.dims(), "{what}");
        assert_close(&fast, &slow, &what);
        assert_grads_close(&fast, &slow, &[&x, w, b], &what);
    }
}

#[test]
fn fused_convolution_rejects_mismatched_weights_and_bias() {
    let x = seeded(&[1, 4, 6, 6], 1);
    let spec = specs()[0];
    // 3 input channels in the weight for a 4-channel input
    assert!(conv2d(&x, &seeded(&[2, 3, 3, 3], 2), None, spec).is_err());
    // a bias of the wrong length
    let w = seeded(&[2, 4, 3, 3], 3);
    assert!(conv2d(&x, &w, Some(&seeded(&[3], 4)), spec).is_err());
    // a kernel taller than the padded input
    assert!(conv2d(&x, &seeded(&[2, 4, 9, 3], 5), None, spec).is_err());
}

#[test]
fn group_norm_act_matches_the_composition_with_gradients() {
    for silu in [false, true] {
        for (shape, groups) in [
            (vec![2, 8, 5, 6], 4),
            (vec![3, 6, 17], 3),
            (vec![1, 4, 2, 2], 1),
            // rows longer than the kernels' 64-element blocks, with and without a remainder
            (vec![2, 8, 16, 40], 4),
            (vec![1, 4, 9, 23], 2),
        ] {
            let (b, c) = (shape[0], shape[1]);
            let x = Var::from_tensor(&seeded(&shape, 21).affine(3.0, 0.5).unwrap()).unwrap();
            let sc = Var::from_tensor(&seeded(&[b, c], 22)).unwrap();
            let sh = Var::from_tensor(&seeded(&[b, c], 23)).unwrap();
            let args = (x.as_tensor(), sc.as_tensor(), sh.as_tensor());
            let fast = group_norm_act(args.0, args.1, args.2, groups, 1e-5, silu).unwrap();
            let slow =
                group_norm_act_reference(args.0, args.1, args.2, groups, 1e-5, silu).unwrap();
            let what = format!("group norm {shape:?} / {groups}, silu {silu}");
            assert_close(&fast, &slow, &what);
            let gf = conv_grads(&fast, &[&x, &sc, &sh]);
            let gs = conv_grads(&slow, &[&x, &sc, &sh]);
            for (k, (a, e)) in gf.iter().zip(&gs).enumerate() {
                assert_close(a, e, &format!("{what}: gradient {k}"));
            }
        }
    }
}

#[test]
fn group_norm_layer_matches_candle_nn_group_norm() {
    let (c, groups) = (8, 4);
    let weight = seeded(&[c], 31);
    let bias = seeded(&[c], 32);
    let mut map = HashMap::new();
    map.insert("weight".to_string(), weight.clone());
    map.insert("bias".to_string(), bias.clone());
    let ours = group_norm(
        groups,
        c,
        VarBuilder::from_tensors(map, DType::F32, &Device::Cpu),
    )
    .unwrap();
    let theirs = candle_nn::GroupNorm::new(weight, bias, c, groups, 1e-5).unwrap();
    let x = (seeded(&[2, c, 4, 9], 33) * 2.0).unwrap();
    let want = candle_core::Module::forward(&theirs, &x).unwrap();
    assert_close(&ours.forward(&x).unwrap(), &want, "group norm");
    assert_close(
        &ours.forward_silu(&x).unwrap(),
        &candle_nn::ops::silu(&want).unwrap(),
        "group norm + silu",
    );
    let s = seeded(&[2, c], 34);
    let t = seeded(&[2, c], 35);
    let modulated = want
        .broadcast_mul(&(s.reshape((2, c, 1, 1)).unwrap() + 1.0).unwrap())
        .unwrap()
        .broadcast_add(&t.reshape((2, c, 1, 1)).unwrap())
        .unwrap();
    assert_close(
        &ours.forward_modulated_silu(&x, &s, &t).unwrap(),
        &candle_nn::ops::silu(&modulated).unwrap(),
        "group norm + FiLM + silu",
    );
}

#[test]
fn add_scaled_matches_the_composition_with_gradients() {
    let a = Var::from_tensor(&seeded(&[3, 5, 7, 11], 41)).unwrap();
    let b = Var::from_tensor(&seeded(&[3, 5, 7, 11], 42)).unwrap();
    let fast = add_scaled(a.as_tensor(), b.as_tensor(), 0.7).unwrap();
    let slow = ((a.as_tensor() + b.as_tensor()).unwrap() * 0.7).unwrap();
    assert_close(&fast, &slow, "add_scaled");
    let gf = conv_grads(&fast, &[&a, &b]);
    let gs = conv_grads(&slow, &[&a, &b]);
    for (k, (x, e)) in gf.iter().zip(&gs).enumerate() {
        assert_close(x, e, &format!("add_scaled gradient {k}"));
    }
}

#[test]
fn upsample_nearest_matches_the_broadcast_with_gradients() {
    let x = Var::from_tensor(&seeded(&[2, 3, 4, 5], 51)).unwrap();
    let fast = veila_nn::fused::upsample_nearest(x.as_tensor(), 2).unwrap();
    let slow = x
        .as_tensor()
        .reshape((2, 3, 4, 1, 5, 1))
        .unwrap()
        .broadcast_as((2, 3, 4, 2, 5, 2))
        .unwrap()
        .reshape((2, 3, 8, 10))
        .unwrap();
    assert_close(&fast, &slow, "upsample");
    let gf = conv_grads(&fast, &[&x]);
    let gs = conv_grads(&slow, &[&x]);
    assert_close(&gf[0], &gs[0], "upsample gradient");
}

#[test]
fn fused_residual_block_matches_the_composition_with_gradients() {
    // the block as one op against candle's composition of the same formula (reference GroupNorm,
    // im2col + matmul convolutions, plain sum): with and without the 1x1 skip and biases, at
    // batch 1 (threaded products) and 3 (samples in parallel)
    let spec = Im2ColSpec {
        kernel: (3, 3),
        stride: (1, 1),
        pad_h: 1,
        pad_w: 1,
        ring: true,
        ones_row: false,
    };
    for (case, (b, ci, co, biases)) in [
        (3, 4, 4, true),
        (1, 4, 6, true),
        (3, 6, 4, false),
        (2, 4, 4, false),
    ]
    .into_iter()
    .enumerate()
    {
        let (h, w) = (5, 12);
        let seed = 100 * case as u64;
        let var = |shape: &[usize], k: u64, scale: f64| {
            Var::from_tensor(&(seeded(shape, seed + k) * scale).unwrap()).unwrap()
        };
        let x = var(&[b, ci, h, w], 1, 1.0);
        let (sc1, sh1) = (var(&[b, ci], 2, 0.5), var(&[b, ci], 3, 0.5));
        let (sc2, sh2) = (var(&[b, co], 4, 0.5), var(&[b, co], 5, 0.5));
        let (w1, b1) = (var(&[co, ci, 3, 3], 6, 0.3), var(&[co], 7, 0.5));
        let (w2, b2) = (var(&[co, co, 3, 3], 8, 0.3), var(&[co], 9, 0.5));
        let (ws, bs) = (var(&[co, ci, 1, 1], 10, 0.4), var(&[co], 11, 0.5));
        let with_skip = ci != co;
        let bias = |v: &Var| biases.then(|| v.as_tensor().clone());
        let (b1t, b2t, bst) = (bias(&b1), bias(&b2), bias(&bs));
        let (groups1, groups2) = (ci / 2, co / 2);
        let rb_spec = ResBlockSpec {
            groups1,
            groups2,
            eps: 1e-5,
            scale: 0.7,
            conv: spec,
        };
        let fast = res_block(
            x.as_tensor(),
            ResBlockParams {
                norm1: (sc1.as_tensor(), sh1.as_tensor()),
                conv1: (w1.as_tensor(), b1t.as_ref()),
                norm2: (sc2.as_tensor(), sh2.as_tensor()),
                conv2: (w2.as_tensor(), b2t.as_ref()),
                skip: with_skip.then(|| (ws.as_tensor(), bst.as_ref())),
            },
            rb_spec,
        )
        .unwrap()
        .expect("CPU f32 takes the fused op");
        let a1 = group_norm_act_reference(
            x.as_tensor(),
            sc1.as_tensor(),
            sh1.as_tensor(),
            groups1,
            1e-5,
            true,
        )
        .unwrap();
        let h1 = conv2d_reference(&a1, w1.as_tensor(), b1t.as_ref(), spec, (b, h, w)).unwrap();
        let a2 =
            group_norm_act_reference(&h1, sc2.as_tensor(), sh2.as_tensor(), groups2, 1e-5, true)
                .unwrap();
        let h2 = conv2d_reference(&a2, w2.as_tensor(), b2t.as_ref(), spec, (b, h, w)).unwrap();
        let skip = if with_skip {
            conv2d_reference(
                x.as_tensor(),
                ws.as_tensor(),
                bst.as_ref(),
                Im2ColSpec::POINTWISE,
                (b, h, w),
            )
            .unwrap()
        } else {
            x.as_tensor().clone()
        };
        let slow = ((skip + h2).unwrap() * 0.7).unwrap();
        let what = format!("residual block b{b} {ci}->{co} biases {biases}");
        assert_eq!(fast.dims(), [b, co, h, w], "{what}");
        assert_close(&fast, &slow, &what);
        let mut vars = vec![&x, &sc1, &sh1, &sc2, &sh2, &w1, &w2];
        if biases {
            vars.extend([&b1, &b2]);
        }
        if with_skip {
            vars.push(&ws);
            if biases {
                vars.push(&bs);
            }
        }
        assert_grads_close(&fast, &slow, &vars, &what);
    }
}

#[test]
fn fused_residual_block_rejects_mismatched_parameters() {
    let spec = ResBlockSpec {
        groups1: 2,
        groups2: 2,
        eps: 1e-5,
        scale: 1.0,
        conv: Im2ColSpec {
            kernel: (3, 3),
            stride: (1, 1),
            pad_h: 1,
            pad_w: 1,
            ring: true,
            ones_row: false,
        },
    };
    let x = seeded(&[2, 4, 4, 6], 1);
    let n4 = seeded(&[2, 4], 2);
    let w = seeded(&[4, 4, 3, 3], 3);
    fn params<'a>(
        n4: &'a Tensor,
        w: &'a Tensor,
        norm2: &'a Tensor,
        skip: Option<(&'a Tensor, Option<&'a Tensor>)>,
    ) -> ResBlockParams<'a> {
        ResBlockParams {
            norm1: (n4, n4),
            conv1: (w, None),
            norm2: (norm2, norm2),
            conv2: (w, None),
            skip,
        }
    }
    assert!(
        res_block(&x, params(&n4, &w, &n4, None), spec)
            .unwrap()
            .is_some()
    );
    // a per-sample scale for the wrong batch
    let n3 = seeded(&[3, 4], 4);
    assert!(res_block(&x, params(&n4, &w, &n3, None), spec).is_err());
    // a skip projection of the wrong shape
    let ws = seeded(&[4, 3, 1, 1], 5);
    assert!(res_block(&x, params(&n4, &w, &n4, Some((&ws, None))), spec).is_err());
    // groups that do not divide the channels
    let bad = ResBlockSpec { groups1: 3, ..spec };
    assert!(res_block(&x, params(&n4, &w, &n4, None), bad).is_err());
}
