//! Shared helpers for the veila-nn integration tests: small configs, a KITTI-like camera, seeded data.
#![allow(dead_code, clippy::excessive_precision)]

use candle_core::{DType, Device, Tensor};
use candle_nn::VarMap;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use veila_geom::{
    BeamLayout, DepthSpacing, EpipolarConfig, FourierEncoding, LidarSensor, PinholeCamera,
};
use veila_nn::{
    ConditioningConfig, Cues, DenoiserConfig, Fusion, GcmaConfig, PfcConfig, TimeEmbeddingConfig,
};

/// Image size of the test camera.
pub const IMG_W: u32 = 160;
pub const IMG_H: u32 = 48;

/// A 16 x 128 HDL-64E-like sensor.
pub fn small_sensor() -> LidarSensor {
    LidarSensor {
        rows: 16,
        cols: 128,
        beams: BeamLayout::Uniform,
        ..LidarSensor::hdl64e()
    }
}

/// SemanticKITTI sequence 00 calibration (P2, Tr) scaled to a `IMG_W x IMG_H` image.
pub fn kitti_camera() -> PinholeCamera {
    let (sx, sy) = (IMG_W as f32 / 1241.0, IMG_H as f32 / 376.0);
    let p2 = [
        [718.856 * sx, 0.0, 607.1928 * sx, 45.38225 * sx],
        [0.0, 718.856 * sy, 185.2157 * sy, -0.1130887 * sy],
        [0.0, 0.0, 1.0, 0.003779761],
    ];
    let tr = [
        [
            4.276802385584e-04,
            -9.999672484946e-01,
            -8.084491683471e-03,
            -1.198459927713e-02,
        ],
        [
            -7.210626507497e-03,
            8.081198471645e-03,
            -9.999413164504e-01,
            -5.403984729748e-02,
        ],
        [
            9.999738645903e-01,
            4.859485810390e-04,
            -7.206933692422e-03,
            -2.921968648686e-01,
        ],
    ];
    PinholeCamera::from_kitti_odometry(p2, tr, IMG_W, IMG_H).expect("valid KITTI camera")
}

/// The same camera looking backwards (rotated 180 degrees about z): a second view for multi-camera tests.
pub fn rear_camera() -> PinholeCamera {
    let mut cam = kitti_camera();
    // lidar x -> -x, y -> -y before applying cam_from_lidar
    cam.cam_from_lidar *= glam::Mat4::from_diagonal(glam::Vec4::new(-1.0, -1.0, 1.0, 1.0));
    cam
}

pub fn epipolar(k: usize) -> EpipolarConfig {
    EpipolarConfig {
        num_samples: k,
        near_m: 2.0,
        far_m: 60.0,
        spacing: DepthSpacing::Log,
        tau_m: 30.0,
    }
}

/// A small conditional config on the 16 x 128 sensor with 48 x 160 images.
pub fn small_config() -> DenoiserConfig {
    DenoiserConfig {
        sensor: small_sensor(),
        in_channels: 3,
        out_channels: 3,
        base_channels: 16,
        channel_mults: vec![1, 2, 2, 2],
        num_res_blocks: 1,
        norm_groups: 4,
        residual_scale: std::f32::consts::FRAC_1_SQRT_2,
        time: TimeEmbeddingConfig {
            dim: 32,
            max_period: 10_000.0,
            input_scale: 1000.0,
        },
        ray_features: Some(FourierEncoding {
            num_freqs: 2,
            scale: 1.0,
            include_input: true,
        }),
        pfc: Some(PfcConfig { num_heads: 2 }),
        conditioning: Some(ConditioningConfig {
            cues: Cues::Both,
            fusion: Fusion::Cacm,
            semantic_channels: vec![8, 12, 16, 16],
            depth_channels: vec![6, 10, 12, 16],
            feature_sizes: ConditioningConfig::pyramid_sizes(IMG_H as usize, IMG_W as usize),
            cond_channels: vec![8, 8, 16, 16],
            cacm_delta: 1e-6,
            num_views: 1,
            gcma: Some(GcmaConfig {
                levels: vec![0, 1, 2, 3],
                decoder: true,
                attn_dim: 8,
                num_heads: 2,
                point_encoding: FourierEncoding {
                    num_freqs: 3,
                    scale: 1.0 / 60.0,
                    include_input: true,
                },
            }),
        }),
    }
}

