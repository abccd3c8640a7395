//! Valid seed files, made by the library's own writers where it has one, else small literals.

use std::collections::HashMap;
use std::io::Write;
use std::path::Path;

use candle_core::{DType, Device, Tensor};
use candle_nn::VarMap;
use glam::Vec3;
use veila_data::PointCloud;
use veila_data::image::{Rgb, RgbImage};
use veila_data::shard::{CameraMatrices, ShardSample, ShardView};
use veila_diffusion::app::bundle::{
    Bundle, BundleConfig, DENOISER_FILE, DEPTH_FILE, MEAN_FILE, Method, SEMANTIC_FILE, Variant,
};
use veila_diffusion::app::varmap_tensors;
use veila_geom::{LidarSensor, PinholeCamera, ProjectionOptions, Projector, RangeImage};
use veila_nn::ConditioningConfig;
use veila_nn::encoders::small_cnn::{SmallCnn, SmallCnnConfig};

/// Encoder input size of the seed bundle.
const IH: usize = 64;
const IW: usize = 96;

/// A small full bundle config (both small-CNN encoders, the residual method's mean network).
pub fn bundle_config() -> BundleConfig {
    let mut cfg = BundleConfig::cpu_default(Variant::Full).with_method(Method::Residual);
    cfg.image_height = IH;
    cfg.image_width = IW;
    let shrink = |d: &mut veila_nn::DenoiserConfig| {
        d.sensor.rows = 8;
        d.sensor.cols = 64;
        d.base_channels = 8;
        d.norm_groups = 4;
        if let Some(c) = d.conditioning.as_mut() {
            c.feature_sizes = ConditioningConfig::pyramid_sizes(IH, IW);
            c.semantic_channels = vec![8, 8, 16, 16];
            c.depth_channels = vec![8, 8, 16, 16];
            c.cond_channels = vec![8, 8, 16, 16];
        }
    };
    shrink(&mut cfg.denoiser);
    if let Some(r) = cfg.residual.as_mut() {
        shrink(&mut r.mean_net);
    }
    for e in [&mut cfg.semantic_encoder, &mut cfg.depth_encoder]
        .into_iter()
        .flatten()
    {
        let c = e.config.as_mut().expect("a small CNN");
        c.channels = [8, 8, 16, 16];
        c.head_channels = 8;
    }
    cfg
}

