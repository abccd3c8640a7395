//! The converted shards of `veila convert` as training examples: each sample projected to the
//! model's grid and encoded, its image resized to the encoders' input with the LiDAR's sparse
//! depth and labels projected into it ([`prepare_sample`]); all of them in memory
//! ([`load_prepared`]), or [`ShardSource`], which reads samples from the shards one at a time for
//! streaming training (`[data] stream = true`). Errors name the shard file and the sample.

use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};

use veila_data::image::imageops;
use veila_data::shard::{Manifest, ShardReader, ShardSample, read_shard};
use veila_geom::{LidarSensor, PinholeCamera, ProjectionOptions, Projector, RayTable};

use super::bundle::BundleConfig;
use super::dataset::{EncoderExample, ExampleSource, TrainExample, TrainView, blind_camera};
use crate::error::{Error, Result};

/// The error of one sample of a shard file.
fn sample_error(path: &Path, id: &str, reason: impl std::fmt::Display) -> Error {
    Error::Input {
        path: path.to_path_buf(),
        reason: format!("sample {id}: {reason}"),
    }
}

/// One shard sample reduced to what training uses.
#[derive(Debug, Clone)]
pub struct Prepared {
    /// RGB at the bundle image size (empty when the model never looks at the camera).
    pub rgb: Vec<u8>,
    /// The camera, fitted to the bundle image size.
    pub camera: PinholeCamera,
    /// The scan on the model's grid, encoded.
    pub x0: Vec<f32>,
    /// The sample's further cameras at the bundle image size (multi-view models).
    pub extra_views: Vec<TrainView>,
    /// Sparse camera depth at the bundle image size (0 = no return).
    pub depth_m: Vec<f32>,
    /// Sparse train ids at the bundle image size (0 = ignored), when the shard has labels.
    pub labels: Option<Vec<u32>>,
}

/// Shard sample `s` (of the file `shard_path`, whose sensor is `shard_sensor`) as training uses it
/// for the bundle `cfg`; `needs_camera`: whether the model or its encoders' training looks at the
/// camera (without it the image is not read).
pub fn prepare_sample(
    s: &ShardSample,
    shard_sensor: &LidarSensor,
    shard_rays: &RayTable,
    cfg: &BundleConfig,
    projector: &Projector,
    shard_path: &Path,
    needs_camera: bool,
) -> Result<Prepared> {
    let err = |reason: String| sample_error(shard_path, &s.id, reason);
    let (iw, ih) = (cfg.image_width as u32, cfg.image_height as u32);
    let un = shard_rays.unproject(&s.scan)?;
    let projected;
    let on_grid = if shard_sensor == &cfg.denoiser.sensor {
        &s.scan
    } else {
        projected = projector.project(&un.points, Some(&un.intensity), None)?.0;
        &projected
    };
    let x0 = cfg.encoding.encode_to_vec(on_grid)?;
    if !needs_camera {
        // an unconditional model without encoders to train never looks at the camera
        return Ok(Prepared {
            rgb: Vec::new(),
            camera: blind_camera(cfg)?,
            x0,
            extra_views: Vec::new(),
            depth_m: Vec::new(),
            labels: None,
        });
    }
    let Some(image) = &s.image else {
        return Err(err(
            "has no camera image (convert the dataset with images: `veila convert` without --no-images)"
                .into(),
        ));
    };
    let Some(matrices) = &s.camera else {
        return Err(err(
            "has no camera matrices (intrinsics / cam_from_lidar); the dataset needs a calibrated camera"
                .into(),
        ));
    };
    let (w, h) = image.dimensions();
    let full = matrices
        .to_camera(w, h)
        .map_err(|e| err(format!("invalid camera: {e}")))?;
    let camera = full
        .resized(iw, ih)
        .ok_or_else(|| err("the model's image size has a zero dimension".into()))?;
    let rgb = imageops::resize(image, iw, ih, imageops::FilterType::Triangle).into_raw();
    // sparse supervision: returns projected into the resized image, nearest wins
    let npx = (iw * ih) as usize;
    let mut depth_m = vec![0f32; npx];
    let mut labels = s.train_ids.as_ref().map(|_| vec![0u32; npx]);
    for (p, (r, c)) in un.points.iter().zip(&un.pixels) {
        let Some(ip) = camera.try_project_in_image(*p) else {
            continue;
        };
        let (u, v) = ((ip.u_px + 0.5).floor(), (ip.v_px + 0.5).floor());
        if u < 0.0 || v < 0.0 || u >= iw as f32 || v >= ih as f32 {
            continue;
        }
        let k = v as usize * iw as usize + u as usize;
        if depth_m[k] == 0.0 || ip.depth_m < depth_m[k] {
            depth_m[k] = ip.depth_m;
            if let (Some(l), Some(src_l)) = (labels.as_mut(), s.train_ids.as_ref()) {
                l[k] = u32::from(src_l[(*r * shard_sensor.cols + *c) as usize]);
            }
        }
    }
    let views = cfg.num_views();
    if 1 + s.extra_views.len() < views {
        return Err(err(format!(
            "has {} camera(s), the model takes {views} views (convert with more cameras: \
             `veila convert --camera CAM_FRONT,CAM_FRONT_LEFT,CAM_FRONT_RIGHT`)",
            1 + s.extra_views.len()
        )));
    }
    // the rig's further cameras the model takes, fitted to the encoders' input like the first
    let extra_views = s
        .extra_views
        .iter()
        .take(views - 1)
        .enumerate()
        .map(|(j, v)| -> Result<TrainView> {
            let (w, h) = v.image.dimensions();
            let camera = v
                .camera
                .to_camera(w, h)
                .map_err(|e| err(format!("invalid camera of view {}: {e}", j + 1)))?
                .resized(iw, ih)
                .ok_or_else(|| err("the model's image size has a zero dimension".into()))?;
            let rgb = imageops::resize(&v.image, iw, ih, imageops::FilterType::Triangle).into_raw();
            Ok(TrainView { rgb, camera })
        })
        .collect::<Result<Vec<_>>>()?;
    Ok(Prepared {
        rgb,
        camera,
        x0,
        extra_views,
        depth_m,
        labels,
    })
}

