//! GCMA against a brute-force f64 reference written from equations 7-10 (with `grid_sample`-style
//! bilinear sampling, zeros outside the image), plus the degenerate cases.

use crate::common::*;
use candle_core::{DType, Device, Tensor};
use candle_nn::VarMap;
use veila_geom::{EpipolarTable, PinholeCamera, RayTable};
use veila_nn::gcma::sensor_at_level;
use veila_nn::{DenoiserConfig, Gcma, GcmaGeometry, seeded_var_builder};

fn get(vm: &VarMap, name: &str) -> Vec<f64> {
    let data = vm.data().lock().unwrap();
    let t = data.get(name).unwrap_or_else(|| panic!("no {name}"));
    t.as_tensor()
        .flatten_all()
        .unwrap()
        .to_vec1::<f32>()
        .unwrap()
        .into_iter()
        .map(f64::from)
        .collect()
}

/// `grid_sample(..., mode="bilinear", padding_mode="zeros", align_corners=False)` of a `[C, H, W]` map.
fn grid_sample(feat: &[f32], c: usize, h: usize, w: usize, gx: f32, gy: f32) -> Vec<f64> {
    let x = ((f64::from(gx) + 1.0) * w as f64 - 1.0) / 2.0;
    let y = ((f64::from(gy) + 1.0) * h as f64 - 1.0) / 2.0;
    let (x0, y0) = (x.floor(), y.floor());
    let mut out = vec![0.0; c];
    for (dx, dy) in [(0.0, 0.0), (1.0, 0.0), (0.0, 1.0), (1.0, 1.0)] {
        let (xi, yi) = (x0 + dx, y0 + dy);
        let wt = (1.0 - (x - xi).abs()) * (1.0 - (y - yi).abs());
        if xi < 0.0 || yi < 0.0 || xi >= w as f64 || yi >= h as f64 {
            continue;
        }
        for ch in 0..c {
            out[ch] += wt * f64::from(feat[ch * h * w + yi as usize * w + xi as usize]);
        }
    }
    out
}

fn group_norm_ref(
    x: &[f32],
    c: usize,
    hw: usize,
    groups: usize,
    gamma: &[f64],
    beta: &[f64],
) -> Vec<f64> {
    let cg = c / groups;
    let mut out = vec![0.0; c * hw];
    for g in 0..groups {
        let vals: Vec<f64> = (g * cg * hw..(g + 1) * cg * hw)
            .map(|i| f64::from(x[i]))
            .collect();
        let mean = vals.iter().sum::<f64>() / vals.len() as f64;
        let var = vals.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / vals.len() as f64;
        for ch in g * cg..(g + 1) * cg {
            for p in 0..hw {
                out[ch * hw + p] =
                    (f64::from(x[ch * hw + p]) - mean) / (var + 1e-5).sqrt() * gamma[ch] + beta[ch];
            }
        }
    }
    out
}

fn matvec(wm: &[f64], bias: Option<&[f64]>, x: &[f64], out_n: usize) -> Vec<f64> {
    let in_n = x.len();
    (0..out_n)
        .map(|o| {
            (0..in_n).map(|i| wm[o * in_n + i] * x[i]).sum::<f64>() + bias.map_or(0.0, |b| b[o])
        })
        .collect()
}

