//! CACM (equations 4-6) against a per-pixel reference, and its degenerate confidences.

use std::collections::HashMap;

use crate::common::*;
use candle_core::{DType, Device, Tensor};
use candle_nn::VarBuilder;
use veila_nn::Cacm;
use veila_nn::ops::bilinear_resize;

fn cacm_weights(
    ds: usize,
    dd: usize,
    c: usize,
    conf_bias: (f32, f32),
    seed: u64,
) -> HashMap<String, Tensor> {
    let mut r = rng(seed);
    let mut m = HashMap::new();
    m.insert("proj_s.weight".into(), rand_tensor(&mut r, &[c, ds, 1, 1]));
    m.insert("proj_s.bias".into(), rand_tensor(&mut r, &[c]));
    m.insert("proj_d.weight".into(), rand_tensor(&mut r, &[c, dd, 1, 1]));
    m.insert("proj_d.bias".into(), rand_tensor(&mut r, &[c]));
    m.insert(
        "conf_s.weight".into(),
        rand_tensor(&mut r, &[1, c, 3, 3]).affine(0.1, 0.0).unwrap(),
    );
    m.insert(
        "conf_d.weight".into(),
        rand_tensor(&mut r, &[1, c, 3, 3]).affine(0.1, 0.0).unwrap(),
    );
    m.insert(
        "conf_s.bias".into(),
        Tensor::new(&[conf_bias.0], &Device::Cpu).unwrap(),
    );
    m.insert(
        "conf_d.bias".into(),
        Tensor::new(&[conf_bias.1], &Device::Cpu).unwrap(),
    );
    m
}

/// Per-pixel f64 evaluation of equations 4-6 from the weights (3x3 confidence convs with zero padding).
#[test]
fn cacm_matches_per_pixel_reference() {
    let (ds, dd, c, h, w) = (5, 4, 6, 6, 10);
    let weights = cacm_weights(ds, dd, c, (0.3, -0.2), 1);
    let delta = 1e-3;
    let cacm = Cacm::new(
        ds,
        dd,
        c,
        delta,
        VarBuilder::from_tensors(weights.clone(), DType::F32, &Device::Cpu),
    )
    .unwrap();
    let mut r = rng(2);
    let fs = rand_tensor(&mut r, &[1, ds, h, w]);
    let fd = rand_tensor(&mut r, &[1, dd, 3, 5]);
    let (out, cs, cd) = cacm.forward_with_confidence(&fs, &fd).unwrap();
    assert_eq!(out.dims(), &[1, c, h, w]);
    let v = |n: &str| weights[n].flatten_all().unwrap().to_vec1::<f32>().unwrap();
    let (ws, bs, wd, bd) = (
        v("proj_s.weight"),
        v("proj_s.bias"),
        v("proj_d.weight"),
        v("proj_d.bias"),
    );
    let (wcs, wcd) = (v("conf_s.weight"), v("conf_d.weight"));
    let (bcs, bcd) = (v("conf_s.bias")[0], v("conf_d.bias")[0]);
    let fsv = fs.flatten_all().unwrap().to_vec1::<f32>().unwrap();
    // the resize itself is checked against PyTorch's formula in tests/it/ops.rs
    let fdv = bilinear_resize(&fd, h, w)
        .unwrap()
        .flatten_all()
        .unwrap()
        .to_vec1::<f32>()
        .unwrap();
    let proj = |wm: &[f32], b: &[f32], x: &[f32], cin: usize| -> Vec<f64> {
        let mut o = vec![0.0; c * h * w];
        for co in 0..c {
            for p in 0..h * w {
                o[co * h * w + p] = f64::from(b[co])
                    + (0..cin)
                        .map(|ci| f64::from(wm[co * cin + ci]) * f64::from(x[ci * h * w + p]))
                        .sum::<f64>();
            }
        }
        o
    };
    let ts = proj(&ws, &bs, &fsv, ds);
    let td = proj(&wd, &bd, &fdv, dd);
    let conf = |t: &[f64], wk: &[f32], b: f32, y: usize, x: usize| -> f64 {
        let mut s = f64::from(b);
        for ci in 0..c {
            for ky in 0..3 {
                for kx in 0..3 {
                    let (yy, xx) = (y as i64 + ky as i64 - 1, x as i64 + kx as i64 - 1);
                    if yy < 0 || xx < 0 || yy >= h as i64 || xx >= w as i64 {
                        continue;
                    }
                    s += f64::from(wk[ci * 9 + ky * 3 + kx])
                        * t[ci * h * w + yy as usize * w + xx as usize];
                }
            }
        }
        1.0 / (1.0 + (-s).exp())
    };
    let outv = out.flatten_all().unwrap().to_vec1::<f32>().unwrap();
    let (csv, cdv) = (
        cs.flatten_all().unwrap().to_vec1::<f32>().unwrap(),
        cd.flatten_all().unwrap().to_vec1::<f32>().unwrap(),
    );
    for y in 0..h {
        for x in 0..w {
            let p = y * w + x;
            let (a, b) = (conf(&ts, &wcs, bcs, y, x), conf(&td, &wcd, bcd, y, x));
            assert!((f64::from(csv[p]) - a).abs() < 1e-5 && (f64::from(cdv[p]) - b).abs() < 1e-5);
            for co in 0..c {
                let e =
                    (a * ts[co * h * w + p] + b * td[co * h * w + p]) / (a + b + f64::from(delta));
                assert!(
                    (f64::from(outv[co * h * w + p]) - e).abs() < 1e-4,
                    "pixel {p} ch {co}"
                );
            }
        }
    }
}