fn random_tensors(
    build: impl FnOnce(candle_nn::VarBuilder<'_>),
    seed: u64,
) -> HashMap<String, Tensor> {
    let vm = VarMap::new();
    build(veila_nn::seeded_var_builder(
        &vm,
        seed,
        DType::F32,
        &Device::Cpu,
    ));
    varmap_tensors(&vm).expect("the weights")
}

/// Saves a tiny segmenter (`SegmenterConfig::tiny`, SemanticKITTI's first five classes) with
/// random weights in `dir` (by `SegmenterModel::save`).
pub fn save_segmenter(dir: &Path) {
    use veila_diffusion::app::segment::{LabelSpace, SegmenterModel, SegmenterModelConfig};
    let network = veila_nn::segmenter::SegmenterConfig::tiny();
    let mut classes = LabelSpace::semantic_kitti().classes();
    classes.truncate(network.num_classes);
    let cfg = SegmenterModelConfig::new(network, &LidarSensor::hdl64e(), classes);
    let weights = random_tensors(
        |vb| {
            veila_nn::segmenter::Segmenter::new(&cfg.network, vb).expect("the segmenter");
        },
        6,
    );
    SegmenterModel::save(dir, &cfg, &weights).expect("a segmenter folder");
}

/// Saves a bundle of [`bundle_config`] with random weights in `dir` (by [`Bundle::save`]).
pub fn save_bundle(dir: &Path) -> BundleConfig {
    let cfg = bundle_config();
    let mut weights: HashMap<&str, HashMap<String, Tensor>> = HashMap::new();
    for (file, spec) in [
        (SEMANTIC_FILE, &cfg.semantic_encoder),
        (DEPTH_FILE, &cfg.depth_encoder),
    ] {
        if let Some(c) = spec.as_ref().and_then(|e| e.small_cnn_config()) {
            weights.insert(
                file,
                random_tensors(
                    |vb| {
                        SmallCnn::new(c, vb).expect("a small CNN");
                    },
                    3,
                ),
            );
        }
    }
    weights.insert(
        DENOISER_FILE,
        random_tensors(
            |vb| {
                veila_nn::Denoiser::new(&cfg.denoiser, vb).expect("the denoiser");
            },
            4,
        ),
    );
    if let Some(r) = &cfg.residual {
        weights.insert(
            MEAN_FILE,
            random_tensors(
                |vb| {
                    veila_nn::Denoiser::new(&r.mean_net, vb).expect("the mean network");
                },
                5,
            ),
        );
    }
    Bundle::save(dir, &cfg, &weights).expect("saving the seed bundle");
    cfg
}

/// A small CNN's config and its weights as a safetensors file (as the recipe writes them).
pub fn small_cnn_file() -> (SmallCnnConfig, Vec<u8>) {
    let c = SmallCnnConfig {
        channels: [8, 8, 16, 16],
        head_channels: 8,
        ..SmallCnnConfig::default()
    };
    let t = random_tensors(
        |vb| {
            SmallCnn::new(&c, vb).expect("a small CNN");
        },
        6,
    );
    let bytes = veila_nn::checkpoint::safetensors_bytes(&t, Path::new("cnn.safetensors"))
        .expect("serialising");
    (c, bytes)
}

/// A denoiser checkpoint folder (`config.json`, `model.safetensors`) of the tiny unconditional
/// denoiser, written by [`veila_nn::checkpoint::save_checkpoint`].
pub fn save_checkpoint(dir: &Path) {
    let mut cfg = veila_nn::DenoiserConfig::tiny().unconditional();
    cfg.sensor.rows = 8;
    cfg.sensor.cols = 64;
    cfg.base_channels = 8;
    cfg.norm_groups = 4;
    let t = random_tensors(
        |vb| {
            veila_nn::Denoiser::new(&cfg, vb).expect("the denoiser");
        },
        7,
    );
    veila_nn::checkpoint::save_checkpoint(dir, &cfg, &t).expect("saving the checkpoint");
}

/// A scan of 200 points with rings and labels.
pub fn cloud() -> PointCloud {
    let n = 200;
    PointCloud {
        xyz: (0..n)
            .map(|i| {
                let a = i as f32 * 0.37;
                Vec3::new(8.0 * a.cos(), 8.0 * a.sin(), -1.0 + 0.01 * i as f32)
            })
            .collect(),
        intensity: (0..n).map(|i| (i % 10) as f32 / 10.0).collect(),
        ring: Some((0..n).map(|i| (i % 32) as u16).collect()),
        label: Some((0..n).map(|i| (i % 5) as u32).collect()),
    }
}

/// The nuScenes `.pcd.bin` bytes of `c` (x, y, z, intensity, ring as `f32`).
pub fn pcd_bin(c: &PointCloud) -> Vec<u8> {
    let mut bytes = Vec::new();
    for k in 0..c.len() {
        let p = c.xyz[k];
        let ring = c.ring.as_ref().map_or(0.0, |r| f32::from(r[k]));
        for v in [p.x, p.y, p.z, 100.0 * c.intensity[k], ring] {
            bytes.extend_from_slice(&v.to_le_bytes());
        }
    }
    bytes
}

/// An 8 x 32 sensor.
pub fn small_sensor() -> LidarSensor {
    LidarSensor {
        rows: 8,
        cols: 32,
        ..LidarSensor::hdl64e()
    }
}

/// A small test image.
pub fn image(w: u32, h: u32) -> RgbImage {
    RgbImage::from_fn(w, h, |x, y| {
        Rgb([(x * 10 % 256) as u8, (y * 20 % 256) as u8, 7])
    })
}

/// JPEG bytes of `img`.
pub fn jpeg(img: &RgbImage) -> Vec<u8> {
    let mut buf = std::io::Cursor::new(Vec::new());
    img.write_to(&mut buf, veila_data::image::ImageFormat::Jpeg)
        .expect("encoding a JPEG");
    buf.into_inner()
}

/// The range EXR of [`cloud`] on [`small_sensor`] (by `encode_range_exr`).
pub fn range_exr() -> Vec<u8> {
    let s = small_sensor();
    let c = cloud();
    let (img, _) = Projector::new(&s, ProjectionOptions::default())
        .expect("a projector")
        .project(&c.xyz, Some(&c.intensity), None)
        .expect("the projection");
    veila_data::range_exr::encode_range_exr(&s, &img).expect("encoding the EXR")
}

/// A shard sample of `sensor` with an image, its camera and a second view.
pub fn shard_sample(sensor: &LidarSensor, id: &str) -> ShardSample {
    let n = (sensor.rows * sensor.cols) as usize;
    let cam = PinholeCamera::new(
        [
            [100.0, 0.0, 12.0, 0.0],
            [0.0, 100.0, 6.0, 0.0],
            [0.0, 0.0, 1.0, 0.0],
        ],
        glam::Mat4::IDENTITY,
        24,
        12,
    )
    .expect("a camera");
    ShardSample {
        id: id.into(),
        scan: RangeImage {
            range_m: (0..n).map(|i| 1.0 + i as f32 * 0.1).collect(),
            intensity: vec![0.5; n],
            mask: (0..n).map(|i| i % 3 != 0).collect(),
            label: Some(vec![10; n]),
            ..RangeImage::new_empty(sensor.rows, sensor.cols)
        },
        train_ids: Some(vec![1; n]),
        image: Some(image(24, 12)),
        camera: Some(CameraMatrices::from_camera(&cam)),
        extra_views: vec![ShardView {
            image: image(24, 12),
            camera: CameraMatrices::from_camera(&cam),
        }],
    }
}

/// A 2-D `.npy` of `rows x cols` values, `f32` or `f64`, C order.
pub fn npy(rows: usize, cols: usize, f64s: bool) -> Vec<u8> {
    let descr = if f64s { "<f8" } else { "<f4" };
    let mut h =
        format!("{{'descr': '{descr}', 'fortran_order': False, 'shape': ({rows}, {cols}), }}");
    while (10 + h.len() + 1) % 64 != 0 {
        h.push(' ');
    }
    h.push('\n');
    let mut out = b"\x93NUMPY\x01\x00".to_vec();
    out.extend_from_slice(&(h.len() as u16).to_le_bytes());
    out.extend_from_slice(h.as_bytes());
    for i in 0..rows * cols {
        let v = (i as f64 * 0.25).sin();
        if f64s {
            out.extend_from_slice(&v.to_le_bytes());
        } else {
            out.extend_from_slice(&(v as f32).to_le_bytes());
        }
    }
    out
}

/// Writes `bytes` to `path`, its folder created.
pub fn write(path: &Path, bytes: &[u8]) {
    if let Some(p) = path.parent() {
        std::fs::create_dir_all(p).expect("a folder");
    }
    let mut f = std::fs::File::create(path).expect("creating a seed file");
    f.write_all(bytes).expect("writing a seed file");
}

/// KITTI object calibration (`calib/*.txt`) for a 100 x 40 image.
pub const KITTI_CALIB: &str = "P0: 100 0 50 0 0 100 20 0 0 0 1 0\nP1: 100 0 50 0 0 100 20 0 0 0 1 0\nP2: 100 0 50 0 0 100 20 0 0 0 1 0\nP3: 100 0 50 0 0 100 20 0 0 0 1 0\nR0_rect: 1 0 0 0 1 0 0 0 1\nTr_velo_to_cam: 0 -1 0 0 0 0 -1 0 1 0 0 0\nTr_imu_to_velo: 1 0 0 0 0 1 0 0 0 0 1 0\n";

/// KITTI odometry calibration (`calib.txt`) for a 100 x 40 image.
pub const ODOMETRY_CALIB: &str = "P0: 100 0 50 0 0 100 20 0 0 0 1 0\nP1: 100 0 50 0 0 100 20 0 0 0 1 0\nP2: 100 0 50 0 0 100 20 0 0 0 1 0\nP3: 100 0 50 0 0 100 20 0 0 0 1 0\nTr: 0 -1 0 0 0 0 -1 0 1 0 0 0\n";

/// A nuScenes sample JSON for a 64 x 36 `CAM_FRONT` image (its files relative to the data root).
pub const NUSCENES_JSON: &str = r#"{"sample_token": "t0",
 "lidar": {"file": "samples/LIDAR_TOP/x.pcd.bin", "timestamp_s": 1.0,
   "lidar2ego": {"matrix_4x4_row_major": [[1,0,0,0],[0,1,0,0],[0,0,1,1.8],[0,0,0,1]]}},
 "ego2global_at_lidar_time": {"matrix_4x4_row_major": [[1,0,0,5],[0,1,0,0],[0,0,1,0],[0,0,0,1]]},
 "cameras": {"CAM_FRONT": {"file": "samples/CAM_FRONT/x.jpg", "timestamp_s": 1.0,
   "intrinsic_3x3": [[50,0,32],[0,50,18],[0,0,1]],
   "cam2ego": {"matrix_4x4_row_major": [[0,0,1,1.7],[-1,0,0,0],[0,-1,0,1.5],[0,0,0,1]]},
   "lidar2cam": {"matrix_4x4_row_major": [[0,-1,0,0],[0,0,-1,0.3],[1,0,0,-0.7],[0,0,0,1]]}}},
 "instances_lidar_frame": [{"label": "car", "bbox_3d": [10,2,-1,4,1.8,1.5,0.3], "num_lidar_pts": 40}]}"#;

