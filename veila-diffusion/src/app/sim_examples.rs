//! Simulated examples for training and benchmarking (feature `sim`): scenes of a split list
//! rendered by `veila_data::sim` and reduced to what a bundle trains and is scored on, at its
//! size. `cargo xtask train-default`, `bench-report`, `bench-real` and `bench-memory` draw their
//! frames here.
//!
//! * [`SimExample`]: one frame: the camera image fitted to the encoders' input (the same
//!   resize every door gets from `ScanPipeline`), dense ground-truth semantics and depth at that size, the
//!   scan on the bundle's range grid and the rig's further cameras; [`SimExample::train_example`]
//!   turns it into a [`TrainExample`].
//! * Split lists: [`split_items`] (the first frames of a list, its scene files interleaved),
//!   [`train_split_of`] (the list a bundle's provenance names), [`test_list_for`] (the held-out
//!   list beside a training list).
//! * [`render_split`] / [`render_split_styled`]: the first `n` frames of a list, rendered in
//!   parallel; byte-identical for a given list, bundle config and [`RenderStyle`] whatever the
//!   thread count ([`render_split_shown`]: with a progress bar).
//! * [`TrainImages`] and [`RenderStyle`]: issue 18's domain randomisation of the camera images
//!   (scene appearance, sensor model), as a bundle's provenance records it.
//! * [`retrieval_baseline`]: the zero-skill retrieval baseline on simulated frames.

use std::path::{Path, PathBuf};

use rayon::prelude::*;
use veila_data::augment::Photometric;
use veila_data::semantic_kitti::class;
use veila_data::sim::{Scene, SceneConfig, SceneList, SimFrame, SimImage, SimScan, SimView};
use veila_geom::{PinholeCamera, ProjectionOptions, Projector, RangeImage};

use super::bundle::{Bundle, BundleConfig};
use super::dataset::{TrainExample, TrainView, blind_camera};
use super::generate::CameraView;
use super::progress::Progress;
use super::rig::prepare_view;
use crate::error::{Error, Result, invalid};

/// One simulated frame, reduced to what training and evaluation use.
#[derive(Debug, Clone)]
pub struct SimExample {
    /// RGB at the bundle image size.
    pub rgb: Vec<u8>,
    /// Learning-map class ids at the bundle image size (nearest).
    pub labels: Vec<u32>,
    /// Ground-truth depth at the bundle image size (nearest; 0 = sky).
    pub depth_m: Vec<f32>,
    /// The camera of the resized image.
    pub camera: PinholeCamera,
    /// The scan projected on the bundle's grid, with each pixel's SemanticKITTI raw label (its
    /// point's) where the simulator labels its points.
    pub range: RangeImage,
    /// The rig's further cameras at the bundle image size (multi-view configs, see
    /// [`RIG_YAWS_DEG`]).
    pub extra_views: Vec<TrainView>,
}

/// The turns of a simulated rig's further cameras from the front one, degrees (positive: left),
/// in view order: nuScenes' front-left and front-right cameras sit at about +-55 degrees.
pub const RIG_YAWS_DEG: [f32; 5] = [55.0, -55.0, 110.0, -110.0, 180.0];

impl SimExample {
    /// The training example (encoded range image).
    pub fn train_example(&self, cfg: &BundleConfig) -> Result<TrainExample> {
        let x0 = cfg.encoding.encode_to_vec(&self.range)?;
        Ok(TrainExample {
            extra_views: self.extra_views.clone(),
            ..TrainExample::new(self.rgb.clone(), self.camera, x0)
        })
    }

    /// The example's first `n` camera views (the front camera, then the rig's further ones), as
    /// the bundle's sampling takes them.
    pub fn views(&self, n: usize) -> Vec<CameraView<'_>> {
        std::iter::once(CameraView {
            rgb: &self.rgb,
            camera: &self.camera,
        })
        .chain(
            self.extra_views
                .iter()
                .take(n.saturating_sub(1))
                .map(|v| CameraView {
                    rgb: &v.rgb,
                    camera: &v.camera,
                }),
        )
        .collect()
    }
}

fn nearest<T: Copy>(src: &[T], w: usize, h: usize, new_w: usize, new_h: usize) -> Vec<T> {
    let mut out = Vec::with_capacity(new_w * new_h);
    for y in 0..new_h {
        let sy = (((y as f64 + 0.5) * h as f64 / new_h as f64) as usize).min(h - 1);
        for x in 0..new_w {
            let sx = (((x as f64 + 0.5) * w as f64 / new_w as f64) as usize).min(w - 1);
            out.push(src[sy * w + sx]);
        }
    }
    out
}

