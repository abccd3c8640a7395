//! The FRD / FPD feature networks: shapes, official tensor layouts (closed-form parameter counts),
//! convolution and max-pool against brute force, invariances, determinism, bundle round trips and
//! integrity checks.

use std::collections::HashMap;

use candle_core::{DType, Device, Tensor};
use candle_nn::{Optimizer, VarMap};
use glam::Vec3;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use veila_geom::LidarSensor;
use veila_nn::feature_nets::{
    self, FeatureNets, PointNet, PointNetConfig, RangeNet, RangeNetConfig, RangeNetInput,
    rangenet::conv2d_strided,
};
use veila_nn::{Error, seeded_var_builder};

fn tiny_range_cfg() -> RangeNetConfig {
    RangeNetConfig {
        sensor: LidarSensor {
            rows: 8,
            cols: 64,
            ..LidarSensor::hdl64e()
        },
        ..RangeNetConfig::small()
    }
}

fn tiny_point_cfg() -> PointNetConfig {
    PointNetConfig {
        num_points: Some(128),
        ..PointNetConfig::small()
    }
}

fn rand_vec(n: usize, seed: u64) -> Vec<f32> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    (0..n).map(|_| rng.random_range(-1.0f32..1.0)).collect()
}

fn varmap_tensors(varmap: &VarMap) -> HashMap<String, Tensor> {
    varmap
        .data()
        .lock()
        .unwrap()
        .iter()
        .map(|(k, v)| (k.clone(), v.as_tensor().clone()))
        .collect()
}

/// A street-like synthetic scan: ground ring, a wall and a box, seeded.
fn synthetic_scan(seed: u64, n: usize) -> (Vec<Vec3>, Vec<f32>) {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut pts = Vec::with_capacity(n);
    let mut inten = Vec::with_capacity(n);
    for i in 0..n {
        let az = rng.random_range(-std::f32::consts::PI..std::f32::consts::PI);
        let p = match i % 3 {
            0 => {
                let r = rng.random_range(3.0f32..40.0);
                Vec3::new(r * az.cos(), r * az.sin(), -1.73)
            }
            1 => Vec3::new(
                rng.random_range(-30.0..30.0),
                8.0,
                rng.random_range(-1.7..4.0),
            ),
            _ => Vec3::new(
                rng.random_range(5.0..9.0),
                rng.random_range(-3.0..-1.0),
                rng.random_range(-1.7..0.0),
            ),
        };
        pts.push(p);
        inten.push(rng.random_range(0.0..1.0));
    }
    (pts, inten)
}

#[test]
fn rangenet_shapes_and_levels() {
    let cfg = tiny_range_cfg();
    let dev = Device::Cpu;
    let vm = VarMap::new();
    let net = RangeNet::new(&cfg, seeded_var_builder(&vm, 1, DType::F32, &dev)).unwrap();
    let x = Tensor::from_vec(rand_vec(2 * 5 * 8 * 64, 2), (2, 5, 8, 64), &dev).unwrap();
    let levels = net.encode(&x, false).unwrap();
    let widths: Vec<usize> = levels.iter().map(|l| l.dim(3).unwrap()).collect();
    assert_eq!(widths, vec![64, 32, 16, 8, 4, 2]);
    assert!(
        levels.iter().all(|l| l.dim(2).unwrap() == 8),
        "rows never downsampled"
    );
    assert_eq!(net.forward(&x).unwrap().dims(), &[2, 20, 8, 64]);
    assert_eq!(net.features(&x).unwrap().dims(), &[2, 128]);
    // odd widths: ceil(W / 2) per stage
    let x = Tensor::zeros((1, 5, 3, 37), DType::F32, &dev).unwrap();
    let levels = net.encode(&x, false).unwrap();
    let widths: Vec<usize> = levels.iter().map(|l| l.dim(3).unwrap()).collect();
    assert_eq!(widths, vec![37, 19, 10, 5, 3, 2]);
    assert_eq!(net.forward(&x).unwrap().dims(), &[1, 20, 3, 37]);
    // wrong channel count is an error, not a panic
    let bad = Tensor::zeros((1, 4, 8, 64), DType::F32, &dev).unwrap();
    assert!(matches!(net.features(&bad), Err(Error::Shape { .. })));
}