/// Runs GCMA at `level` of the small config with `cameras` and compares with the reference.
fn check_against_reference(cameras: &[PinholeCamera], level: usize, feature_scale: f32) {
    let mut cfg = small_config();
    let k = 5;
    let cc = cfg.conditioning.as_mut().unwrap();
    cc.num_views = cameras.len();
    let g = cc.gcma.clone().unwrap();
    let scale = cc.scale_for_level(level);
    let [fh, fw] = cc.feature_sizes[scale];
    let fc = cc.cond_channels[scale];
    let cfg: DenoiserConfig = cfg;
    let dev = Device::Cpu;
    let geom = GcmaGeometry::new(&cfg, cameras, &crate::common::epipolar(k), &dev).unwrap();
    let lg = geom.level(level).unwrap();
    let (h, w) = lg.range_size();
    let c = cfg.level_channels(level);
    let groups = veila_nn::ops::groups_for(c, cfg.norm_groups);

    let vm = VarMap::new();
    let gcma = Gcma::new(
        &g,
        c,
        fc,
        cfg.norm_groups,
        seeded_var_builder(&vm, 11, DType::F32, &dev).pp("gcma"),
    )
    .unwrap();
    // give the (otherwise identity) GroupNorm affine parameters non-trivial values
    {
        let mut r = rng(5);
        let data = vm.data().lock().unwrap();
        for n in ["gcma.norm.weight", "gcma.norm.bias"] {
            data[n].set(&rand_tensor(&mut r, &[c])).unwrap();
        }
    }
    let mut r = rng(7);
    let b = 2;
    let views = cameras.len();
    let rin = rand_tensor(&mut r, &[b, c, h, w]);
    let feat = rand_tensor(&mut r, &[b * views, fc, fh, fw])
        .affine(f64::from(feature_scale), 0.0)
        .unwrap();
    let out = gcma.attend(&rin, &feat, lg).unwrap();
    let d = g.attn_dim;
    assert_eq!(out.dims(), &[b, d, h, w]);
    let out = out.flatten_all().unwrap().to_vec1::<f32>().unwrap();

    let (wq, bq) = (get(&vm, "gcma.q.weight"), get(&vm, "gcma.q.bias"));
    let wkv = get(&vm, "gcma.kv.weight");
    let (w0, b0) = (get(&vm, "gcma.pos.0.weight"), get(&vm, "gcma.pos.0.bias"));
    let (w2, b2) = (get(&vm, "gcma.pos.2.weight"), get(&vm, "gcma.pos.2.bias"));
    let (gamma, beta) = (get(&vm, "gcma.norm.weight"), get(&vm, "gcma.norm.bias"));
    let sensor = sensor_at_level(&cfg.sensor, level).unwrap();
    let rays = RayTable::new(&sensor).unwrap();
    let tables: Vec<EpipolarTable> = cameras
        .iter()
        .map(|cam| EpipolarTable::build(&rays, cam, &crate::common::epipolar(k)).unwrap())
        .collect();
    let rin_v = rin.flatten_all().unwrap().to_vec1::<f32>().unwrap();
    let feat_v = feat.flatten_all().unwrap().to_vec1::<f32>().unwrap();
    let heads = g.num_heads;
    let dh = d / heads;
    let mut active = 0;
    let mut max_err = 0f64;
    let mut max_mag = 0f64;
    for bi in 0..b {
        let gn = group_norm_ref(
            &rin_v[bi * c * h * w..(bi + 1) * c * h * w],
            c,
            h * w,
            groups,
            &gamma,
            &beta,
        );
        for p in 0..h * w {
            let (row, col) = ((p / w) as u32, (p % w) as u32);
            let x: Vec<f64> = (0..c).map(|ch| gn[ch * h * w + p]).collect();
            let q = matvec(&wq, Some(&bq), &x, d);
            // (valid weight, logits per head, value)
            let mut samples: Vec<(f64, Vec<f64>, Vec<f64>)> = Vec::new();
            for (v, t) in tables.iter().enumerate() {
                for kk in 0..k {
                    let i = t.sample_idx(row, col, kk);
                    if !t.valid[i] || t.weight[i] <= 0.0 {
                        continue;
                    }
                    let fmap = &feat_v
                        [(bi * views + v) * fc * fh * fw..(bi * views + v + 1) * fc * fh * fw];
                    let f = grid_sample(fmap, fc, fh, fw, t.grid[i][0], t.grid[i][1]);
                    let kv = matvec(&wkv, None, &f, 2 * d);
                    let mut gam = Vec::new();
                    g.point_encoding
                        .encode(t.sample_point_lidar(row, col, kk), &mut gam);
                    let gam: Vec<f64> = gam.into_iter().map(f64::from).collect();
                    let hid: Vec<f64> = matvec(&w0, Some(&b0), &gam, d)
                        .into_iter()
                        .map(|z| z / (1.0 + (-z).exp()))
                        .collect();
                    let pos = matvec(&w2, Some(&b2), &hid, d);
                    let logits: Vec<f64> = (0..heads)
                        .map(|hh| {
                            (0..dh)
                                .map(|j| (q[hh * dh + j] + pos[hh * dh + j]) * kv[hh * dh + j])
                                .sum::<f64>()
                                / (dh as f64).sqrt()
                        })
                        .collect();
                    samples.push((f64::from(t.weight[i]), logits, kv[d..].to_vec()));
                }
            }
            let mut expected = vec![0.0; d];
            if !samples.is_empty() {
                active += 1;
                for hh in 0..heads {
                    let m = samples
                        .iter()
                        .map(|s| s.1[hh])
                        .fold(f64::NEG_INFINITY, f64::max);
                    let z: f64 = samples.iter().map(|s| s.0 * (s.1[hh] - m).exp()).sum();
                    for s in &samples {
                        let a = s.0 * (s.1[hh] - m).exp() / z;
                        for j in 0..dh {
                            expected[hh * dh + j] += a * s.2[hh * dh + j];
                        }
                    }
                }
            }
            for (j, e) in expected.iter().enumerate() {
                let got = f64::from(out[((bi * d) + j) * h * w + p]);
                assert!(got.is_finite());
                if samples.is_empty() {
                    assert_eq!(got, 0.0, "pixel without valid samples must be exactly zero");
                }
                max_err = max_err.max((got - e).abs());
                max_mag = max_mag.max(e.abs());
            }
        }
    }
    assert_eq!(active, b * lg.num_active(), "active pixel count");
    assert!(
        lg.num_active() > 0 && lg.num_active() < h * w,
        "the camera sees part of the panorama"
    );
    assert!(
        max_err <= 1e-4 * max_mag.max(1.0),
        "max error {max_err} (magnitude {max_mag})"
    );
}