/// A simulated camera image and its camera fitted to `cfg`'s input ([`prepare_view`]).
fn fitted(cfg: &BundleConfig, image: &SimImage, camera: &PinholeCamera) -> Result<TrainView> {
    let (rgb, camera) = prepare_view(cfg, &image.to_rgb_image()?, camera)?;
    Ok(TrainView { rgb, camera })
}

/// Reduces a rendered frame to a [`SimExample`] for `cfg`'s image size and range grid.
pub fn example_from_frame(frame: &SimFrame, cfg: &BundleConfig) -> Result<SimExample> {
    let img = &frame.image;
    let (w, h) = (img.width as usize, img.height as usize);
    let (nw, nh) = (cfg.image_width, cfg.image_height);
    let TrainView { rgb, camera } = fitted(cfg, img, &frame.camera)?;
    let labels: Vec<u32> = nearest(&img.semantic, w, h, nw, nh)
        .into_iter()
        .map(|r| class::learning_id(r) as u32)
        .collect();
    let depth_m = nearest(&img.depth_m, w, h, nw, nh);
    Ok(SimExample {
        rgb,
        labels,
        depth_m,
        camera,
        range: scan_on_grid(&frame.scan, cfg)?,
        extra_views: Vec::new(),
    })
}

/// A simulated scan projected on `cfg`'s range grid, each pixel with its point's SemanticKITTI
/// raw label (the segmentation benchmark's truth) where the simulator labels its points.
fn scan_on_grid(scan: &SimScan, cfg: &BundleConfig) -> Result<RangeImage> {
    let projector = Projector::new(&cfg.denoiser.sensor, ProjectionOptions::default())?;
    let cloud = &scan.points;
    let (mut range, _) = projector.project(&cloud.xyz, Some(&cloud.intensity), None)?;
    if let Some(raw) = &cloud.label {
        let labels = range
            .point_index
            .iter()
            .zip(&range.mask)
            .map(|(&i, &m)| {
                if m {
                    raw.get(i as usize).copied().unwrap_or(0)
                } else {
                    0
                }
            })
            .collect();
        range.label = Some(labels);
    }
    Ok(range)
}

/// [`example_from_frame`] with the rig's further cameras (`views` from
/// [`Scene::render_frame_rig`]), each fitted to `cfg`'s image size.
pub fn example_from_rig(
    frame: &SimFrame,
    views: &[SimView],
    cfg: &BundleConfig,
) -> Result<SimExample> {
    let mut ex = example_from_frame(frame, cfg)?;
    ex.extra_views = views
        .iter()
        .map(|v| fitted(cfg, &v.image, &v.camera))
        .collect::<Result<_>>()?;
    Ok(ex)
}

/// The depth encoder's targets of a simulated image with its sky read as far (`train-default
/// --sky-depth`): the pixels whose camera ray hits nothing carry depth 0 ("no ground truth", so
/// the loss skips them); here they get `far_m`, every other pixel keeps its depth. In the
/// simulator's images depth 0 is exactly the sky: every surface it draws has a depth above 0.
pub fn depth_with_sky_at(depth_m: &[f32], far_m: f32) -> Vec<f32> {
    depth_m
        .iter()
        .map(|&d| if d == 0.0 { far_m } else { d })
        .collect()
}

/// The street list (streets and a junction): what every bundle whose provenance names no list was
/// trained on, the list the shipped recipe trains its encoders on (`train-default
/// --encoder-scenes`), and that of the reference mean scan `bench-real` adds for bundles trained
/// on another list.
pub const DEFAULT_SCENES: &str = "scenes/train.txt";

/// The list the shipped recipe trains its mean network and denoiser on (`train-default
/// --scenes`): the streets plus T junctions (since 2026-11-26).
pub const RECIPE_SCENES: &str = "scenes/train-v5.txt";

/// The held-out list of the shipped recipe.
pub const DEFAULT_TEST_SCENES: &str = "scenes/test.txt";

/// The scene list a bundle was trained on, as its provenance's `train_split` names it (relative
/// to the workspace; [`DEFAULT_SCENES`] for bundles that do not say), so its baselines are built
/// from the same scenes.
pub fn train_split_of(cfg: &BundleConfig) -> PathBuf {
    let rel = cfg
        .provenance
        .get("train_split")
        .and_then(|v| v.as_str())
        .unwrap_or(DEFAULT_SCENES);
    PathBuf::from(rel)
}