/// A SemanticKITTI label map (`semantic-kitti.yaml`), three classes.
pub const LABEL_YAML: &str = "labels:\n  0: unlabeled\n  10: car\n  40: road\ncolor_map:\n  0: [0, 0, 0]\n  10: [245, 150, 100]\n  40: [255, 0, 255]\nlearning_map:\n  0: 0\n  10: 1\n  40: 2\nlearning_map_inv:\n  0: 0\n  1: 10\n  2: 40\nlearning_ignore:\n  0: true\n  1: false\n  2: false\n";

/// A small scene file.
pub const SCENE_TOML: &str = "name = \"tiny\"\nlayout = \"straight\"\n[lidar.sensor]\nrows = 8\ncols = 64\nfov_up_deg = 3.0\nfov_down_deg = -25.0\nmin_range_m = 0.5\nmax_range_m = 120.0\n[camera]\nwidth = 40\nheight = 12\nfx = 30.0\nfy = 30.0\ncx = 20.0\ncy = 6.0\n[frames]\ncount = 1\n";

/// A training config of the CPU default model.
pub const TRAIN_TOML: &str = "[data]\nshards = \"shards\"\nmax_frames = 20\nprefetch = 4\n\n[model]\nvariant = \"full\"\nimage_height = 64\nimage_width = 96\nviews = 1\nground_prior = true\n\n[train]\nsteps = 100\nbatch = 4\nlr = 1e-3\nseed = 0\nencoder_steps = 10\ncheckpoint_every = 50\ngrad_accum_steps = 2\n\n[output]\ndir = \"runs/x\"\n";

/// A training config that starts from a bundle config beside it.
pub const TRAIN_TOML_BUNDLE: &str = "[data]\nshards = \"shards\"\n\n[model]\nbundle = \"b/bundle.json\"\nmethod = \"v\"\ndepth_features = true\n\n[train]\nsteps = 10\nbatch = 2\n\n[output]\ndir = \"runs/y\"\n";