#[test]
fn rangenet_features_are_the_mean_of_the_deepest_map() {
    let cfg = tiny_range_cfg();
    let dev = Device::Cpu;
    let vm = VarMap::new();
    let net = RangeNet::new(&cfg, seeded_var_builder(&vm, 4, DType::F32, &dev)).unwrap();
    let x = Tensor::from_vec(rand_vec(5 * 8 * 64, 5), (1, 5, 8, 64), &dev).unwrap();
    let deepest = net.encode(&x, false).unwrap().pop().unwrap();
    let (_, c, h, w) = deepest.dims4().unwrap();
    let v = deepest.flatten_all().unwrap().to_vec1::<f32>().unwrap();
    let f = net.features(&x).unwrap().to_vec2::<f32>().unwrap();
    for ch in 0..c {
        let mean: f64 = v[ch * h * w..(ch + 1) * h * w]
            .iter()
            .map(|&a| f64::from(a))
            .sum::<f64>()
            / (h * w) as f64;
        assert!((mean - f64::from(f[0][ch])).abs() < 1e-5 * (1.0 + mean.abs()));
    }
}

/// Parameter count of an official DarkNet backbone in closed form (conv weights without bias, four
/// BatchNorm vectors per conv).
fn darknet_params(blocks: [usize; 5]) -> usize {
    let widths = [32usize, 64, 128, 256, 512, 1024];
    let mut n = 5 * 32 * 9 + 4 * 32;
    for s in 0..5 {
        let (i, o) = (widths[s], widths[s + 1]);
        n += 9 * i * o + 4 * o;
        n += blocks[s] * (o * i + 4 * i + 9 * i * o + 4 * o);
    }
    n
}

#[test]
fn darknet_presets_match_the_official_layout() {
    for (cfg, blocks) in [
        (RangeNetConfig::darknet21(), [1, 1, 2, 2, 1]),
        (RangeNetConfig::darknet53(), [1, 2, 8, 8, 4]),
    ] {
        let t = RangeNet::expected_tensors(&cfg).unwrap();
        assert_eq!(
            RangeNet::parameter_count(&cfg).unwrap(),
            darknet_params(blocks)
        );
        assert_eq!(t["conv1.weight"], vec![32, 5, 3, 3]);
        assert_eq!(t["bn1.running_var"], vec![32]);
        assert_eq!(t["enc1.conv.weight"], vec![64, 32, 3, 3]);
        assert_eq!(t["enc1.residual_0.conv1.weight"], vec![32, 64, 1, 1]);
        assert_eq!(t["enc1.residual_0.conv2.weight"], vec![64, 32, 3, 3]);
        let last = blocks[4] - 1;
        assert_eq!(
            t[&format!("enc5.residual_{last}.conv2.weight")],
            vec![1024, 512, 3, 3]
        );
        assert!(!t.contains_key(&format!("enc5.residual_{}.conv1.weight", blocks[4])));
        assert!(!t.keys().any(|k| k.starts_with("head.")));
        assert_eq!(cfg.feature_dim(), 1024);
    }
    let small = RangeNet::parameter_count(&RangeNetConfig::small()).unwrap();
    assert!(small < 600_000, "small rangenet has {small} parameters");
}