/// The held-out list that goes with a training list: `test-vN.txt` beside `train-vN.txt` (and
/// `test.txt` beside `train.txt`), or [`DEFAULT_TEST_SCENES`] for a list without one. Relative
/// paths are taken against `root` (the workspace).
pub fn test_list_for(root: &Path, train_list: &Path) -> PathBuf {
    let sibling = train_list
        .file_name()
        .and_then(|n| n.to_str())
        .and_then(|n| n.strip_prefix("train"))
        .map(|rest| train_list.with_file_name(format!("test{rest}")));
    match sibling {
        Some(t) if root.join(&t).is_file() => t,
        _ => PathBuf::from(DEFAULT_TEST_SCENES),
    }
}

/// The first `n` frames of a split list, interleaving its scene files (scene 0 seed 0, scene 1
/// seed 0, ..., scene 0 seed 1, ...); frame `seed % frames` of each scene.
pub fn split_items(list: &Path, n: usize) -> Result<Vec<(PathBuf, u64)>> {
    let scenes = SceneList::read(list)?;
    let mut per_file: Vec<(PathBuf, Vec<u64>)> = Vec::new();
    for (path, seed) in scenes.iter() {
        match per_file.iter_mut().find(|(p, _)| p == path) {
            Some((_, v)) => v.push(seed),
            None => per_file.push((path.to_path_buf(), vec![seed])),
        }
    }
    let mut out = Vec::with_capacity(n);
    let mut k = 0;
    while out.len() < n {
        let mut any = false;
        for (p, seeds) in &per_file {
            if let Some(s) = seeds.get(k) {
                any = true;
                if out.len() < n {
                    out.push((p.clone(), *s));
                }
            }
        }
        if !any {
            break;
        }
        k += 1;
    }
    Ok(out)
}

/// Renders the first `n` frames of a split for `cfg` in parallel, with as many cameras as `cfg`
/// takes views (the front one, then [`RIG_YAWS_DEG`]); `on_frame` is called after each frame
/// (from the rendering threads: a progress bar's tick).
pub fn render_split(
    list: &Path,
    n: usize,
    cfg: &BundleConfig,
    on_frame: &(dyn Fn() + Sync),
) -> Result<Vec<SimExample>> {
    render_split_styled(list, n, cfg, &RenderStyle::default(), on_frame)
}

/// How a training run renders its camera images (issue 18's domain randomisation; `train-default
/// --images`). Only the images change: scans, depth and labels are the same in every style.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum TrainImages {
    /// The simulator's stock images.
    Stock,
    /// The sun and sky drawn per scene (elevation, azimuth, colour, cloud cover) over the stock
    /// materials: the lighting half of `appearance`.
    Lighting,
    /// The palettes and procedural textures drawn per scene under its own sun and sky: the
    /// material half of `appearance` (the recipe of `models/default` since 2026-11-25).
    Materials,
    /// Both halves: scene appearance drawn per scene, no sensor model.
    Appearance,
    /// Scene appearance and the sensor (exposure, white balance, noise, blur, vignetting, JPEG).
    Randomized,
}

impl std::str::FromStr for TrainImages {
    type Err = Error;

    /// A style by its [`name`](TrainImages::name).
    fn from_str(s: &str) -> Result<Self> {
        Self::ALL
            .into_iter()
            .find(|t| t.name() == s)
            .ok_or_else(|| {
                let names: Vec<&str> = Self::ALL.iter().map(|t| t.name()).collect();
                invalid("images", format!("`{s}` is none of {}", names.join(", ")))
            })
    }
}

impl TrainImages {
    /// Every style, in the order of [`name`](TrainImages::name)'s documentation.
    pub const ALL: [TrainImages; 5] = [
        TrainImages::Stock,
        TrainImages::Lighting,
        TrainImages::Materials,
        TrainImages::Appearance,
        TrainImages::Randomized,
    ];

