//! Numerics of the low-level ops against brute-force and closed-form references.

use crate::common::{rand_tensor, rng};
use candle_core::{DType, Device, Tensor};
use veila_nn::ops::{
    RingConv2d, bilinear_resize, masked_softmax_last_dim, ring_pad, sinusoidal_embedding,
};

/// PyTorch `F.interpolate(mode="bilinear", align_corners=False)` for one output pixel, written directly
/// from the documented formula (half-pixel centres, source clamped at 0, upper neighbour clamped).
fn torch_bilinear_ref(src: &[f32], h: usize, w: usize, oh: usize, ow: usize) -> Vec<f64> {
    let coord = |i: usize, inn: usize, out: usize| -> (usize, usize, f64) {
        let s = ((i as f64 + 0.5) * inn as f64 / out as f64 - 0.5).max(0.0);
        let i0 = s.floor() as usize;
        let i0 = i0.min(inn - 1);
        let i1 = if i0 < inn - 1 { i0 + 1 } else { i0 };
        (i0, i1, s - i0 as f64)
    };
    let mut out = vec![0.0; oh * ow];
    for y in 0..oh {
        let (y0, y1, ly) = coord(y, h, oh);
        for x in 0..ow {
            let (x0, x1, lx) = coord(x, w, ow);
            let v = |r: usize, c: usize| f64::from(src[r * w + c]);
            out[y * ow + x] = (1.0 - ly) * ((1.0 - lx) * v(y0, x0) + lx * v(y0, x1))
                + ly * ((1.0 - lx) * v(y1, x0) + lx * v(y1, x1));
        }
    }
    out
}

#[test]
fn bilinear_resize_matches_pytorch_formula() {
    let mut r = rng(1);
    for &(h, w, oh, ow) in &[
        (3, 5, 7, 11),
        (8, 8, 3, 5),
        (6, 10, 12, 20),
        (5, 7, 5, 3),
        (1, 4, 3, 9),
        (4, 4, 1, 1),
    ] {
        let x = rand_tensor(&mut r, &[2, 3, h, w]);
        let y = bilinear_resize(&x, oh, ow).unwrap();
        assert_eq!(y.dims(), &[2, 3, oh, ow]);
        let xs = x.reshape((6, h * w)).unwrap().to_vec2::<f32>().unwrap();
        let ys = y.reshape((6, oh * ow)).unwrap().to_vec2::<f32>().unwrap();
        for (xc, yc) in xs.iter().zip(&ys) {
            let reference = torch_bilinear_ref(xc, h, w, oh, ow);
            for (a, b) in yc.iter().zip(&reference) {
                assert!(
                    (f64::from(*a) - b).abs() < 1e-5,
                    "{h}x{w}->{oh}x{ow}: {a} vs {b}"
                );
            }
        }
    }
}

#[test]
fn bilinear_resize_known_pytorch_values() {
    // torch.nn.functional.interpolate(torch.tensor([[[[0., 1.]]]]), size=(1, 4), mode="bilinear",
    // align_corners=False) == [[[[0.0, 0.25, 0.75, 1.0]]]]
    let x = Tensor::new(&[[[[0f32, 1.0]]]], &Device::Cpu).unwrap();
    let y = bilinear_resize(&x, 1, 4)
        .unwrap()
        .flatten_all()
        .unwrap()
        .to_vec1::<f32>()
        .unwrap();
    assert_eq!(y, vec![0.0, 0.25, 0.75, 1.0]);
    // downsampling 4 -> 2 averages the two middle samples of each pair: [0,1,2,3] -> [0.5, 2.5]
    let x = Tensor::new(&[[[[0f32, 1.0, 2.0, 3.0]]]], &Device::Cpu).unwrap();
    let y = bilinear_resize(&x, 1, 2)
        .unwrap()
        .flatten_all()
        .unwrap()
        .to_vec1::<f32>()
        .unwrap();
    assert_eq!(y, vec![0.5, 2.5]);
}

#[test]
fn bilinear_resize_is_differentiable() {
    let x = candle_core::Var::from_tensor(&rand_tensor(&mut rng(2), &[1, 1, 3, 4])).unwrap();
    let y = bilinear_resize(x.as_tensor(), 6, 8).unwrap();
    let grads = y.sum_all().unwrap().backward().unwrap();
    let g = grads
        .get(x.as_tensor())
        .expect("gradient reaches the input");
    // every output is a convex combination, so the gradient sums to the number of outputs
    let total = g.sum_all().unwrap().to_scalar::<f32>().unwrap();
    assert!((total - 48.0).abs() < 1e-4, "{total}");
}