pub fn rng(seed: u64) -> ChaCha8Rng {
    ChaCha8Rng::seed_from_u64(seed)
}

/// Uniform(-1, 1) tensor from a seeded stream.
pub fn rand_tensor(rng: &mut ChaCha8Rng, shape: &[usize]) -> Tensor {
    let n: usize = shape.iter().product();
    let v: Vec<f32> = (0..n).map(|_| rng.random_range(-1.0f32..1.0)).collect();
    Tensor::from_vec(v, shape, &Device::Cpu).expect("tensor")
}

/// Random encoder pyramids for `cfg` (batch `b`, `views` views, depth maps at half the semantic size
/// to exercise the bilinear resize).
pub fn rand_pyramids(
    rng: &mut ChaCha8Rng,
    cfg: &DenoiserConfig,
    b: usize,
) -> (Vec<Tensor>, Vec<Tensor>) {
    let cc = cfg.conditioning.as_ref().expect("conditional");
    let n = b * cc.num_views;
    let mut sem = Vec::new();
    let mut dep = Vec::new();
    for i in 0..cc.num_scales() {
        let [h, w] = cc.feature_sizes[i];
        sem.push(rand_tensor(rng, &[n, cc.semantic_channels[i], h, w]));
        dep.push(rand_tensor(
            rng,
            &[n, cc.depth_channels[i], h.div_ceil(2), w.div_ceil(2)],
        ));
    }
    (sem, dep)
}

pub fn varmap_model(cfg: &DenoiserConfig, seed: u64) -> (VarMap, veila_nn::Denoiser) {
    let vm = VarMap::new();
    let net = veila_nn::Denoiser::new(
        cfg,
        veila_nn::seeded_var_builder(&vm, seed, DType::F32, &Device::Cpu),
    )
    .expect("model builds");
    (vm, net)
}

/// The largest absolute value of `t` (any float dtype), in f64.
pub fn max_abs(t: &Tensor) -> f64 {
    t.to_dtype(DType::F64)
        .unwrap()
        .abs()
        .unwrap()
        .flatten_all()
        .unwrap()
        .max(0)
        .unwrap()
        .to_scalar::<f64>()
        .unwrap()
}

pub fn max_abs_diff(a: &Tensor, b: &Tensor) -> f32 {
    let a = a.flatten_all().unwrap().to_vec1::<f32>().unwrap();
    let b = b.flatten_all().unwrap().to_vec1::<f32>().unwrap();
    assert_eq!(a.len(), b.len());
    a.iter()
        .zip(&b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f32::max)
}

pub fn all_finite(t: &Tensor) -> bool {
    t.flatten_all()
        .unwrap()
        .to_vec1::<f32>()
        .unwrap()
        .iter()
        .all(|v| v.is_finite())
}

/// Gives every zero-initialised variable (the zero convolutions of GCMA and CACM's residuals)
/// small random values in the variable's dtype, so that every branch contributes to the output and
/// its gradient.
pub fn wake_zero_branches(vm: &VarMap, seed: u64) {
    let mut r = rng(seed);
    let data = vm.data().lock().unwrap();
    let mut names: Vec<&String> = data.keys().collect();
    names.sort();
    for name in names {
        let v = &data[name];
        let zero = v
            .as_tensor()
            .abs()
            .unwrap()
            .sum_all()
            .unwrap()
            .to_dtype(DType::F64)
            .unwrap()
            .to_scalar::<f64>()
            .unwrap()
            == 0.0;
        if zero && !name.ends_with(".bias") {
            let t = (rand_tensor(&mut r, v.dims()) * 0.2).unwrap();
            v.set(&t.to_dtype(v.dtype()).unwrap()).unwrap();
        }
    }
}