    /// The style's name on the command line: `stock`, `lighting`, `materials`, `appearance` or
    /// `randomized`.
    pub fn name(self) -> &'static str {
        match self {
            TrainImages::Stock => "stock",
            TrainImages::Lighting => "lighting",
            TrainImages::Materials => "materials",
            TrainImages::Appearance => "appearance",
            TrainImages::Randomized => "randomized",
        }
    }

    /// The name a bundle's provenance records (`provenance.train_images.appearance`).
    pub fn provenance_name(self) -> &'static str {
        match self {
            TrainImages::Stock => "stock",
            TrainImages::Lighting => "lighting randomized",
            TrainImages::Materials => "materials randomized",
            TrainImages::Appearance => "lighting and materials randomized",
            TrainImages::Randomized => "randomized",
        }
    }

    /// The style a bundle was trained on, from its provenance (stock when it records none, as
    /// bundles from before 2026-11-25 do).
    pub fn of_bundle(cfg: &BundleConfig) -> Self {
        let name = cfg
            .provenance
            .get("train_images")
            .and_then(|t| t.get("appearance"))
            .and_then(|v| v.as_str());
        Self::ALL
            .into_iter()
            .find(|t| Some(t.provenance_name()) == name)
            .unwrap_or(TrainImages::Stock)
    }

    /// The render style a bundle's training images had: [`TrainImages::of_bundle`] on the share
    /// its provenance records.
    pub fn style_of_bundle(cfg: &BundleConfig) -> RenderStyle {
        let number = |key: &str| {
            cfg.provenance
                .get("train_images")
                .and_then(|t| t.get(key))
                .and_then(|v| v.as_f64())
                .map(|p| p as f32)
        };
        let images = Self::of_bundle(cfg);
        let mut style = images.style(number("randomized_share"));
        if images.draws_materials() {
            style.wide_facade_share = number("wide_facade_share").unwrap_or(0.0);
        }
        style
    }

    /// [`TrainImages::style`] with the wide facade palette on `wide` of the drawn facades
    /// (`train-default`'s `--randomize-share` and `--wide-facades`): each share within (0, 1],
    /// `share` only with a randomised style and `wide` only with one that draws materials.
    pub fn checked_style(self, share: Option<f32>, wide: Option<f32>) -> Result<RenderStyle> {
        let in_unit = |p: f32| p > 0.0 && p <= 1.0;
        if let Some(p) = share {
            if !in_unit(p) {
                return Err(invalid(
                    "randomize_share",
                    format!("{p} is not a share within (0, 1]"),
                ));
            }
            if self == TrainImages::Stock {
                return Err(invalid(
                    "randomize_share",
                    "needs an images style other than stock",
                ));
            }
        }
        if let Some(w) = wide {
            if !in_unit(w) {
                return Err(invalid(
                    "wide_facades",
                    format!("{w} is not a share within (0, 1]"),
                ));
            }
            if !self.draws_materials() {
                return Err(invalid(
                    "wide_facades",
                    "needs an images style that draws materials (materials, appearance or randomized)",
                ));
            }
        }
        let mut style = self.style(share);
        style.wide_facade_share = wide.unwrap_or(0.0);
        Ok(style)
    }

    /// Whether these images draw palettes and textures (what `--wide-facades` widens).
    pub fn draws_materials(self) -> bool {
        matches!(
            self,
            TrainImages::Materials | TrainImages::Appearance | TrainImages::Randomized
        )
    }

    /// The render style of these images, on the given share of the frames (`None`: all).
    pub fn style(self, share: Option<f32>) -> RenderStyle {
        let mut style = RenderStyle::randomized(self == TrainImages::Randomized);
        style.randomize_lighting = matches!(self, TrainImages::Lighting | TrainImages::Appearance);
        style.randomize_materials =
            matches!(self, TrainImages::Materials | TrainImages::Appearance);
        style.share = share.filter(|_| self != TrainImages::Stock);
        style
    }
}
/// How simulated camera images look: the simulator's stock images by default, or with the
/// domain randomisation of issue 18.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct RenderStyle {
    /// Scene appearance drawn per scene (`[appearance] randomize`: textures, palettes, sun, sky).
    pub randomize_appearance: bool,
    /// The sun and sky alone drawn per scene (`[appearance] randomize_lighting`), stock materials.
    pub randomize_lighting: bool,
    /// The palettes and textures alone drawn per scene (`[appearance] randomize_materials`), the
    /// scene's own sun and sky.
    pub randomize_materials: bool,
    /// Sensor randomisation at the rendered resolution (exposure, vignetting, blur, white
    /// balance, noise, colour, JPEG), seeded per frame.
    pub sensor: Option<Photometric>,
    /// The share of the frames, within `(0, 1]`, that the two randomisations apply to (chosen
    /// per frame by a hash of its seed and place, so the same list gives the same choice); the
    /// others keep the stock images. `None`: every frame.
    pub share: Option<f32>,
    /// The share of the facade looks drawn from the whole colour wheel where materials are drawn
    /// (`[appearance] wide_facade_share`; 0: the stock palettes).
    pub wide_facade_share: f32,
    /// No camera at all: the scans alone, for models that never look at the camera
    /// ([`BundleConfig::needs_camera`]); a camera image costs most of a frame. The examples have
    /// no image, labels or depth, and carry [`blind_camera`]. The scans are the same either way.
    pub scan_only: bool,
}

impl RenderStyle {
    /// The stock images (`false`) or both randomisations at their defaults (`true`).
    pub fn randomized(on: bool) -> Self {
        RenderStyle {
            randomize_appearance: on,
            randomize_lighting: false,
            randomize_materials: false,
            sensor: on.then(Photometric::default),
            share: None,
            wide_facade_share: 0.0,
            scan_only: false,
        }
    }

