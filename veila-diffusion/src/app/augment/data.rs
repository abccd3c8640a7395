//! The benchmark's data on the bundle's grid: simulated frames turned into the segmenter's
//! training frames and held-out scans, the scans of each [`ScanSource`] for the split's frames
//! (kept in the work folder, so a resumed run does not sample them again), and the fixed lists of
//! labelled frames.

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use candle_core::{Device, Tensor};
use glam::Vec3;
use rand::SeedableRng;
use rand::seq::SliceRandom;
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};
use veila_data::read_capped::{MAX_CONFIG_BYTES, read_metadata};
use veila_geom::{Projector, RangeImage, RayTable};
use veila_nn::segmenter::SegmenterConfig;

use crate::app::bundle::Bundle;
use crate::app::generate::GenerateOptions;
use crate::app::progress::Progress;
use crate::app::segment::{GridScan, HeldOutScan, LabelSpace, SegFrame, SegmenterModel};
use crate::app::sim_examples::{SimExample, retrieval_baseline};
use crate::error::{Error, Result};
use crate::sampler::SamplerConfig;

/// How often a worker that waits for another (a scan set it makes, a run it holds) looks again.
pub(super) const POLL: std::time::Duration = std::time::Duration::from_secs(5);

/// Seed of the permutation whose prefixes are the labelled lists (one for every row and seed).
pub const LABELLED_LIST_SEED: u64 = 0x5e9_1ab;

/// Where the extra training scans of a row come from: one scan for each unlabelled frame of the
/// split, on the bundle's grid.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum ScanSource {
    /// The bundle's sample from the frame's camera image (its default sampler, one seed a frame).
    Generated,
    /// The frame's true scan: what a perfect generator would give.
    True,
    /// The bundle's mean network alone (a residual bundle's conditional mean).
    MeanNetwork,
    /// The true scan of the training frame whose image is nearest in the bundle's features.
    Retrieved,
}

impl ScanSource {
    /// Every source, in the report's order.
    pub const ALL: [ScanSource; 4] = [
        ScanSource::Generated,
        ScanSource::True,
        ScanSource::MeanNetwork,
        ScanSource::Retrieved,
    ];

    /// Short name (file and run names).
    pub fn name(self) -> &'static str {
        match self {
            ScanSource::Generated => "generated",
            ScanSource::True => "true",
            ScanSource::MeanNetwork => "mean-network",
            ScanSource::Retrieved => "retrieved",
        }
    }

    /// What the report calls its scans.
    pub fn title(self) -> &'static str {
        match self {
            ScanSource::Generated => "generated scans (the bundle, from the image)",
            ScanSource::True => "true scans of those frames (a perfect generator)",
            ScanSource::MeanNetwork => "the mean network's scans",
            ScanSource::Retrieved => "retrieved scans (nearest training image's scan)",
        }
    }
}

/// The labelled frames of `fraction` of a split of `n` frames: the first `max(1, round(fraction
/// n))` of one seeded permutation, so a smaller fraction's frames are among a larger one's.
pub fn labelled_frames(n: usize, fraction: f64) -> Vec<usize> {
    let mut perm: Vec<usize> = (0..n).collect();
    perm.shuffle(&mut ChaCha8Rng::seed_from_u64(LABELLED_LIST_SEED));
    let k = ((fraction * n as f64).round() as usize).clamp(1, n);
    let mut out = perm[..k].to_vec();
    out.sort_unstable();
    out
}

/// A scan on the grid as points: one per pixel with a return, at its ray's centre.
#[derive(Debug, Clone)]
pub struct GridPoints {
    /// Points in the LiDAR frame, metres.
    pub xyz: Vec<Vec3>,
    /// Their intensity.
    pub intensity: Vec<f32>,
    /// Their SemanticKITTI raw label (0 where the scan carries none).
    pub raw_labels: Vec<u32>,
}

/// Turns range images into points and points into the segmenter's frames.
#[derive(Debug)]
pub struct Grid {
    rays: RayTable,
    projector: Projector,
    net: SegmenterConfig,
    labels: LabelSpace,
}

impl Grid {
    /// The grid of `sensor` (the bundle's, which must be the segmenter's) for network `net`.
    pub fn new(sensor: &veila_geom::LidarSensor, net: SegmenterConfig) -> Result<Self> {
        if (sensor.rows as usize, sensor.cols as usize) != (net.rows, net.cols) {
            return Err(Error::Data(format!(
                "the bundle's grid is {} x {}, the segmenter's {} x {}",
                sensor.rows, sensor.cols, net.rows, net.cols
            )));
        }
        Ok(Grid {
            rays: RayTable::new(sensor)?,
            projector: Projector::new(sensor, veila_geom::ProjectionOptions::default())?,
            net,
            labels: LabelSpace::semantic_kitti(),
        })
    }