#[test]
fn gcma_matches_bruteforce_reference_single_view() {
    check_against_reference(&[kitti_camera()], 0, 1.0);
    check_against_reference(&[kitti_camera()], 2, 1.0);
}

#[test]
fn gcma_matches_bruteforce_reference_two_views() {
    check_against_reference(&[kitti_camera(), rear_camera()], 1, 1.0);
}

#[test]
fn gcma_stays_finite_with_huge_features() {
    // features of 1e18 make q.k overflow f32 (|logit| ~ 1e36 .. inf): the masked softmax must stay finite
    let cfg = small_config();
    let dev = Device::Cpu;
    let geom =
        GcmaGeometry::new(&cfg, &[kitti_camera()], &crate::common::epipolar(4), &dev).unwrap();
    let g = cfg.conditioning.as_ref().unwrap().gcma.clone().unwrap();
    let vm = VarMap::new();
    let gcma = Gcma::new(&g, 16, 8, 4, seeded_var_builder(&vm, 3, DType::F32, &dev)).unwrap();
    let mut r = rng(9);
    let rin = rand_tensor(&mut r, &[1, 16, 16, 128])
        .affine(1e18, 0.0)
        .unwrap();
    let feat = rand_tensor(&mut r, &[1, 8, 12, 40])
        .affine(1e18, 0.0)
        .unwrap();
    let out = gcma.attend(&rin, &feat, geom.level(0).unwrap()).unwrap();
    assert!(all_finite(&out));
}

#[test]
fn untrained_gcma_is_exactly_the_identity_and_keep_zero_drops_it() {
    let cfg = small_config();
    let dev = Device::Cpu;
    let geom =
        GcmaGeometry::new(&cfg, &[kitti_camera()], &crate::common::epipolar(4), &dev).unwrap();
    let g = cfg.conditioning.as_ref().unwrap().gcma.clone().unwrap();
    let vm = VarMap::new();
    let gcma = Gcma::new(&g, 16, 8, 4, seeded_var_builder(&vm, 3, DType::F32, &dev)).unwrap();
    let mut r = rng(10);
    let rin = rand_tensor(&mut r, &[2, 16, 16, 128]);
    let feat = rand_tensor(&mut r, &[2, 8, 12, 40]);
    let lg = geom.level(0).unwrap();
    let out = gcma.forward(&rin, &feat, lg, None).unwrap();
    let a = out.flatten_all().unwrap().to_vec1::<f32>().unwrap();
    let b = rin.flatten_all().unwrap().to_vec1::<f32>().unwrap();
    assert!(
        a.iter().zip(&b).all(|(x, y)| x.to_bits() == y.to_bits()),
        "zero-init GCMA changed its input"
    );
    // trained (non-zero) output conv: the branch is active, and keep = 0 removes it per sample
    {
        let data = vm.data().lock().unwrap();
        data["out.weight"]
            .set(&rand_tensor(&mut r, &[16, 8, 1, 1]))
            .unwrap();
    }
    let keep = Tensor::new(&[1f32, 0.0], &dev).unwrap();
    let out = gcma.forward(&rin, &feat, lg, Some(&keep)).unwrap();
    let d0 = max_abs_diff(&out.narrow(0, 0, 1).unwrap(), &rin.narrow(0, 0, 1).unwrap());
    let d1 = max_abs_diff(&out.narrow(0, 1, 1).unwrap(), &rin.narrow(0, 1, 1).unwrap());
    assert!(
        d0 > 1e-3,
        "a trained GCMA changes the conditioned sample ({d0})"
    );
    assert_eq!(d1, 0.0, "keep = 0 leaves the sample unchanged");
}