#[test]
fn ring_pad_wraps_azimuth_and_zero_pads_rows() {
    let (h, w, p) = (3usize, 5usize, 2usize);
    let x = Tensor::arange(1f32, (h * w) as f32 + 1.0, &Device::Cpu)
        .unwrap()
        .reshape((1, 1, h, w))
        .unwrap();
    let y = ring_pad(&x, 1, p).unwrap();
    assert_eq!(y.dims(), &[1, 1, h + 2, w + 2 * p]);
    let y = y
        .reshape((h + 2, w + 2 * p))
        .unwrap()
        .to_vec2::<f32>()
        .unwrap();
    for (r, row) in y.iter().enumerate() {
        for (c, v) in row.iter().enumerate() {
            let expected = if r == 0 || r == h + 1 {
                0.0
            } else {
                let src_c = (c + w - p) % w;
                ((r - 1) * w + src_c + 1) as f32
            };
            assert_eq!(*v, expected, "row {r} col {c}");
        }
    }
    assert!(ring_pad(&x, 0, w + 1).is_err());
}

#[test]
fn masked_softmax_huge_logits_and_masks() {
    let dev = Device::Cpu;
    let logits = Tensor::new(
        &[
            [1e30f32, -1e30, 3e38, 0.0], // huge logits: the largest valid wins
            [f32::INFINITY, 1.0, 2.0, f32::NEG_INFINITY], // infinities are clamped, not NaN
            [5.0, 1e38, 7.0, 1.0],       // the huge one is masked out
            [1.0, 2.0, 3.0, 4.0],        // every entry invalid
        ],
        &dev,
    )
    .unwrap();
    let valid = Tensor::new(
        &[[1u8, 1, 1, 1], [1, 1, 1, 1], [1, 0, 1, 0], [0, 0, 0, 0]],
        &dev,
    )
    .unwrap();
    let log_w = Tensor::zeros((4, 4), DType::F32, &dev).unwrap();
    let a = masked_softmax_last_dim(&logits, &log_w, &valid)
        .unwrap()
        .to_vec2::<f32>()
        .unwrap();
    assert_eq!(a[0], vec![0.0, 0.0, 1.0, 0.0]);
    assert_eq!(a[1], vec![1.0, 0.0, 0.0, 0.0]);
    let e = (-2f64).exp();
    let (p0, p2) = ((e / (1.0 + e)) as f32, (1.0 / (1.0 + e)) as f32);
    assert!(
        (a[2][0] - p0).abs() < 1e-6
            && (a[2][2] - p2).abs() < 1e-6
            && a[2][1] == 0.0
            && a[2][3] == 0.0
    );
    assert_eq!(a[3], vec![0.0; 4]);
}

#[test]
fn masked_softmax_matches_weighted_reference() {
    let mut r = rng(3);
    let logits = rand_tensor(&mut r, &[3, 6]).affine(20.0, 0.0).unwrap();
    let w: Vec<f32> = (0..18).map(|i| ((i * 7) % 5) as f32 * 0.3).collect(); // includes zeros
    let valid: Vec<u8> = w.iter().map(|v| u8::from(*v > 0.0)).collect();
    let log_w: Vec<f32> = w
        .iter()
        .map(|v| if *v > 0.0 { v.ln() } else { 0.0 })
        .collect();
    let dev = Device::Cpu;
    let a = masked_softmax_last_dim(
        &logits,
        &Tensor::from_vec(log_w, (3, 6), &dev).unwrap(),
        &Tensor::from_vec(valid, (3, 6), &dev).unwrap(),
    )
    .unwrap()
    .to_vec2::<f32>()
    .unwrap();
    let l = logits.to_vec2::<f32>().unwrap();
    for i in 0..3 {
        let terms: Vec<f64> = (0..6)
            .map(|k| f64::from(w[i * 6 + k]) * f64::from(l[i][k]).exp())
            .collect();
        let s: f64 = terms.iter().sum();
        for k in 0..6 {
            assert!(
                (f64::from(a[i][k]) - terms[k] / s).abs() < 1e-5,
                "row {i} k {k}"
            );
        }
    }
}

#[test]
fn sinusoidal_embedding_closed_form() {
    let t = Tensor::new(&[0.0f32, 0.25, 1.0], &Device::Cpu).unwrap();
    let (dim, period, scale) = (8usize, 10_000.0f64, 1000.0f64);
    let e = sinusoidal_embedding(&t, dim, period, scale)
        .unwrap()
        .to_vec2::<f32>()
        .unwrap();
    for (i, tv) in [0.0f64, 0.25, 1.0].iter().enumerate() {
        for j in 0..dim / 2 {
            let f = (-(period.ln()) * j as f64 / (dim / 2) as f64).exp();
            assert!((f64::from(e[i][j]) - (scale * tv * f).cos()).abs() < 1e-3);
            assert!((f64::from(e[i][j + dim / 2]) - (scale * tv * f).sin()).abs() < 1e-3);
        }
    }
    assert!(sinusoidal_embedding(&t, 7, period, scale).is_err());
}