    /// The points of `image` (its labels too, where it has them).
    pub fn points(&self, image: &RangeImage) -> Result<GridPoints> {
        let u = self.rays.unproject(image)?;
        let cols = image.cols as usize;
        let raw_labels = match &image.label {
            Some(l) => u
                .pixels
                .iter()
                .map(|&(r, c)| l[r as usize * cols + c as usize])
                .collect(),
            None => vec![0; u.points.len()],
        };
        Ok(GridPoints {
            xyz: u.points,
            intensity: u.intensity,
            raw_labels,
        })
    }

    /// The train id of each of `p`'s points, from its raw label.
    pub fn train_ids(&self, p: &GridPoints) -> Vec<u32> {
        p.raw_labels
            .iter()
            .map(|&r| self.labels.train_id(r))
            .collect()
    }

    /// A training frame of `p` labelled with `train_ids`.
    pub fn frame(&self, p: &GridPoints, train_ids: &[u32]) -> Result<SegFrame> {
        SegFrame::from_points(&p.xyz, &p.intensity, train_ids, &self.projector, &self.net)
    }

    /// A held-out scan of `p` with its true train ids.
    pub fn held_out(&self, p: &GridPoints) -> Result<HeldOutScan> {
        Ok(HeldOutScan {
            scan: GridScan::new(&p.xyz, &p.intensity, &self.projector, &self.net)?,
            truth: self.train_ids(p),
        })
    }

    /// A training frame of `p` labelled by `teacher` (its predicted train ids).
    pub fn pseudo_labelled(&self, teacher: &SegmenterModel, p: &GridPoints) -> Result<SegFrame> {
        let grid = teacher.grid_scan(&p.xyz, &p.intensity)?;
        let ids = teacher
            .predict(std::slice::from_ref(&grid))?
            .pop()
            .unwrap_or_default();
        self.frame(p, &ids)
    }
}

/// What identifies the scans of a source (checked before a cached set is used).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
struct ScanSetKey {
    source: ScanSource,
    bundle_manifest_sha256: String,
    sampler: SamplerConfig,
    split: String,
    first_frame: usize,
    frames: usize,
    pool_frames: usize,
    /// Seconds a scan took to make when the set was made (not part of the key).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    seconds_per_scan: Option<f64>,
}

/// The scans of `source` for every frame of `split` (frames `first..first + split.len()` of the
/// bundle's list), with the seconds a scan took to make (as recorded when the set was made; 0 for
/// the true scans): from the cache in `work/scans/` when it holds this very set, else made and
/// cached. `pool` is rendered only when the retrieved scans must be made.
#[allow(clippy::too_many_arguments)]
pub fn scan_set(
    source: ScanSource,
    bundle: &Bundle,
    sampler: &SamplerConfig,
    split: &[SimExample],
    split_name: &str,
    first: usize,
    pool: &mut dyn FnMut() -> Result<Vec<SimExample>>,
    pool_frames: usize,
    work: &Path,
    progress: &dyn Progress,
) -> Result<(Vec<RangeImage>, Option<f64>)> {
    if source == ScanSource::True {
        return Ok((split.iter().map(|e| e.range.clone()).collect(), Some(0.0)));
    }
    let key = ScanSetKey {
        source,
        bundle_manifest_sha256: bundle.manifest_sha256.clone(),
        sampler: sampler.clone(),
        split: split_name.to_string(),
        first_frame: first,
        frames: split.len(),
        pool_frames,
        seconds_per_scan: None,
    };
    let dir = work.join("scans");
    let (key_path, data_path) = (
        dir.join(format!("{}.json", source.name())),
        dir.join(format!("{}.safetensors", source.name())),
    );
    let cached = || -> Result<Option<(Vec<RangeImage>, Option<f64>)>> {
        let found = read_cached(&key, &key_path, &data_path, bundle)?;
        if let Some((scans, _)) = &found {
            progress.line(&format!(
                "  {}: {} scans from {}",
                source.name(),
                scans.len(),
                data_path.display()
            ));
        }
        Ok(found)
    };
    if let Some(found) = cached()? {
        return Ok(found);
    }
    // one worker of those sharing the work folder makes the set; the others wait for it
    std::fs::create_dir_all(&dir).map_err(|source| Error::Io {
        action: "creating the scans folder",
        path: dir.clone(),
        source,
    })?;
    let mut said = false;
    let _lock = loop {
        if let Some(l) = veila_data::atomic::OutputLock::try_acquire(&dir.join(source.name()))? {
            break l;
        }
        if !said {
            progress.line(&format!(
                "  {}: another worker makes these scans; waiting",
                source.name()
            ));
            said = true;
        }
        std::thread::sleep(POLL);
    };
    if let Some(found) = cached()? {
        return Ok(found);
    }
    let t = std::time::Instant::now();
    let scans = match source {
        ScanSource::Retrieved => retrieval_baseline(bundle, &pool()?, split)?,
        _ => {
            let options = |i: usize| GenerateOptions {
                sampler: sampler.clone(),
                samples: 1,
                seed: (first + i) as u64,
                unconditional: false,
                residual_weight: if source == ScanSource::MeanNetwork {
                    0.0
                } else {
                    1.0
                },
            };
            let bar = progress.bar(
                &format!("sampling {} scans", source.name()),
                split.len() as u64,
            );
            let mut out = Vec::with_capacity(split.len());
            for (i, ex) in split.iter().enumerate() {
                let views = ex.views(bundle.config.num_views());
                out.extend(bundle.generate(&views, &options(i), |_, _| {})?);
                bar.inc();
            }
            out
        }
    };
    progress.line(&format!(
        "  {}: {} scans in {:.0} s ({:.2} s a scan)",
        source.name(),
        scans.len(),
        t.elapsed().as_secs_f64(),
        t.elapsed().as_secs_f64() / scans.len().max(1) as f64
    ));
    let seconds = t.elapsed().as_secs_f64() / scans.len().max(1) as f64;
    let key = ScanSetKey {
        seconds_per_scan: Some(seconds),
        ..key
    };
    write_cached(&key, &key_path, &data_path, &scans)?;
    Ok((scans, Some(seconds)))
}

