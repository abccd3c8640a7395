//! Simulated frames for a segmenter (feature `sim`): the LiDAR scans of `veila_data::sim` scenes
//! with their ground truth (each point's SemanticKITTI raw class, mapped by the built-in learning
//! map), projected on the segmenter's grid. Scenes are drawn from a split list as the bundle's
//! frames are (`split_items`: its scene files interleaved, seeds in order); the camera is not
//! rendered.

use std::path::{Path, PathBuf};

use rayon::prelude::*;
use veila_data::PointCloud;
use veila_data::sim::{Scene, SceneConfig};
use veila_geom::Projector;
use veila_nn::segmenter::SegmenterConfig;

use super::frames::{GridScan, SegFrame};
use super::labels::LabelSpace;
use super::train::HeldOutScan;
use crate::app::sim_examples::split_items;
use crate::error::{Error, Result};

/// Frames `frames` of scene file `path` at `seed`, spread over its frames (`None`: the split's
/// frame `seed % count`, one), as point clouds with their raw labels.
fn render(path: &Path, seed: u64, frames: Option<u32>) -> Result<Vec<PointCloud>> {
    let cfg = SceneConfig::from_file(path)?;
    let scene = Scene::generate(&cfg, seed)?;
    let count = cfg.frames.count.max(1);
    let lidar = cfg.lidar.sensor()?;
    let picks: Vec<u32> = match frames {
        Some(f) => (0..f).map(|i| (i * count / f).min(count - 1)).collect(),
        None => vec![(seed % u64::from(count)) as u32],
    };
    picks
        .into_iter()
        .map(|i| {
            let scan = scene.snapshot(i).render_lidar(&lidar, &cfg.lidar.returns)?;
            if scan.points.label.is_none() {
                return Err(Error::Data("a simulated scan without labels".into()));
            }
            Ok(scan.points)
        })
        .collect()
}

/// The train id of every point of a simulated scan.
fn train_ids(cloud: &PointCloud) -> Vec<u32> {
    let space = LabelSpace::semantic_kitti();
    cloud
        .label
        .iter()
        .flatten()
        .map(|&r| space.train_id(r))
        .collect()
}

/// `make` of every scan of the first `scenes` pairs of `list` (`frames` of each, as [`render`]
/// takes it), the scenes rendered in parallel and kept in list order; `on_scene` after each.
fn simulate<T: Send>(
    list: &Path,
    scenes: usize,
    frames: Option<u32>,
    on_scene: &(dyn Fn() + Sync),
    make: impl Fn(&PointCloud) -> Result<T> + Sync,
) -> Result<Vec<T>> {
    let items: Vec<(PathBuf, u64)> = split_items(list, scenes)?;
    check_count(list, items.len(), scenes)?;
    let per: Vec<Vec<T>> = items
        .par_iter()
        .map(|(path, seed)| {
            let out = render(path, *seed, frames)
                .and_then(|clouds| clouds.iter().map(&make).collect::<Result<Vec<T>>>())
                .map_err(|e| Error::Input {
                    path: path.clone(),
                    reason: format!("seed {seed}: {e}"),
                })?;
            on_scene();
            Ok(out)
        })
        .collect::<Result<_>>()?;
    Ok(per.into_iter().flatten().collect())
}

/// The training frames of the first `scenes` (scene file, seed) pairs of the list `list`,
/// `frames_per_scene` of each, projected with `projector` for `cfg`; in parallel, the same
/// arguments giving the same frames. `on_scene` is called after each scene.
pub fn simulated_frames(
    list: &Path,
    scenes: usize,
    frames_per_scene: u32,
    projector: &Projector,
    cfg: &SegmenterConfig,
    on_scene: &(dyn Fn() + Sync),
) -> Result<Vec<SegFrame>> {
    simulate(list, scenes, Some(frames_per_scene), on_scene, |c| {
        SegFrame::from_points(&c.xyz, &c.intensity, &train_ids(c), projector, cfg)
    })
}

/// One held-out scan of each of the first `scenes` pairs of `list` (the split's frame of each),
/// on the grid of `projector` and `cfg`, with the true train id of every point.
pub fn simulated_held_out(
    list: &Path,
    scenes: usize,
    projector: &Projector,
    cfg: &SegmenterConfig,
    on_scene: &(dyn Fn() + Sync),
) -> Result<Vec<HeldOutScan>> {
    simulate(list, scenes, None, on_scene, |c| {
        Ok(HeldOutScan {
            scan: GridScan::new(&c.xyz, &c.intensity, projector, cfg)?,
            truth: train_ids(c),
        })
    })
}

fn check_count(list: &Path, got: usize, want: usize) -> Result<()> {
    if got < want {
        return Err(Error::Input {
            path: list.to_path_buf(),
            reason: format!("the list has {got} (scene, seed) pairs, {want} were asked for"),
        });
    }
    Ok(())
}
