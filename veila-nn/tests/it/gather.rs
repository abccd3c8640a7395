//! GCMA's one-op bilinear gather against its candle composition: output and source gradient, on
//! the CPU kernel (f32) and on the recomputed composition other devices run (f64 here).

use std::sync::Arc;

use crate::common::*;
use candle_core::{DType, Device, Tensor, Var};
use rand::Rng;
use veila_nn::gather::{GatherTaps, bilinear_gather, bilinear_gather_reference};

fn taps(rows: usize, n: usize, seed: u64) -> GatherTaps {
    let mut r = rng(seed);
    let idx = std::array::from_fn(|_| (0..n).map(|_| r.random_range(0..rows as u32)).collect());
    // a quarter of the weights zero (corners outside the image, invalid samples)
    let w = std::array::from_fn(|_| {
        (0..n)
            .map(|_| {
                if r.random_range(0..4) == 0 {
                    0.0
                } else {
                    r.random_range(0.0f32..1.0)
                }
            })
            .collect()
    });
    GatherTaps::new(idx, w, &Device::Cpu).unwrap()
}

/// Output and the source's gradient of `sum(out * probe)`.
fn run(
    src: &Tensor,
    probe: &Tensor,
    f: impl Fn(&Tensor) -> veila_nn::Result<Tensor>,
) -> (Vec<f64>, Vec<f64>) {
    let v = Var::from_tensor(src).unwrap();
    let out = f(v.as_tensor()).unwrap();
    let loss = (&out * probe).unwrap().sum_all().unwrap();
    let g = loss.backward().unwrap();
    let flat = |t: &Tensor| {
        t.to_dtype(DType::F64)
            .unwrap()
            .flatten_all()
            .unwrap()
            .to_vec1::<f64>()
            .unwrap()
    };
    (flat(&out), flat(g.get(v.as_tensor()).unwrap()))
}

fn worst(a: &[f64], b: &[f64]) -> f64 {
    assert_eq!(a.len(), b.len());
    let scale = b.iter().fold(0.0f64, |m, x| m.max(x.abs()));
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f64::max)
        / scale.max(1e-30)
}

#[test]
fn the_gather_op_equals_its_composition_forward_and_backward() {
    for (dtype, tol) in [(DType::F32, 1e-6), (DType::F64, 1e-12)] {
        let (b, rows, c, n) = (2, 50, 12, 300);
        let taps = Arc::new(taps(rows, n, 7));
        let mut r = rng(8);
        let src = rand_tensor(&mut r, &[b, rows, c]).to_dtype(dtype).unwrap();
        let probe = rand_tensor(&mut r, &[b, n, c]).to_dtype(dtype).unwrap();
        let (y1, g1) = run(&src, &probe, |s| bilinear_gather(s, &taps));
        let (y0, g0) = run(&src, &probe, |s| bilinear_gather_reference(s, &taps));
        let (dy, dg) = (worst(&y1, &y0), worst(&g1, &g0));
        eprintln!("{dtype:?}: output {dy:.1e}, gradient {dg:.1e}");
        assert!(dy <= tol && dg <= tol, "{dtype:?}: {dy} {dg}");
        // the gradient reaches rows (many samples share a row, a zero weight adds nothing)
        assert!(g0.iter().filter(|x| **x != 0.0).count() > g0.len() / 2);
    }
}

#[test]
fn a_corner_past_the_source_is_an_error_not_a_panic() {
    let taps = Arc::new(taps(50, 10, 1));
    let src = Tensor::zeros((1, 20, 4), DType::F32, &Device::Cpu).unwrap();
    let e = bilinear_gather(&src, &taps).unwrap_err().to_string();
    assert!(e.contains("past the source"), "{e}");
}