/// The seconds a scan of `source` took to make, as recorded in `work/scans/` (0 for the true
/// scans; none when the set was never made or its time was not recorded).
pub(super) fn cached_seconds(work: &Path, source: ScanSource) -> Result<Option<f64>> {
    if source == ScanSource::True {
        return Ok(Some(0.0));
    }
    let path = work.join("scans").join(format!("{}.json", source.name()));
    Ok(read_work_json::<ScanSetKey>(&path)?.and_then(|key| key.seconds_per_scan))
}

/// A JSON file of the work folder (the job, a run's result, a scan set's key): `None` where it
/// does not exist, else read under [`MAX_CONFIG_BYTES`] (a work folder may be restored from
/// elsewhere) and parsed, with an error naming it.
pub(super) fn read_work_json<T: serde::de::DeserializeOwned>(path: &Path) -> Result<Option<T>> {
    if let Ok(false) = path.try_exists() {
        return Ok(None);
    }
    let bytes = read_metadata(path, MAX_CONFIG_BYTES, "work-folder JSON")?;
    serde_json::from_slice(&bytes)
        .map(Some)
        .map_err(|source| Error::Json {
            path: path.to_path_buf(),
            source,
        })
}

fn read_cached(
    key: &ScanSetKey,
    key_path: &Path,
    data_path: &Path,
    bundle: &Bundle,
) -> Result<Option<(Vec<RangeImage>, Option<f64>)>> {
    let Some(cached) = read_work_json::<ScanSetKey>(key_path)? else {
        return Ok(None);
    };
    let seconds = cached.seconds_per_scan;
    let same = ScanSetKey {
        seconds_per_scan: None,
        ..cached
    };
    if &same != key || !data_path.is_file() {
        return Ok(None);
    }
    let tensors = candle_core::safetensors::load(data_path, &Device::Cpu)?;
    let get = |name: &str| -> Result<Vec<f32>> {
        let t = tensors.get(name).ok_or_else(|| Error::Input {
            path: data_path.to_path_buf(),
            reason: format!("no tensor `{name}`"),
        })?;
        Ok(t.flatten_all()?.to_vec1::<f32>()?)
    };
    let (range, intensity, mask) = (get("range_m")?, get("intensity")?, get("mask")?);
    let sensor = &bundle.config.denoiser.sensor;
    let (rows, cols) = (sensor.rows, sensor.cols);
    let px = rows as usize * cols as usize;
    if range.len() != key.frames * px || intensity.len() != range.len() || mask.len() != range.len()
    {
        return Err(Error::Input {
            path: data_path.to_path_buf(),
            reason: format!("not {} scans of {rows} x {cols}", key.frames),
        });
    }
    Ok(Some((
        (0..key.frames)
            .map(|f| {
                let s = f * px..(f + 1) * px;
                let mut im = RangeImage::new_empty(rows, cols);
                im.range_m.copy_from_slice(&range[s.clone()]);
                im.intensity.copy_from_slice(&intensity[s.clone()]);
                for (m, &v) in im.mask.iter_mut().zip(&mask[s]) {
                    *m = v > 0.5;
                }
                im
            })
            .collect(),
        seconds,
    )))
}