/// Direct convolution with circular azimuth and zero vertical padding, written as nested loops.
fn ring_conv_ref(
    x: &[f32],
    c: usize,
    h: usize,
    w: usize,
    wt: &[f32],
    bias: &[f32],
    out_c: usize,
    k: usize,
    stride: usize,
) -> Vec<f64> {
    let p = (k / 2) as i64;
    let (oh, ow) = (h.div_ceil(stride), w.div_ceil(stride));
    let mut out = vec![0.0; out_c * oh * ow];
    for o in 0..out_c {
        for y in 0..oh {
            for xo in 0..ow {
                let mut s = f64::from(bias[o]);
                for ci in 0..c {
                    for ky in 0..k {
                        for kx in 0..k {
                            let yy = (y * stride) as i64 + ky as i64 - p;
                            if yy < 0 || yy >= h as i64 {
                                continue; // zero padding in elevation
                            }
                            let xx = ((xo * stride) as i64 + kx as i64 - p).rem_euclid(w as i64); // wraps in azimuth
                            s += f64::from(wt[((o * c + ci) * k + ky) * k + kx])
                                * f64::from(x[(ci * h + yy as usize) * w + xx as usize]);
                        }
                    }
                }
                out[(o * oh + y) * ow + xo] = s;
            }
        }
    }
    out
}

#[test]
fn ring_conv_matches_direct_circular_convolution() {
    let mut r = rng(4);
    for &(c, out_c, h, w, k, stride) in &[
        (3usize, 5usize, 6usize, 10usize, 3usize, 1usize),
        (4, 2, 8, 12, 3, 2),
        (2, 3, 5, 9, 5, 1),
        (3, 4, 4, 8, 1, 1),
    ] {
        let x = rand_tensor(&mut r, &[2, c, h, w]);
        let wt = rand_tensor(&mut r, &[out_c, c, k, k]);
        let b = rand_tensor(&mut r, &[out_c]);
        let conv = RingConv2d::from_weights(wt.clone(), Some(b.clone()), stride).unwrap();
        let y = conv.forward(&x).unwrap();
        let (oh, ow) = (h.div_ceil(stride), w.div_ceil(stride));
        assert_eq!(y.dims(), &[2, out_c, oh, ow]);
        let wv = wt.flatten_all().unwrap().to_vec1::<f32>().unwrap();
        let bv = b.to_vec1::<f32>().unwrap();
        for bi in 0..2 {
            let xb = x
                .get(bi)
                .unwrap()
                .flatten_all()
                .unwrap()
                .to_vec1::<f32>()
                .unwrap();
            let yb = y
                .get(bi)
                .unwrap()
                .flatten_all()
                .unwrap()
                .to_vec1::<f32>()
                .unwrap();
            let reference = ring_conv_ref(&xb, c, h, w, &wv, &bv, out_c, k, stride);
            for (a, e) in yb.iter().zip(&reference) {
                assert!(
                    (f64::from(*a) - e).abs() < 1e-4,
                    "c{c} o{out_c} {h}x{w} k{k} s{stride}: {a} vs {e}"
                );
            }
        }
    }
}

/// Direct zero-padded, strided 2-D convolution in f64 (the textbook sum), `[B, C, H, W]` row-major.
#[allow(clippy::too_many_arguments)]
fn conv_ref(
    x: &[f32],
    (b, c, h, w): (usize, usize, usize, usize),
    wt: &[f32],
    (oc, k): (usize, usize),
    bias: &[f32],
    pad: usize,
    stride: usize,
) -> (Vec<f64>, usize, usize) {
    let ho = (h + 2 * pad - k) / stride + 1;
    let wo = (w + 2 * pad - k) / stride + 1;
    let mut out = vec![0.0f64; b * oc * ho * wo];
    for bi in 0..b {
        for o in 0..oc {
            for y in 0..ho {
                for xo in 0..wo {
                    let mut acc = f64::from(bias[o]);
                    for ci in 0..c {
                        for ky in 0..k {
                            for kx in 0..k {
                                let iy = (y * stride + ky) as isize - pad as isize;
                                let ix = (xo * stride + kx) as isize - pad as isize;
                                if iy < 0 || ix < 0 || iy >= h as isize || ix >= w as isize {
                                    continue;
                                }
                                let xv = x[((bi * c + ci) * h + iy as usize) * w + ix as usize];
                                let wv = wt[((o * c + ci) * k + ky) * k + kx];
                                acc += f64::from(xv) * f64::from(wv);
                            }
                        }
                    }
                    out[((bi * oc + o) * ho + y) * wo + xo] = acc;
                }
            }
        }
    }
    (out, ho, wo)
}