/// Brute-force zero-padded convolution with separate strides.
fn conv_ref(
    x: &[f32],
    (c, h, w): (usize, usize, usize),
    wt: &[f32],
    (o, k): (usize, usize),
    pad: usize,
    (sh, sw): (usize, usize),
) -> (Vec<f64>, usize, usize) {
    let ho = (h + 2 * pad - k) / sh + 1;
    let wo = (w + 2 * pad - k) / sw + 1;
    let mut out = vec![0.0; o * ho * wo];
    for oc in 0..o {
        for y in 0..ho {
            for xo in 0..wo {
                let mut acc = 0.0f64;
                for ic in 0..c {
                    for ky in 0..k {
                        for kx in 0..k {
                            let iy = (y * sh + ky) as isize - pad as isize;
                            let ix = (xo * sw + kx) as isize - pad as isize;
                            if iy < 0 || ix < 0 || iy >= h as isize || ix >= w as isize {
                                continue;
                            }
                            acc += f64::from(x[(ic * h + iy as usize) * w + ix as usize])
                                * f64::from(wt[((oc * c + ic) * k + ky) * k + kx]);
                        }
                    }
                }
                out[(oc * ho + y) * wo + xo] = acc;
            }
        }
    }
    (out, ho, wo)
}

#[test]
fn strided_conv_matches_brute_force() {
    let dev = Device::Cpu;
    let (c, h, w, o, k) = (3, 5, 11, 4, 3);
    let xv = rand_vec(c * h * w, 10);
    let wv = rand_vec(o * c * k * k, 11);
    let x = Tensor::from_vec(xv.clone(), (1, c, h, w), &dev).unwrap();
    let wt = Tensor::from_vec(wv.clone(), (o, c, k, k), &dev).unwrap();
    for strides in [(1, 2), (2, 1), (1, 1), (2, 3)] {
        let y = conv2d_strided(&x, &wt, 1, strides.0, strides.1).unwrap();
        let (want, ho, wo) = conv_ref(&xv, (c, h, w), &wv, (o, k), 1, strides);
        assert_eq!(y.dims(), &[1, o, ho, wo], "strides {strides:?}");
        let got = y.flatten_all().unwrap().to_vec1::<f32>().unwrap();
        for (a, b) in got.iter().zip(&want) {
            assert!(
                (f64::from(*a) - b).abs() < 1e-4,
                "strides {strides:?}: {a} vs {b}"
            );
        }
    }
}

#[test]
fn rangenet_is_deterministic_per_seed() {
    let cfg = tiny_range_cfg();
    let dev = Device::Cpu;
    let x = Tensor::from_vec(rand_vec(5 * 8 * 64, 6), (1, 5, 8, 64), &dev).unwrap();
    let feats = |seed| {
        let vm = VarMap::new();
        let net = RangeNet::new(&cfg, seeded_var_builder(&vm, seed, DType::F32, &dev)).unwrap();
        net.features(&x).unwrap().to_vec2::<f32>().unwrap()
    };
    assert_eq!(feats(3), feats(3));
    assert_ne!(feats(3), feats(4));
}

