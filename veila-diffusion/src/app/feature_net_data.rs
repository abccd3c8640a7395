//! The training scans of the FRD / FPD feature networks (feature `sim`; `cargo xtask
//! train-feature-nets`, which trains them with [`veila_nn::feature_nets::train`]): seeded
//! (scene file, seed) pairs of a scene list, rendered with each scene's own LiDAR and projected
//! to the RangeNet's grid exactly as `veila eval` projects scans, every scan augmented once by a
//! random yaw and a random left / right mirror.

use std::path::{Path, PathBuf};

use glam::{Quat, Vec3};
use rand::seq::SliceRandom;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;
use veila_data::semantic_kitti::class;
use veila_data::sim::{Scene, SceneConfig, SceneList};
use veila_geom::LidarSensor;
use veila_nn::feature_nets::RangeNetInput;
use veila_nn::feature_nets::train::{COMPOSITION_CLASSES, FeatureSample};

use crate::error::{Error, Result, invalid};

/// (scene file, seed) pairs, one a scene.
pub type ScenePairs = Vec<(PathBuf, u64)>;

/// A seeded draw of `n` (scene file, seed) pairs from `list`, round-robin over its scene files
/// so layouts stay balanced; also the list's scene files (a pair's layout is its file's index).
pub fn draw_scene_pairs(
    list_path: &Path,
    n: usize,
    seed: u64,
) -> Result<(ScenePairs, Vec<PathBuf>)> {
    let list = SceneList::read(list_path)?;
    let files: Vec<PathBuf> = list.entries.iter().map(|e| e.scene.clone()).collect();
    if files.is_empty() {
        return Err(invalid(
            "scenes",
            format!("{} lists no scene", list_path.display()),
        ));
    }
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut per_file: Vec<Vec<u64>> = list
        .entries
        .iter()
        .map(|e| {
            let mut s: Vec<u64> = e.seeds.clone().collect();
            s.shuffle(&mut rng);
            s
        })
        .collect();
    let mut pairs = Vec::with_capacity(n);
    for i in 0..n {
        let f = i % files.len();
        let Some(seed) = per_file[f].pop() else {
            return Err(invalid(
                "scenes",
                format!("{} has too few seeds for {n} scenes", list_path.display()),
            ));
        };
        pairs.push((files[f].clone(), seed));
    }
    Ok((pairs, files))
}

fn layout_index(scene_file: &Path, files: &[PathBuf]) -> usize {
    files.iter().position(|f| f == scene_file).unwrap_or(0)
}

/// `frames` scans of every pair (spread over the scene's frames), augmented and projected to
/// `sensor`'s grid, in parallel; the same arguments give the same samples.
pub fn simulate_feature_samples(
    pairs: &[(PathBuf, u64)],
    files: &[PathBuf],
    frames: u32,
    sensor: &LidarSensor,
    seed: u64,
) -> Result<Vec<FeatureSample>> {
    let jobs: Vec<(usize, u32)> = (0..pairs.len())
        .flat_map(|s| (0..frames).map(move |f| (s, f)))
        .collect();
    let configs: Vec<SceneConfig> = files
        .iter()
        .map(|f| SceneConfig::from_file(f))
        .collect::<std::result::Result<_, _>>()?;
    let scenes: Vec<Scene> = pairs
        .par_iter()
        .map(|(file, s)| {
            let cfg = &configs[layout_index(file, files)];
            Scene::generate(cfg, *s).map_err(|e| Error::Input {
                path: file.clone(),
                reason: format!("seed {s}: {e}"),
            })
        })
        .collect::<Result<_>>()?;
    jobs.par_iter()
        .map(|&(si, fi)| {
            let scene = &scenes[si];
            let count = scene.config().frames.count.max(1);
            let frame = (fi * count / frames.max(1)).min(count - 1);
            let lidar = scene.config().lidar.sensor()?;
            let scan = scene
                .snapshot(frame)
                .render_lidar(&lidar, &scene.config().lidar.returns)?;
            let mut rng = ChaCha8Rng::seed_from_u64(seed ^ ((si as u64) << 20) ^ u64::from(fi));
            let yaw = rng.random_range(-std::f32::consts::PI..std::f32::consts::PI);
            let mirror = rng.random_bool(0.5);
            let rot = Quat::from_rotation_z(yaw);
            let points: Vec<Vec3> = scan
                .points
                .xyz
                .iter()
                .map(|p| {
                    let q = rot * *p;
                    if mirror { Vec3::new(q.x, -q.y, q.z) } else { q }
                })
                .collect();
            let Some(l) = &scan.points.label else {
                return Err(Error::Data("a simulated scan without labels".into()));
            };
            let labels: Vec<u8> = l
                .iter()
                .map(|v| class::learning_id((v & 0xffff) as u16))
                .collect();
            let input = RangeNetInput::from_points(&points, Some(&scan.points.intensity), sensor)?;
            let pixel_class = input
                .point_index
                .iter()
                .map(|&i| if i == u32::MAX { 0 } else { labels[i as usize] })
                .collect();
            let mut composition = [0f32; COMPOSITION_CLASSES];
            for &l in &labels {
                composition[l as usize] += 1.0;
            }
            let total = labels.len().max(1) as f32;
            composition.iter_mut().for_each(|c| *c /= total);
            Ok(FeatureSample {
                scene: si,
                layout: layout_index(&pairs[si].0, files),
                input,
                pixel_class,
                points,
                composition,
            })
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pairs_are_drawn_round_robin_from_the_list_the_same_way_each_time() {
        let root = Path::new(env!("CARGO_MANIFEST_DIR")).parent().unwrap();
        let list = root.join("scenes/train.txt");
        let (pairs, files) = draw_scene_pairs(&list, 6, 7).unwrap();
        assert_eq!(files.len(), 3);
        for (i, (f, _)) in pairs.iter().enumerate() {
            assert_eq!(f, &files[i % 3]);
        }
        assert_eq!(draw_scene_pairs(&list, 6, 7).unwrap().0, pairs);
        assert_ne!(draw_scene_pairs(&list, 6, 8).unwrap().0, pairs);
        assert!(draw_scene_pairs(&list, 100_000, 7).is_err());
        // one scan of one pair: labels on the grid, a composition that sums to one
        let sensor = veila_nn::feature_nets::RangeNetConfig::small().sensor;
        let s = simulate_feature_samples(&pairs[..1], &files, 1, &sensor, 7).unwrap();
        assert_eq!(s.len(), 1);
        assert!((s[0].composition.iter().sum::<f32>() - 1.0).abs() < 1e-4);
        assert!(s[0].pixel_class.iter().any(|&c| c != 0));
        assert_eq!(s[0].layout, 0);
    }
}