fn write_cached(
    key: &ScanSetKey,
    key_path: &Path,
    data_path: &Path,
    scans: &[RangeImage],
) -> Result<()> {
    let dir = data_path.parent().unwrap_or(Path::new("."));
    std::fs::create_dir_all(dir).map_err(|source| Error::Io {
        action: "creating the scan cache",
        path: dir.to_path_buf(),
        source,
    })?;
    let px = scans.first().map_or(0, |s| s.num_pixels());
    let stack = |f: &dyn Fn(&RangeImage) -> Vec<f32>| -> Result<Tensor> {
        let v: Vec<f32> = scans.iter().flat_map(f).collect();
        Ok(Tensor::from_vec(v, (scans.len(), px), &Device::Cpu)?)
    };
    let tensors: HashMap<String, Tensor> = [
        ("range_m", stack(&|s| s.range_m.clone())?),
        ("intensity", stack(&|s| s.intensity.clone())?),
        (
            "mask",
            stack(&|s| s.mask.iter().map(|&m| f32::from(u8::from(m))).collect())?,
        ),
    ]
    .into_iter()
    .map(|(k, v)| (k.to_string(), v))
    .collect();
    let bytes = veila_nn::checkpoint::safetensors_bytes(&tensors, data_path)?;
    veila_data::atomic::write_atomic(data_path, &bytes)?;
    let json = serde_json::to_vec_pretty(key).map_err(|source| Error::Json {
        path: key_path.to_path_buf(),
        source,
    })?;
    // the key last: a set is used only when its key is there
    veila_data::atomic::write_atomic(key_path, &json)?;
    Ok(())
}

/// The split's name as the report states it (the bundle's list and the frames' range).
pub fn split_name(list: &Path, first: usize, n: usize) -> String {
    format!("{} frames {first}..{}", list.display(), first + n)
}

/// Where a run's files live in the work folder.
pub fn run_dir(work: &Path, name: &str) -> PathBuf {
    work.join("runs").join(name)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn labelled_lists_are_nested_fixed_and_never_empty() {
        let n = 600;
        let one = labelled_frames(n, 0.01);
        let ten = labelled_frames(n, 0.10);
        let twenty = labelled_frames(n, 0.20);
        assert_eq!((one.len(), ten.len(), twenty.len()), (6, 60, 120));
        assert!(one.iter().all(|i| ten.contains(i)));
        assert!(ten.iter().all(|i| twenty.contains(i)));
        assert_eq!(ten, labelled_frames(n, 0.10));
        assert_eq!(labelled_frames(10, 0.001), labelled_frames(10, 0.01));
        assert_eq!(labelled_frames(10, 0.001).len(), 1);
        assert_eq!(labelled_frames(10, 1.0), (0..10).collect::<Vec<_>>());
        // spread over the split, not its first frames
        assert!(twenty.iter().any(|&i| i >= n / 2) && twenty.iter().any(|&i| i < n / 2));
    }

    #[test]
    fn grid_points_carry_each_pixels_label_and_land_in_their_pixel_again() {
        let sensor = veila_geom::LidarSensor {
            rows: 32,
            cols: 256,
            ..veila_geom::LidarSensor::hdl64e()
        };
        let grid = Grid::new(&sensor, SegmenterConfig::bundled()).unwrap();
        let mut im = RangeImage::new_empty(32, 256);
        let mut labels = vec![0u32; im.num_pixels()];
        for (k, (r, m)) in im.range_m.iter_mut().zip(im.mask.iter_mut()).enumerate() {
            if k % 3 == 0 {
                *r = 5.0 + (k % 17) as f32;
                *m = true;
                labels[k] = if k % 2 == 0 { 40 } else { 10 }; // road, car
            }
        }
        im.label = Some(labels.clone());
        let p = grid.points(&im).unwrap();
        assert_eq!(p.xyz.len(), im.mask.iter().filter(|&&m| m).count());
        let ids = grid.train_ids(&p);
        let space = LabelSpace::semantic_kitti();
        assert!(ids.contains(&space.train_id(40)) && ids.contains(&space.train_id(10)));
        let frame = grid.frame(&p, &ids).unwrap();
        // every labelled pixel comes back with its own class
        for (k, &raw) in labels.iter().enumerate() {
            if im.mask[k] {
                assert_eq!(u32::from(frame.labels[k]), space.train_id(raw), "pixel {k}");
            } else {
                assert_eq!(frame.labels[k], 0, "pixel {k}");
            }
        }
    }
}