#[test]
fn pointnet_shapes_invariances_and_brute_force_max() {
    let cfg = tiny_point_cfg();
    let dev = Device::Cpu;
    let vm = VarMap::new();
    let net = PointNet::new(&cfg, seeded_var_builder(&vm, 2, DType::F32, &dev)).unwrap();
    let n = 50;
    let pts: Vec<Vec3> = (0..n)
        .map(|i| {
            let v = rand_vec(3, 100 + i as u64);
            Vec3::new(v[0] * 40.0, v[1] * 40.0, v[2] * 3.0)
        })
        .collect();
    let full = PointNetConfig {
        num_points: None,
        ..cfg.clone()
    };
    let x = Tensor::from_vec(PointNet::prepare(&full, &pts).unwrap(), (1, 3, n), &dev).unwrap();
    let out = net.forward(&x).unwrap();
    assert_eq!(out.global.dims(), &[1, 256]);
    assert_eq!(out.logits.dims(), &[1, 23]);
    let g = out.global.to_vec2::<f32>().unwrap()[0].clone();

    // brute force: the per-point MLP with plain loops over the stored weights, then the max
    let t = varmap_tensors(&vm);
    let layer = |i: usize| {
        let w = t[&format!("feat.conv{i}.weight")]
            .flatten_all()
            .unwrap()
            .to_vec1::<f32>()
            .unwrap();
        let b = t[&format!("feat.conv{i}.bias")].to_vec1::<f32>().unwrap();
        (w, b)
    };
    let mut want = vec![f64::NEG_INFINITY; 256];
    for p in &pts {
        let mut h: Vec<f64> = [p.x, p.y, p.z]
            .iter()
            .map(|v| f64::from(*v) / 80.0)
            .collect();
        for li in 1..=3 {
            let (w, b) = layer(li);
            let out_c = b.len();
            let in_c = h.len();
            let mut y = vec![0.0; out_c];
            for o in 0..out_c {
                let mut acc = f64::from(b[o]);
                for i in 0..in_c {
                    acc += f64::from(w[o * in_c + i]) * h[i];
                }
                y[o] = if li < 3 { acc.max(0.0) } else { acc };
            }
            h = y;
        }
        for (m, v) in want.iter_mut().zip(&h) {
            *m = m.max(*v);
        }
    }
    for (a, b) in g.iter().zip(&want) {
        assert!(
            (f64::from(*a) - b).abs() < 1e-4 * (1.0 + b.abs()),
            "{a} vs {b}"
        );
    }

    // permutation invariance
    let mut rev = pts.clone();
    rev.reverse();
    rev.rotate_left(17);
    let xr = Tensor::from_vec(PointNet::prepare(&full, &rev).unwrap(), (1, 3, n), &dev).unwrap();
    let gr = net.features(&xr).unwrap().to_vec2::<f32>().unwrap()[0].clone();
    for (a, b) in g.iter().zip(&gr) {
        assert!((a - b).abs() < 1e-5);
    }
    // padding a small scan to num_points by repetition leaves the max unchanged
    let xp = Tensor::from_vec(PointNet::prepare(&cfg, &pts).unwrap(), (1, 3, 128), &dev).unwrap();
    let gp = net.features(&xp).unwrap().to_vec2::<f32>().unwrap()[0].clone();
    for (a, b) in g.iter().zip(&gp) {
        assert!((a - b).abs() < 1e-5);
    }
}

#[test]
fn pointnet_prepare_subsamples_deterministically_and_rejects_empty_scans() {
    let cfg = tiny_point_cfg();
    let (pts, _) = synthetic_scan(1, 1000);
    let a = PointNet::prepare(&cfg, &pts).unwrap();
    assert_eq!(a.len(), 3 * 128);
    assert_eq!(a, PointNet::prepare(&cfg, &pts).unwrap());
    // a sample without replacement: 128 distinct points of the scan
    let chosen: std::collections::BTreeSet<(u32, u32, u32)> = (0..128)
        .map(|k| (a[k].to_bits(), a[128 + k].to_bits(), a[256 + k].to_bits()))
        .collect();
    assert_eq!(chosen.len(), 128);
    let bad = [Vec3::NAN, Vec3::new(f32::INFINITY, 0.0, 0.0)];
    assert!(matches!(
        PointNet::prepare(&cfg, &bad),
        Err(Error::Input(_))
    ));
    assert!(PointNet::prepare(&cfg, &[]).is_err());
}