/// How many shard files a [`ShardSource`] keeps open (their headers: offsets and ids).
const OPEN_SHARDS: usize = 8;

/// The first `count` samples of a converted dataset, read from its shards one sample at a time
/// ([`ShardReader`]) and prepared when training asks for them: memory does not grow with the
/// dataset. Errors name the shard file and the sample.
pub struct ShardSource {
    dir: PathBuf,
    /// The shard files, each checked to lie inside `dir` ([`Manifest::shard_path`]).
    files: Vec<PathBuf>,
    /// Sample `i` is sample `.1` of shard file `.0`.
    index: Vec<(u32, u32)>,
    sensor: LidarSensor,
    rays: RayTable,
    projector: Projector,
    cfg: BundleConfig,
    needs_camera: bool,
    /// With `unify_cameras`: the camera every sample is given (the first sample's).
    camera: Option<PinholeCamera>,
    open: Mutex<Vec<(u32, Arc<ShardReader>)>>,
}

impl std::fmt::Debug for ShardSource {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ShardSource")
            .field("dir", &self.dir)
            .field("samples", &self.index.len())
            .finish_non_exhaustive()
    }
}

impl ShardSource {
    /// The first `count` samples listed in `manifest` (in folder `dir`); a conditional model's
    /// samples keep their own cameras unless `unify_cameras` gives them the first one's.
    pub fn new(
        dir: &Path,
        manifest: &Manifest,
        count: usize,
        cfg: &BundleConfig,
        needs_camera: bool,
        conditional: bool,
        unify_cameras: bool,
    ) -> Result<Self> {
        let mut index = Vec::with_capacity(count);
        'outer: for (f, entry) in manifest.shards.iter().enumerate() {
            for k in 0..entry.count {
                if index.len() == count {
                    break 'outer;
                }
                index.push((f as u32, k as u32));
            }
        }
        if index.is_empty() {
            return Err(Error::Input {
                path: dir.to_path_buf(),
                reason: "the manifest lists no samples".into(),
            });
        }
        let mut source = ShardSource {
            dir: dir.to_path_buf(),
            files: (0..manifest.shards.len())
                .map(|i| manifest.shard_path(dir, i))
                .collect::<std::result::Result<_, _>>()?,
            index,
            sensor: manifest.sensor.clone(),
            rays: RayTable::new(&manifest.sensor)?,
            projector: Projector::new(&cfg.denoiser.sensor, ProjectionOptions::default())?,
            cfg: cfg.clone(),
            needs_camera,
            camera: None,
            open: Mutex::new(Vec::new()),
        };
        if conditional && unify_cameras {
            source.camera = Some(source.prepared(0)?.camera);
        }
        Ok(source)
    }

    /// The first sample's shard sample as stored (what checks of the data look at).
    pub fn first_sample(&self) -> Result<ShardSample> {
        let (f, k) = self.index[0];
        Ok(self.reader(f)?.sample(k as usize)?)
    }

    fn reader(&self, f: u32) -> Result<Arc<ShardReader>> {
        let mut open = self
            .open
            .lock()
            .map_err(|_| Error::Data("the shard reader cache lock is poisoned".into()))?;
        if let Some((_, r)) = open.iter().find(|(g, _)| *g == f) {
            return Ok(r.clone());
        }
        let path = self.files[f as usize].clone();
        let r = Arc::new(ShardReader::open(&path)?);
        if r.sensor() != &self.sensor {
            return Err(Error::Input {
                path,
                reason: "the shard's sensor differs from the manifest's".into(),
            });
        }
        if open.len() == OPEN_SHARDS {
            open.remove(0);
        }
        open.push((f, r.clone()));
        Ok(r)
    }

    fn prepared(&self, i: usize) -> Result<Prepared> {
        let &(f, k) = self
            .index
            .get(i)
            .ok_or_else(|| Error::Data(format!("sample {i} of {}", self.index.len())))?;
        let reader = self.reader(f)?;
        let s = reader.sample(k as usize)?;
        let path = self.files[f as usize].clone();
        let mut p = prepare_sample(
            &s,
            &self.sensor,
            &self.rays,
            &self.cfg,
            &self.projector,
            &path,
            self.needs_camera,
        )?;
        if let Some(c) = self.camera {
            p.camera = c;
        }
        Ok(p)
    }
}