    /// Whether the randomisations apply to item `k` of a split, rendered from scene seed `seed`.
    pub fn applies_to(&self, seed: u64, k: u64) -> bool {
        self.share.is_none_or(|p| {
            // the top 24 bits of the frame's hash as a uniform draw in [0, 1)
            let u = (sensor_seed(seed, k ^ 0x5eed) >> 40) as f32 / (1u64 << 24) as f32;
            u < p
        })
    }
}

/// [`render_split`] with a [`RenderStyle`] (the default style renders the same bytes). Errors
/// name the scene file and seed.
pub fn render_split_styled(
    list: &Path,
    n: usize,
    cfg: &BundleConfig,
    style: &RenderStyle,
    on_frame: &(dyn Fn() + Sync),
) -> Result<Vec<SimExample>> {
    render_items(&split_items(list, n)?, 0, cfg, style, on_frame)
}

/// `items` (a split's items from its item `first` on) rendered in parallel, in order.
fn render_items(
    items: &[(PathBuf, u64)],
    first: usize,
    cfg: &BundleConfig,
    style: &RenderStyle,
    on_frame: &(dyn Fn() + Sync),
) -> Result<Vec<SimExample>> {
    items
        .par_iter()
        .enumerate()
        .map(|(j, (path, seed))| {
            let k = (first + j) as u64;
            let ex = render_item(path, *seed, k, cfg, style).map_err(|e| Error::Input {
                path: path.clone(),
                reason: format!("seed {seed}: {e}"),
            })?;
            on_frame();
            Ok(ex)
        })
        .collect()
}

/// [`render_split_styled`] of a list relative to the workspace `root`, shown as a bar named
/// `label` (the benchmarks' and the recipe's frames).
pub fn render_split_shown(
    root: &Path,
    list: &Path,
    n: usize,
    cfg: &BundleConfig,
    style: &RenderStyle,
    label: &str,
    progress: &dyn Progress,
) -> Result<Vec<SimExample>> {
    let bar = progress.bar(label, n as u64);
    render_split_styled(&root.join(list), n, cfg, style, &|| bar.inc())
}

/// The split's frames `skip..skip + n` of a list relative to the workspace `root`, in the
/// default style, shown as a bar named `label`: the frames after the `skip` a bundle trained on.
pub fn render_split_after(
    root: &Path,
    list: &Path,
    skip: usize,
    n: usize,
    cfg: &BundleConfig,
    label: &str,
    progress: &dyn Progress,
) -> Result<Vec<SimExample>> {
    let items = split_items(&root.join(list), skip + n)?;
    if items.len() < skip + n {
        return Err(Error::Input {
            path: root.join(list),
            reason: format!(
                "the list has {} frames, {} were asked for ({skip} skipped, then {n})",
                items.len(),
                skip + n
            ),
        });
    }
    let bar = progress.bar(label, n as u64);
    render_items(&items[skip..], skip, cfg, &RenderStyle::default(), &|| {
        bar.inc()
    })
}

/// Item `k` of a split: scene file `path` at `seed`, rendered in `style`.
fn render_item(
    path: &Path,
    seed: u64,
    k: u64,
    cfg: &BundleConfig,
    style: &RenderStyle,
) -> Result<SimExample> {
    let mut scene_cfg = SceneConfig::from_file(path)?;
    let on = style.applies_to(seed, k);
    scene_cfg.appearance.randomize |= style.randomize_appearance && on;
    scene_cfg.appearance.randomize_lighting |= style.randomize_lighting && on;
    scene_cfg.appearance.randomize_materials |= style.randomize_materials && on;
    if on && style.wide_facade_share > 0.0 {
        scene_cfg.appearance.wide_facade_share = style.wide_facade_share;
    }
    let scene = Scene::generate(&scene_cfg, seed)?;
    let frames = scene_cfg.frames.count.max(1) as u64;
    if style.scan_only {
        let scan = scene.render_scan((seed % frames) as u32)?;
        return Ok(SimExample {
            rgb: Vec::new(),
            labels: Vec::new(),
            depth_m: Vec::new(),
            camera: blind_camera(cfg)?,
            range: scan_on_grid(&scan, cfg)?,
            extra_views: Vec::new(),
        });
    }
    let yaws = &RIG_YAWS_DEG[..cfg.num_views().clamp(1, RIG_YAWS_DEG.len() + 1) - 1];
    let (mut frame, mut views) = scene.render_frame_rig((seed % frames) as u32, yaws)?;
    if let Some(sensor) = style.sensor.as_ref().filter(|_| on) {
        // one draw per frame (the rig's cameras share a sensor model, each its noise)
        let frame_seed = sensor_seed(seed, k);
        degrade(&mut frame.image, sensor, frame_seed)?;
        for (j, v) in views.iter_mut().enumerate() {
            degrade(&mut v.image, sensor, frame_seed ^ (j as u64 + 1))?;
        }
    }
    example_from_rig(&frame, &views, cfg)
}