#[test]
fn sparenet_preset_matches_pointnet_pytorch_names() {
    let cfg = PointNetConfig::sparenet();
    let t = PointNet::expected_tensors(&cfg).unwrap();
    for (name, shape) in [
        ("feat.stn.conv1.weight", vec![64, 3, 1]),
        ("feat.stn.conv3.weight", vec![1024, 128, 1]),
        ("feat.stn.fc3.weight", vec![9, 256]),
        ("feat.stn.bn5.running_mean", vec![256]),
        ("feat.conv1.weight", vec![64, 3, 1]),
        ("feat.conv3.weight", vec![1024, 128, 1]),
        ("feat.bn3.running_var", vec![1024]),
        ("fc1.weight", vec![512, 1024]),
        ("bn2.weight", vec![256]),
        ("fc3.weight", vec![16, 256]),
        ("fc3.bias", vec![16]),
    ] {
        assert_eq!(t.get(name), Some(&shape), "{name}");
    }
    assert!(
        !t.contains_key("bn3.weight"),
        "no BatchNorm after the logits"
    );
    assert!(!t.contains_key("feat.stn.bn6.weight"));
    // a forward pass with the T-Net runs and is invariant to point order
    let dev = Device::Cpu;
    let vm = VarMap::new();
    let net = PointNet::new(&cfg, seeded_var_builder(&vm, 0, DType::F32, &dev)).unwrap();
    let (pts, _) = synthetic_scan(3, 64);
    let x = Tensor::from_vec(PointNet::prepare(&cfg, &pts).unwrap(), (1, 3, 64), &dev).unwrap();
    let mut rev = pts.clone();
    rev.reverse();
    let xr = Tensor::from_vec(PointNet::prepare(&cfg, &rev).unwrap(), (1, 3, 64), &dev).unwrap();
    let (a, b) = (net.forward(&x).unwrap(), net.forward(&xr).unwrap());
    assert_eq!(a.global.dims(), &[1, 1024]);
    assert_eq!(a.logits.dims(), &[1, 16]);
    let (ga, gb) = (
        a.global.to_vec2::<f32>().unwrap(),
        b.global.to_vec2::<f32>().unwrap(),
    );
    for (x, y) in ga[0].iter().zip(&gb[0]) {
        assert!((x - y).abs() < 1e-4 * (1.0 + x.abs()));
    }
}

#[test]
fn range_input_from_points_places_points_and_masks_the_rest() {
    let sensor = LidarSensor {
        rows: 8,
        cols: 64,
        ..LidarSensor::hdl64e()
    };
    // straight ahead (azimuth 0) at elevation ~ -11 deg, and a nearer point on the same ray
    let far = Vec3::new(10.0, 0.0, -2.0);
    let near = far * 0.5;
    let input = RangeNetInput::from_points(&[far, near], Some(&[0.25, 0.75]), &sensor).unwrap();
    assert_eq!(input.mask.iter().filter(|m| **m).count(), 1);
    let k = input.mask.iter().position(|m| *m).unwrap();
    let n = 8 * 64;
    assert!(
        (input.channels[k] - near.length()).abs() < 1e-5,
        "nearest point wins"
    );
    assert_eq!(
        [
            input.channels[n + k],
            input.channels[2 * n + k],
            input.channels[3 * n + k]
        ],
        [near.x, near.y, near.z]
    );
    assert_eq!(input.channels[4 * n + k], 0.75);
    let cfg = tiny_range_cfg();
    let norm = input.normalized(&cfg);
    for c in 0..5 {
        for j in 0..n {
            if j == k {
                let want = (input.channels[c * n + j] - cfg.input_mean[c]) / cfg.input_std[c];
                assert!((norm[c * n + j] - want).abs() < 1e-6);
            } else {
                assert_eq!(norm[c * n + j], 0.0);
            }
        }
    }
    // from the range image of the same sensor: x, y, z along the pixel's ray
    let rays = veila_geom::RayTable::new(&sensor).unwrap();
    let mut img = veila_geom::RangeImage::new_empty(8, 64);
    img.range_m[k] = 5.0;
    img.mask[k] = true;
    img.intensity[k] = 0.5;
    let from_img = RangeNetInput::from_range_image(&img, &rays).unwrap();
    let d = rays.dirs()[k] * 5.0;
    assert_eq!(from_img.channels[n + k], d.x);
    assert_eq!(from_img.channels[4 * n + k], 0.5);
    assert!(
        RangeNetInput::from_points(&[far], Some(&[0.1, 0.2]), &sensor).is_err(),
        "intensity length mismatch"
    );
}