impl ExampleSource for ShardSource {
    fn len(&self) -> usize {
        self.index.len()
    }

    fn example(&self, index: usize) -> Result<TrainExample> {
        let p = self.prepared(index)?;
        Ok(TrainExample {
            rgb: p.rgb,
            camera: p.camera,
            x0: p.x0,
            extra_views: p.extra_views,
        })
    }

    fn encoder_example(&self, index: usize) -> Result<EncoderExample> {
        let p = self.prepared(index)?;
        Ok(EncoderExample {
            rgb: p.rgb,
            camera: Some(p.camera),
            labels: p.labels,
            depth_m: p.depth_m,
        })
    }
}

/// Hands every sample of the shards in `dir` (listed in `manifest`), in order, to `each` with its
/// shard file, one shard in memory at a time, until `each` answers `false`. A shard whose sensor
/// is not the manifest's is an error naming it.
pub fn each_sample(
    dir: &Path,
    manifest: &Manifest,
    mut each: impl FnMut(&Path, &ShardSample) -> Result<bool>,
) -> Result<()> {
    for i in 0..manifest.shards.len() {
        let path = manifest.shard_path(dir, i)?;
        let shard = read_shard(&path)?;
        if shard.sensor != manifest.sensor {
            return Err(Error::Input {
                path,
                reason: "the shard's sensor differs from the manifest's".into(),
            });
        }
        for s in &shard.samples {
            if !each(&path, s)? {
                return Ok(());
            }
        }
    }
    Ok(())
}

/// The first `want` samples of the shards in `dir` (listed in `manifest`), prepared for the bundle
/// `cfg` and held in memory; `on_sample` is called after each. With `unify_cameras` a conditional
/// model's samples all get the first one's camera.
pub fn load_prepared(
    dir: &Path,
    manifest: &Manifest,
    want: usize,
    cfg: &BundleConfig,
    needs_camera: bool,
    unify_cameras: bool,
    mut on_sample: impl FnMut(),
) -> Result<Vec<Prepared>> {
    let projector = Projector::new(&cfg.denoiser.sensor, ProjectionOptions::default())?;
    let shard_rays = RayTable::new(&manifest.sensor)?;
    let mut prepared = Vec::with_capacity(want);
    each_sample(dir, manifest, |path, s| {
        if prepared.len() == want {
            return Ok(false);
        }
        prepared.push(prepare_sample(
            s,
            &manifest.sensor,
            &shard_rays,
            cfg,
            &projector,
            path,
            needs_camera,
        )?);
        on_sample();
        Ok(true)
    })?;
    if cfg.denoiser.conditioning.is_some()
        && unify_cameras
        && let Some(first) = prepared.first().map(|p| p.camera)
    {
        for p in &mut prepared {
            p.camera = first;
        }
    }
    Ok(prepared)
}