#[test]
fn geometry_rejects_wrong_view_count_and_feature_shapes() {
    let cfg = small_config();
    let dev = Device::Cpu;
    assert!(
        GcmaGeometry::new(
            &cfg,
            &[kitti_camera(), rear_camera()],
            &crate::common::epipolar(4),
            &dev
        )
        .is_err()
    );
    let geom =
        GcmaGeometry::new(&cfg, &[kitti_camera()], &crate::common::epipolar(4), &dev).unwrap();
    let g = cfg.conditioning.as_ref().unwrap().gcma.clone().unwrap();
    let gcma = Gcma::new(
        &g,
        16,
        8,
        4,
        seeded_var_builder(&VarMap::new(), 3, DType::F32, &dev),
    )
    .unwrap();
    let rin = Tensor::zeros((1, 16, 16, 128), DType::F32, &dev).unwrap();
    let bad = Tensor::zeros((1, 8, 13, 40), DType::F32, &dev).unwrap();
    let err = gcma
        .attend(&rin, &bad, geom.level(0).unwrap())
        .unwrap_err()
        .to_string();
    assert!(err.contains("conditioning map"), "{err}");
}

/// Tables in which no sample of any pixel is valid (e.g. a camera that sees none of the sampled depths):
/// GCMA attends to nothing, its output is exactly zero (no NaN from an empty softmax), and a denoiser with
/// such a geometry equals the unconditioned one.
#[test]
fn every_sample_invalid_gives_zero_attention_and_no_nan() {
    let cfg = small_config();
    let dev = Device::Cpu;
    let epi = crate::common::epipolar(3);
    let mut tables = Vec::new();
    for level in 0..4 {
        let rays = RayTable::new(&sensor_at_level(&cfg.sensor, level).unwrap()).unwrap();
        let mut t = EpipolarTable::build(&rays, &kitti_camera(), &epi).unwrap();
        assert!(
            t.valid.iter().any(|v| *v),
            "the camera sees something before invalidation"
        );
        t.valid.iter_mut().for_each(|v| *v = false);
        t.weight.iter_mut().for_each(|w| *w = 0.0);
        tables.push((level, vec![t]));
    }
    let geom = GcmaGeometry::from_tables(&cfg, &tables, &dev).unwrap();
    assert!(geom.levels().iter().all(|l| l.num_active() == 0));
    let g = cfg.conditioning.as_ref().unwrap().gcma.clone().unwrap();
    let vm = VarMap::new();
    let gcma = Gcma::new(&g, 16, 8, 4, seeded_var_builder(&vm, 3, DType::F32, &dev)).unwrap();
    {
        // a "trained" output conv, so that a NaN or non-zero attention would show in the output
        let data = vm.data().lock().unwrap();
        data["out.weight"]
            .set(&rand_tensor(&mut rng(1), &[16, 8, 1, 1]))
            .unwrap();
    }
    let rin = rand_tensor(&mut rng(2), &[1, 16, 16, 128]);
    let feat = rand_tensor(&mut rng(3), &[1, 8, 12, 40]);
    let att = gcma.attend(&rin, &feat, geom.level(0).unwrap()).unwrap();
    assert_eq!(
        att.abs()
            .unwrap()
            .max_all()
            .unwrap()
            .to_scalar::<f32>()
            .unwrap(),
        0.0
    );
    let out = gcma
        .forward(&rin, &feat, geom.level(0).unwrap(), None)
        .unwrap();
    assert_eq!(max_abs_diff(&out, &rin), 0.0);
    // the whole network: conditioned with the empty geometry == unconditioned
    let (_, net) = varmap_model(&cfg, 5);
    let (sem, dep) = rand_pyramids(&mut rng(4), &cfg, 1);
    let prepared = net
        .prepare_condition(
            &veila_nn::ConditionInput {
                semantic: Some(sem),
                depth: Some(dep),
                keep: None,
            },
            Some(&geom),
        )
        .unwrap();
    let x = rand_tensor(&mut rng(6), &[1, 3, 16, 128]);
    let t = Tensor::new(&[0.5f32], &dev).unwrap();
    let a = net.forward(&x, &t, Some(&prepared)).unwrap();
    assert!(all_finite(&a));
    assert_eq!(max_abs_diff(&a, &net.forward(&x, &t, None).unwrap()), 0.0);
}