#[test]
fn cacm_with_both_confidences_near_zero_is_finite_and_defined() {
    let (ds, dd, c) = (3, 3, 4);
    let mut r = rng(3);
    let fs = rand_tensor(&mut r, &[2, ds, 5, 7]);
    let fd = rand_tensor(&mut r, &[2, dd, 5, 7]);
    // biases of -1e4: sigmoid underflows to exactly 0 for both cues -> F = 0 / delta = 0
    let cacm = Cacm::new(
        ds,
        dd,
        c,
        1e-6,
        VarBuilder::from_tensors(
            cacm_weights(ds, dd, c, (-1e4, -1e4), 4),
            DType::F32,
            &Device::Cpu,
        ),
    )
    .unwrap();
    let (out, cs, cd) = cacm.forward_with_confidence(&fs, &fd).unwrap();
    assert!(all_finite(&out));
    assert_eq!(cs.max_all().unwrap().to_scalar::<f32>().unwrap(), 0.0);
    assert_eq!(cd.max_all().unwrap().to_scalar::<f32>().unwrap(), 0.0);
    assert_eq!(
        out.abs()
            .unwrap()
            .max_all()
            .unwrap()
            .to_scalar::<f32>()
            .unwrap(),
        0.0
    );
    // biases of -80: confidences ~1.8e-35 (tiny but non-zero, below delta): finite and bounded by the
    // projected features times c/(2c+delta) << 1
    let cacm = Cacm::new(
        ds,
        dd,
        c,
        1e-6,
        VarBuilder::from_tensors(
            cacm_weights(ds, dd, c, (-80.0, -80.0), 4),
            DType::F32,
            &Device::Cpu,
        ),
    )
    .unwrap();
    let out = cacm.forward(&fs, &fd).unwrap();
    assert!(all_finite(&out));
    assert!(
        out.abs()
            .unwrap()
            .max_all()
            .unwrap()
            .to_scalar::<f32>()
            .unwrap()
            < 1e-20
    );
    // one cue fully confident, the other off: F = F~_s / (1 + delta)
    let w = cacm_weights(ds, dd, c, (1e4, -1e4), 4);
    let cacm = Cacm::new(
        ds,
        dd,
        c,
        1e-6,
        VarBuilder::from_tensors(w.clone(), DType::F32, &Device::Cpu),
    )
    .unwrap();
    let out = cacm.forward(&fs, &fd).unwrap();
    let proj = veila_nn::ops::Conv1x1::new(
        ds,
        c,
        true,
        VarBuilder::from_tensors(w, DType::F32, &Device::Cpu).pp("proj_s"),
    )
    .unwrap();
    let expected = (proj.forward(&fs).unwrap() / (1.0 + 1e-6)).unwrap();
    assert!(max_abs_diff(&out, &expected) < 1e-5);
}