fn sensor_seed(scene_seed: u64, item: u64) -> u64 {
    scene_seed
        .wrapping_mul(0x9E37_79B9_7F4A_7C15)
        .wrapping_add(item.wrapping_mul(0xD1B5_4A32_D192_ED03))
}

fn degrade(image: &mut SimImage, sensor: &Photometric, seed: u64) -> Result<()> {
    let img = image.to_rgb_image()?;
    image.rgb = sensor.augment(&img, seed)?.into_raw();
    Ok(())
}

/// The retrieval baseline: for every test frame, the range image of the training frame whose
/// camera image is nearest (cosine) in `bundle`'s frozen encoders' features.
pub fn retrieval_baseline(
    bundle: &Bundle,
    train: &[SimExample],
    tests: &[SimExample],
) -> Result<Vec<RangeImage>> {
    let descriptor = |ex: &SimExample| {
        bundle.image_descriptor(CameraView {
            rgb: &ex.rgb,
            camera: &ex.camera,
        })
    };
    let keys = train.iter().map(descriptor).collect::<Result<Vec<_>>>()?;
    tests
        .iter()
        .map(|ex| {
            let i = veila_metrics::baseline::nearest(&descriptor(ex)?, &keys)?;
            Ok(train[i].range.clone())
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::app::bundle::Variant;

    /// The workspace (this crate lives one level below it): the scene lists are relative to it.
    fn workspace_root() -> PathBuf {
        Path::new(env!("CARGO_MANIFEST_DIR"))
            .parent()
            .expect("the crate sits in the workspace")
            .to_path_buf()
    }

    #[test]
    fn a_randomize_share_picks_that_share_of_frames_the_same_way_each_time() {
        let all = RenderStyle::randomized(true);
        assert!((0..1000u64).all(|k| all.applies_to(k % 800, k)));
        let half = RenderStyle {
            share: Some(0.5),
            ..all
        };
        let picked: Vec<bool> = (0..4000u64).map(|k| half.applies_to(k % 800, k)).collect();
        let n = picked.iter().filter(|&&b| b).count();
        // binomial(4000, 0.5): sd 32
        assert!((1850..2150).contains(&n), "{n}");
        let again: Vec<bool> = (0..4000u64).map(|k| half.applies_to(k % 800, k)).collect();
        assert_eq!(picked, again);
        // a smaller share picks a subset of a larger one's frames
        let tenth = RenderStyle {
            share: Some(0.1),
            ..all
        };
        let m = (0..4000u64)
            .filter(|&k| tenth.applies_to(k % 800, k))
            .count();
        assert!((330..470).contains(&m), "{m}");
        assert!((0..4000u64).all(|k| !tenth.applies_to(k % 800, k) || half.applies_to(k % 800, k)));
        let one = RenderStyle {
            share: Some(1.0),
            ..all
        };
        assert!((0..1000u64).all(|k| one.applies_to(k, k)));
    }

    #[test]
    fn a_bundles_training_images_read_back_from_its_provenance() {
        let mut cfg = BundleConfig::cpu_default(Variant::Full);
        // bundles from before the style was recorded trained on the stock images
        cfg.provenance = serde_json::Value::Null;
        assert_eq!(TrainImages::of_bundle(&cfg), TrainImages::Stock);
        assert_eq!(TrainImages::style_of_bundle(&cfg), RenderStyle::default());
        for t in TrainImages::ALL {
            assert_eq!(t.name().parse::<TrainImages>().unwrap(), t);
            cfg.provenance = serde_json::json!({
                "train_images": { "appearance": t.provenance_name(), "randomized_share": 0.5 }
            });
            assert_eq!(TrainImages::of_bundle(&cfg), t);
            let style = TrainImages::style_of_bundle(&cfg);
            assert_eq!(style, t.style(Some(0.5)));
            // the stock images have nothing to share out
            assert_eq!(style.share, (t != TrainImages::Stock).then_some(0.5));
            // the wide facade palette reads back where the style draws materials
            cfg.provenance["train_images"]["wide_facade_share"] = serde_json::json!(0.25);
            let wide = TrainImages::style_of_bundle(&cfg);
            let expected = if t.draws_materials() { 0.25 } else { 0.0 };
            assert_eq!(wide.wide_facade_share, expected, "{t:?}");
            assert_eq!(
                RenderStyle {
                    wide_facade_share: 0.0,
                    ..wide
                },
                style
            );
        }
        // the flags' checks: shares within (0, 1], each only where it means something
        use TrainImages::*;
        let wide = Materials.checked_style(Some(0.5), Some(0.25)).unwrap();
        assert_eq!((wide.share, wide.wide_facade_share), (Some(0.5), 0.25));
        assert!(wide.randomize_materials && !wide.randomize_lighting);
        assert_eq!(
            Stock.checked_style(None, None).unwrap(),
            RenderStyle::default()
        );
        for (t, share, w, needle) in [
            (Materials, Some(0.0), None, "`randomize_share`: 0 is"),
            (Materials, Some(1.5), None, "`randomize_share`: 1.5 is"),
            (Materials, Some(f32::NAN), None, "`randomize_share`: NaN is"),
            (Stock, Some(0.5), None, "other than stock"),
            (Materials, None, Some(0.0), "`wide_facades`: 0 is"),
            (Appearance, None, Some(2.0), "`wide_facades`: 2 is"),
            (Stock, None, Some(0.5), "draws materials"),
            (Lighting, None, Some(0.5), "draws materials"),
        ] {
            let e = t.checked_style(share, w).unwrap_err().to_string();
            assert!(e.contains(needle), "{t:?} {share:?} {w:?}: {e}");
        }
        assert!(Randomized.checked_style(None, Some(1.0)).is_ok());
        assert!("sunny".parse::<TrainImages>().is_err());
        // each style switches on exactly its own randomisations
        assert_eq!(TrainImages::Stock.style(None), RenderStyle::default());
        assert_eq!(
            TrainImages::Randomized.style(None),
            RenderStyle::randomized(true)
        );
        let flags = |t: TrainImages| {
            let s = t.style(None);
            (
                s.randomize_appearance,
                s.randomize_lighting,
                s.randomize_materials,
                s.sensor.is_some(),
            )
        };
        assert_eq!(flags(TrainImages::Lighting), (false, true, false, false));
        assert_eq!(flags(TrainImages::Materials), (false, false, true, false));
        assert_eq!(flags(TrainImages::Appearance), (false, true, true, false));
        assert_eq!(flags(TrainImages::Randomized), (true, false, false, true));
    }

    #[test]
    fn scans_alone_are_the_scans_of_whole_frames_without_a_camera() {
        let cfg = BundleConfig::cpu_default(Variant::Unconditional);
        let list = workspace_root().join("scenes/train-v5.txt");
        // stock images, and drawn appearance (which sets the scans' intensities too)
        for style in [RenderStyle::default(), TrainImages::Appearance.style(None)] {
            let whole = render_split_styled(&list, 3, &cfg, &style, &|| {}).unwrap();
            let alone = RenderStyle {
                scan_only: true,
                ..style
            };
            let scans = render_split_styled(&list, 3, &cfg, &alone, &|| {}).unwrap();
            assert_eq!(scans.len(), 3);
            for (k, (w, s)) in whole.iter().zip(&scans).enumerate() {
                assert!(!w.rgb.is_empty() && s.rgb.is_empty(), "frame {k}");
                assert!(s.labels.is_empty() && s.depth_m.is_empty(), "frame {k}");
                assert_eq!(s.camera, blind_camera(&cfg).unwrap());
                assert!(w.range.mask.iter().any(|&m| m), "frame {k}: no returns");
                assert_eq!(w.range.range_m, s.range.range_m, "frame {k}");
                assert_eq!(w.range.intensity, s.range.intensity, "frame {k}");
                assert_eq!(w.range.mask, s.range.mask, "frame {k}");
                assert_eq!(w.range.label, s.range.label, "frame {k}");
                assert_eq!(
                    w.train_example(&cfg).unwrap().x0,
                    s.train_example(&cfg).unwrap().x0
                );
            }
            assert_ne!(scans[0].range.range_m, scans[1].range.range_m);
        }
    }

    #[test]
    fn the_sky_is_exactly_the_pixels_without_depth_and_reads_as_far() {
        let list = workspace_root().join(DEFAULT_SCENES);
        let (path, seed) = split_items(&list, 1).unwrap().remove(0);
        let scene = Scene::generate(&SceneConfig::from_file(&path).unwrap(), seed).unwrap();
        let frame = scene.render_frame(0).unwrap();
        let img = &frame.image;
        let sky: Vec<bool> = img.depth_m.iter().map(|&d| d == 0.0).collect();
        let n_sky = sky.iter().filter(|&&s| s).count();
        // a street scene shows both sky and surfaces
        assert!(
            n_sky > img.depth_m.len() / 20 && n_sky < img.depth_m.len() / 2,
            "{n_sky}"
        );
        // depth 0 is the sky (class 0, nothing hit) and nothing else
        for (i, &s) in sky.iter().enumerate() {
            assert_eq!(s, img.semantic[i] == 0, "pixel {i}");
            assert!(s || img.depth_m[i] > 0.0, "pixel {i}");
        }
        let t = depth_with_sky_at(&img.depth_m, 80.0);
        for (i, (&d, &s)) in img.depth_m.iter().zip(&sky).enumerate() {
            if s {
                assert_eq!(t[i], 80.0);
            } else {
                assert_eq!(t[i].to_bits(), d.to_bits(), "pixel {i}");
            }
        }
    }

    #[test]
    fn each_training_list_has_its_held_out_list_beside_it() {
        for (train, test) in [
            ("scenes/train.txt", "scenes/test.txt"),
            ("scenes/train-v4.txt", "scenes/test-v4.txt"),
            ("scenes/train-v5.txt", "scenes/test-v5.txt"),
            // a list of one's own has no sibling: the shipped held-out list
            ("scenes/mine.txt", "scenes/test.txt"),
            ("scenes/train-v99.txt", "scenes/test.txt"),
        ] {
            assert_eq!(
                test_list_for(&workspace_root(), Path::new(train)),
                Path::new(test),
                "{train}"
            );
        }
        // and the scene files of every held-out list are those of its training list
        for v in ["", "-v2", "-v3", "-v4", "-v5"] {
            let scenes = |kind: &str| -> std::collections::BTreeSet<PathBuf> {
                SceneList::read(&workspace_root().join(format!("scenes/{kind}{v}.txt")))
                    .unwrap()
                    .iter()
                    .map(|(p, _)| p.to_path_buf())
                    .collect()
            };
            assert_eq!(scenes("train"), scenes("test"), "v{v}");
        }
    }

    #[test]
    fn baselines_follow_the_bundles_own_training_list() {
        let mut cfg = BundleConfig::cpu_default(Variant::Full);
        // bundles written before the list was recorded were trained on scenes/train.txt
        cfg.provenance = serde_json::Value::Null;
        assert_eq!(train_split_of(&cfg), Path::new("scenes/train.txt"));
        cfg.provenance = serde_json::json!({ "train_split": "scenes/train-v3.txt" });
        assert_eq!(train_split_of(&cfg), Path::new("scenes/train-v3.txt"));
        let list = workspace_root().join(train_split_of(&cfg));
        // and the list it names is one split_items reads, with every scene file of v3 in turn
        let items = split_items(&list, 6).unwrap();
        let files: std::collections::BTreeSet<_> = items.iter().map(|(p, _)| p.clone()).collect();
        assert_eq!(files.len(), 6, "{items:?}");
    }

    #[test]
    fn a_rendered_frame_is_fitted_to_the_bundle_and_its_rig_to_the_views() {
        let mut cfg = BundleConfig::cpu_default(Variant::Full);
        if let Some(c) = cfg.denoiser.conditioning.as_mut() {
            c.num_views = 3;
        }
        let list = workspace_root().join(DEFAULT_SCENES);
        let frames = render_split(&list, 1, &cfg, &|| {}).unwrap();
        let ex = &frames[0];
        let npx = cfg.image_width * cfg.image_height;
        assert_eq!(
            (ex.rgb.len(), ex.labels.len(), ex.depth_m.len()),
            (3 * npx, npx, npx)
        );
        assert_eq!(
            (ex.camera.width as usize, ex.camera.height as usize),
            (cfg.image_width, cfg.image_height)
        );
        let (rows, cols) = (cfg.denoiser.height(), cfg.denoiser.width());
        assert_eq!(
            (ex.range.rows as usize, ex.range.cols as usize),
            (rows, cols)
        );
        assert!(ex.range.num_valid() > rows * cols / 4);
        // two further cameras, turned by the rig's first yaws, and three views to sample with
        assert_eq!(ex.extra_views.len(), 2);
        assert_eq!(ex.views(3).len(), 3);
        assert_eq!(ex.views(1).len(), 1);
        assert_ne!(
            ex.extra_views[0].camera.cam_from_lidar,
            ex.camera.cam_from_lidar
        );
        // the same list renders the same bytes again
        let again = render_split(&list, 1, &cfg, &|| {}).unwrap();
        assert_eq!(again[0].rgb, ex.rgb);
        assert_eq!(again[0].range.range_m, ex.range.range_m);
        let train = ex.train_example(&cfg).unwrap();
        assert_eq!(train.extra_views.len(), 2);
    }
}