/// The sample attention's written-out gradient against candle's backward pass through its
/// composition, in f64 (1e-12) and f32, with masked samples, a pixel whose samples are all
/// masked, and large logits; and bf16 (f32 inside) against f64 within its rounding.
#[test]
fn the_sample_attention_gradient_by_hand_equals_the_compositions() {
    use veila_nn::gcma::{sample_attention, sample_attention_grad, sample_attention_reference};
    let (b, p, s, d, heads) = (2, 7, 5, 8, 2);
    let mut r = rng(21);
    let dev = Device::Cpu;
    let mut valid = vec![1u8; p * s];
    let mut log_w: Vec<f32> = rand_tensor(&mut r, &[p * s])
        .to_vec1::<f32>()
        .unwrap()
        .into_iter()
        .map(|x| -x.abs())
        .collect();
    for k in [1, 3, 8, 14, 22] {
        valid[k] = 0;
        log_w[k] = 0.0;
    }
    for k in 0..s {
        valid[4 * s + k] = 0; // pixel 4: no valid sample
    }
    let valid = Tensor::from_vec(valid, (p, s), &dev).unwrap();
    let log_w = Tensor::from_vec(log_w, (p, s), &dev).unwrap();
    let qr = rand_tensor(&mut r, &[b, p, d]);
    let pos = rand_tensor(&mut r, &[p, s, d]);
    // keys scaled up: logits of tens, a peaked softmax
    let kv = (rand_tensor(&mut r, &[b, p * s, 2 * d]) * 6.0).unwrap();
    let probe = rand_tensor(&mut r, &[b, p, d]);
    for (dtype, tol) in [(DType::F64, 1e-12), (DType::F32, 1e-5)] {
        let inputs: Vec<Tensor> = [&qr, &pos, &kv]
            .iter()
            .map(|t| t.to_dtype(dtype).unwrap())
            .collect();
        let probe = probe.to_dtype(dtype).unwrap();
        let run = |f: &dyn Fn(&[&Tensor]) -> Tensor| {
            let vars: Vec<candle_core::Var> = inputs
                .iter()
                .map(|t| candle_core::Var::from_tensor(t).unwrap())
                .collect();
            let ts: Vec<&Tensor> = vars.iter().map(|v| v.as_tensor()).collect();
            let y = f(&ts);
            let g = (&y * &probe)
                .unwrap()
                .sum_all()
                .unwrap()
                .backward()
                .unwrap();
            let grads: Vec<Tensor> = ts.iter().map(|t| g.get(t).unwrap().clone()).collect();
            (y, grads)
        };
        let (y1, g1) = run(&|t| sample_attention(t[0], t[1], t[2], &log_w, &valid, heads).unwrap());
        let (y0, g0) =
            run(&|t| sample_attention_reference(t[0], t[1], t[2], &log_w, &valid, heads).unwrap());
        let rel = |a: &Tensor, z: &Tensor| max_abs(&(a - z).unwrap()) / max_abs(z).max(1e-300);
        assert!(rel(&y1, &y0) <= tol, "{dtype:?} output");
        for (name, (a, z)) in ["qr", "pos", "kv"].iter().zip(g1.iter().zip(&g0)) {
            assert_eq!(a.dims(), z.dims());
            let e = rel(a, z);
            assert!(e <= tol, "{dtype:?}, gradient of {name}: {e:e}");
        }
        // pixel 4 attends to nothing: no gradient reaches its samples' keys and values
        let gkv = g1[2].to_dtype(DType::F64).unwrap();
        let dead = gkv
            .narrow(1, 4 * s, s)
            .unwrap()
            .abs()
            .unwrap()
            .sum_all()
            .unwrap();
        assert_eq!(dead.to_scalar::<f64>().unwrap(), 0.0);
        // bf16: computed in f32 inside, the gradients within bf16 rounding of f64's
        if dtype == DType::F64 {
            let bf = |t: &Tensor| t.to_dtype(DType::BF16).unwrap();
            let rounded: Vec<Tensor> = inputs
                .iter()
                .map(|t| bf(t).to_dtype(DType::F64).unwrap())
                .collect();
            let (gq, gp, gkv) = sample_attention_grad(
                &bf(&rounded[0]),
                &bf(&rounded[1]),
                &bf(&rounded[2]),
                &log_w,
                &valid,
                heads,
                &bf(&probe),
            )
            .unwrap();
            assert_eq!(gq.dtype(), DType::BF16);
            let (want_q, want_p, want_kv) = sample_attention_grad(
                &rounded[0],
                &rounded[1],
                &rounded[2],
                &log_w,
                &valid,
                heads,
                &bf(&probe).to_dtype(DType::F64).unwrap(),
            )
            .unwrap();
            for (name, (a, z)) in [
                ("qr", (&gq, &want_q)),
                ("pos", (&gp, &want_p)),
                ("kv", (&gkv, &want_kv)),
            ] {
                let e = rel(&a.to_dtype(DType::F64).unwrap(), z);
                assert!(e <= 2e-2, "bf16, gradient of {name}: {e:e}");
            }
        }
    }
}