#[test]
fn training_updates_batch_norm_statistics_and_lowers_the_loss() {
    let cfg = tiny_range_cfg();
    let dev = Device::Cpu;
    let vm = VarMap::new();
    let net = RangeNet::new(&cfg, seeded_var_builder(&vm, 7, DType::F32, &dev)).unwrap();
    let x = Tensor::from_vec(rand_vec(2 * 5 * 8 * 64, 8), (2, 5, 8, 64), &dev).unwrap();
    // labels: class 1 where the first channel is positive, 2 elsewhere
    let first = x.narrow(1, 0, 1).unwrap().squeeze(1).unwrap();
    let labels = first
        .gt(0.0)
        .unwrap()
        .to_dtype(DType::U32)
        .unwrap()
        .affine(-1.0, 2.0)
        .unwrap()
        .flatten_all()
        .unwrap();
    let mut opt = candle_nn::AdamW::new(
        vm.all_vars(),
        candle_nn::ParamsAdamW {
            lr: 3e-3,
            ..Default::default()
        },
    )
    .unwrap();
    let loss = |train| {
        let logits = net.forward_t(&x, train).unwrap();
        let flat = logits
            .permute((0, 2, 3, 1))
            .unwrap()
            .reshape(((), 20))
            .unwrap();
        candle_nn::loss::cross_entropy(&flat, &labels).unwrap()
    };
    let before = loss(true).to_scalar::<f32>().unwrap();
    for _ in 0..15 {
        let l = loss(true);
        opt.backward_step(&l).unwrap();
    }
    let after = loss(true).to_scalar::<f32>().unwrap();
    assert!(after < 0.8 * before, "loss {before} -> {after}");
    // running statistics moved away from their initial 0 / 1
    let stats = net.batch_norm_stats();
    let mean = stats
        .iter()
        .find(|(n, _)| n == "bn1.running_mean")
        .unwrap()
        .1
        .to_vec1::<f32>()
        .unwrap();
    assert!(mean.iter().any(|v| v.abs() > 1e-3));
    assert_eq!(stats.len(), 2 * (1 + 5 * 3));
}

#[test]
fn bundle_round_trip_and_integrity_errors() {
    let dev = Device::Cpu;
    let (rcfg, pcfg) = (tiny_range_cfg(), tiny_point_cfg());
    let (rvm, pvm) = (VarMap::new(), VarMap::new());
    let rnet = RangeNet::new(&rcfg, seeded_var_builder(&rvm, 11, DType::F32, &dev)).unwrap();
    let pnet = PointNet::new(&pcfg, seeded_var_builder(&pvm, 12, DType::F32, &dev)).unwrap();
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("nets");
    let manifest = feature_nets::save_bundle(
        &out,
        "test",
        "unit test",
        (&rcfg, &varmap_tensors(&rvm)),
        (&pcfg, &varmap_tensors(&pvm)),
    )
    .unwrap();
    assert_eq!(manifest.files.len(), 4);

    let scans: Vec<(Vec<Vec3>, Vec<f32>)> = (0..3).map(|s| synthetic_scan(s, 3000)).collect();
    let loaded = FeatureNets::from_dir(&out, &dev).unwrap();
    assert_eq!(loaded.frd_protocol(), "test rangenet-small, gap features");
    let pairs: Vec<(&[Vec3], Option<&[f32]>)> = scans
        .iter()
        .map(|(p, i)| (p.as_slice(), Some(i.as_slice())))
        .collect();
    let rf = loaded.scan_range_features(&pairs).unwrap();
    assert_eq!(rf.len(), 3);
    let inputs: Vec<RangeNetInput> = pairs
        .iter()
        .map(|(p, i)| RangeNetInput::from_points(p, *i, &rcfg.sensor).unwrap())
        .collect();
    let refs: Vec<&RangeNetInput> = inputs.iter().collect();
    let direct = rnet
        .features(&RangeNetInput::batch(&refs, &rcfg, &dev).unwrap())
        .unwrap()
        .to_vec2::<f32>()
        .unwrap();
    assert_eq!(rf, direct, "saved and loaded range net agree");
    assert_ne!(rf[0], rf[1]);
    let pts: Vec<&[Vec3]> = scans.iter().map(|(p, _)| p.as_slice()).collect();
    let pf = loaded.point_features(&pts).unwrap();
    let x0 =
        Tensor::from_vec(PointNet::prepare(&pcfg, pts[0]).unwrap(), (1, 3, 128), &dev).unwrap();
    assert_eq!(
        pf[0],
        pnet.features(&x0).unwrap().to_vec2::<f32>().unwrap()[0]
    );

    // in-memory bundle gives the same features
    let files: Vec<(String, Vec<u8>)> = ["manifest.json"]
        .iter()
        .chain(feature_nets::BUNDLE_FILES.iter())
        .map(|n| (n.to_string(), std::fs::read(out.join(n)).unwrap()))
        .collect();
    let borrowed: Vec<(&str, &[u8])> = files
        .iter()
        .map(|(n, b)| (n.as_str(), b.as_slice()))
        .collect();
    let mem = FeatureNets::from_bytes(&borrowed, &dev).unwrap();
    assert_eq!(mem.point_features(&pts).unwrap(), pf);

    // one flipped byte in a weights file: an integrity error naming that file
    let wpath = out.join("pointnet.safetensors");
    let mut bytes = std::fs::read(&wpath).unwrap();
    let last = bytes.len() - 1;
    bytes[last] ^= 1;
    std::fs::write(&wpath, &bytes).unwrap();
    match FeatureNets::from_dir(&out, &dev) {
        Err(Error::Integrity { path, message }) => {
            assert_eq!(path, wpath);
            assert!(message.contains("sha256"), "{message}");
        }
        other => panic!("expected an integrity error, got {other:?}"),
    }
    // a missing file names it
    let missing: Vec<(&str, &[u8])> = borrowed
        .iter()
        .copied()
        .filter(|(n, _)| *n != "rangenet.json")
        .collect();
    let err = FeatureNets::from_bytes(&missing, &dev).unwrap_err();
    assert!(err.to_string().contains("rangenet.json"), "{err}");
}