#[test]
fn im2col_convolution_matches_the_direct_sum_for_every_stride_and_odd_size() {
    use veila_nn::ops::conv2d_zero_pad;
    let mut r = rng(11);
    for &(h, w, k, stride) in &[
        (7usize, 9usize, 3usize, 1usize),
        (7, 9, 3, 2),
        (8, 10, 3, 2),
        (5, 6, 1, 2),
        (6, 7, 5, 3),
    ] {
        let (b, c, oc) = (2, 3, 4);
        let x = rand_tensor(&mut r, &[b, c, h, w]);
        let wt = rand_tensor(&mut r, &[oc, c, k, k]);
        let bias = rand_tensor(&mut r, &[oc]);
        let pad = k / 2;
        let y = conv2d_zero_pad(&x, &wt, Some(&bias), pad, stride).unwrap();
        let (want, ho, wo) = conv_ref(
            &x.flatten_all().unwrap().to_vec1::<f32>().unwrap(),
            (b, c, h, w),
            &wt.flatten_all().unwrap().to_vec1::<f32>().unwrap(),
            (oc, k),
            &bias.to_vec1::<f32>().unwrap(),
            pad,
            stride,
        );
        assert_eq!(y.dims(), &[b, oc, ho, wo], "h {h} w {w} k {k} s {stride}");
        let got = y.flatten_all().unwrap().to_vec1::<f32>().unwrap();
        for (g, e) in got.iter().zip(&want) {
            assert!((f64::from(*g) - e).abs() < 1e-4, "{g} vs {e}");
        }
    }
}

#[test]
fn im2col_convolution_gradients_match_candles_conv2d() {
    use candle_core::Var;
    use veila_nn::ops::conv2d_zero_pad;
    let mut r = rng(5);
    for stride in [1usize, 2] {
        // even sizes: candle's own conv2d backward mis-sizes the input gradient of strided
        // convolutions over odd inputs (its transposed convolution drops the last row)
        let x = Var::from_tensor(&rand_tensor(&mut r, &[2, 3, 10, 8])).unwrap();
        let wt = Var::from_tensor(&rand_tensor(&mut r, &[4, 3, 3, 3])).unwrap();
        let upstream = rand_tensor(&mut r, &[2, 4, 10 / stride, 8 / stride]);
        let ours = conv2d_zero_pad(x.as_tensor(), wt.as_tensor(), None, 1, stride).unwrap();
        let theirs = x
            .as_tensor()
            .conv2d(wt.as_tensor(), 1, stride, 1, 1)
            .unwrap();
        let g1 = (ours * &upstream)
            .unwrap()
            .sum_all()
            .unwrap()
            .backward()
            .unwrap();
        let g2 = (theirs * &upstream)
            .unwrap()
            .sum_all()
            .unwrap()
            .backward()
            .unwrap();
        for v in [x.as_tensor(), wt.as_tensor()] {
            let a = g1
                .get(v)
                .unwrap()
                .flatten_all()
                .unwrap()
                .to_vec1::<f32>()
                .unwrap();
            let b = g2
                .get(v)
                .unwrap()
                .flatten_all()
                .unwrap()
                .to_vec1::<f32>()
                .unwrap();
            for (p, q) in a.iter().zip(&b) {
                assert!((p - q).abs() < 1e-4, "stride {stride}: {p} vs {q}");
            }
        }
    }
}

#[test]
fn broadcast_upsampling_equals_nearest_neighbour_and_sums_its_gradient() {
    use candle_core::Var;
    use veila_nn::ops::upsample_nearest;
    let mut r = rng(3);
    let x = Var::from_tensor(&rand_tensor(&mut r, &[2, 3, 4, 5])).unwrap();
    let up = upsample_nearest(x.as_tensor(), 2).unwrap();
    let reference = x.as_tensor().upsample_nearest2d(8, 10).unwrap();
    let d = (&up - &reference)
        .unwrap()
        .abs()
        .unwrap()
        .max_all()
        .unwrap();
    assert_eq!(d.to_scalar::<f32>().unwrap(), 0.0);
    // d(sum(up))/dx = factor^2 for every input
    let g = up.sum_all().unwrap().backward().unwrap();
    let gx = g
        .get(x.as_tensor())
        .unwrap()
        .flatten_all()
        .unwrap()
        .to_vec1::<f32>()
        .unwrap();
    assert!(gx.iter().all(|v| *v == 4.0));
}