#[test]
fn loading_reports_missing_and_mis_shaped_tensors() {
    let dev = Device::Cpu;
    let cfg = tiny_range_cfg();
    let vm = VarMap::new();
    RangeNet::new(&cfg, seeded_var_builder(&vm, 1, DType::F32, &dev)).unwrap();
    let mut t = varmap_tensors(&vm);
    t.remove("enc2.bn.running_var");
    t.insert(
        "enc1.conv.weight".into(),
        Tensor::zeros((32, 16, 1, 1), DType::F32, &dev).unwrap(),
    );
    t.insert(
        "decoder.dec1.conv.weight".into(),
        Tensor::zeros(3, DType::F32, &dev).unwrap(),
    );
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("w.safetensors");
    candle_core::safetensors::save(&t, &path).unwrap();
    match RangeNet::load(&path, &cfg, &dev) {
        Err(Error::CheckpointMismatch { path: p, report }) => {
            assert_eq!(p, path);
            assert_eq!(report.missing, vec!["enc2.bn.running_var".to_string()]);
            assert_eq!(
                report.unexpected,
                vec!["decoder.dec1.conv.weight".to_string()]
            );
            assert_eq!(report.mis_shaped.len(), 1);
            assert_eq!(report.mis_shaped[0].0, "enc1.conv.weight");
        }
        other => panic!("expected a mismatch, got {other:?}"),
    }
    // a clean file loads and gives the same features as the net it came from
    let vm2 = VarMap::new();
    let net = RangeNet::new(&cfg, seeded_var_builder(&vm2, 2, DType::F32, &dev)).unwrap();
    let good = dir.path().join("good.safetensors");
    candle_core::safetensors::save(&varmap_tensors(&vm2), &good).unwrap();
    let loaded = RangeNet::load(&good, &cfg, &dev).unwrap();
    let x = Tensor::from_vec(rand_vec(5 * 8 * 64, 3), (1, 5, 8, 64), &dev).unwrap();
    assert_eq!(
        loaded.features(&x).unwrap().to_vec2::<f32>().unwrap(),
        net.features(&x).unwrap().to_vec2::<f32>().unwrap()
    );
}
