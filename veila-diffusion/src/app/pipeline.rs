//! The one path from a camera rig to scans in the LiDAR's own frame. Every door (`veila generate`,
//! `veila edit`, `veila demo`, the Python `generate`, `examples/generate.rs`) calls
//! [`ScanPipeline`], so the same images, calibration, bundle and seed give the same scans
//! through each of them.
//!
//! [`ScanPipeline::new`] takes a rig, one or several cameras, each an image at the resolution its
//! calibration describes and that camera (LiDAR frame to pixels; [`super::rig::load_view`] reads
//! both from files), and
//!
//! 1. fits every image to the encoders' input (`image_width x image_height` of the bundle, triangle
//!    filter, the camera rescaled with it);
//! 2. turns the rig into the model's frame: the bundled prior was learnt with the front camera
//!    looking along `+x` (KITTI's LiDAR frame), so a LiDAR frame whose forward axis is another
//!    (nuScenes: `+y`) is turned by quarter turns about `z`, counted from the first camera.
//!
//! The steps themselves live in [`super::rig`], private to the crate: no door can leave one out.
//!
//! [`ScanPipeline::generate`] then samples, turns every range image back into the LiDAR frame (a
//! roll of its columns, exact) and unprojects it: each [`Scan`] is a range image and its points,
//! both in the LiDAR frame of the calibration. [`ScanPipeline::inpaint`] does the same for RePaint
//! edits of a scan given in that frame.
//!
//! ```no_run
//! use std::path::Path;
//!
//! use candle_core::Device;
//! use veila_diffusion::app::{Bundle, GenerateOptions, ScanPipeline, load_view};
//!
//! # fn main() -> veila_diffusion::Result<()> {
//! let bundle = Bundle::from_dir(Path::new("models/default"), &Device::Cpu)?;
//! // KITTI camera 2 or nuScenes CAM_FRONT: the scans come out in that calibration's LiDAR frame
//! let view = load_view(Path::new("image.png"), Path::new("calib.txt"), None)?;
//! let pipeline = ScanPipeline::new(&bundle, &[view.rig_image()])?;
//! let options = GenerateOptions::new(bundle.config.sampler.clone()); // one scan, seed 0
//! let scan = pipeline.generate(&options, |_, _| {})?.remove(0);
//! println!("{} points, {} returns on the grid", scan.points.len(), scan.range.num_valid());
//! # Ok(())
//! # }
//! ```

use veila_data::PointCloud;
use veila_geom::{PinholeCamera, RangeImage};

use super::bundle::Bundle;
use super::generate::{CameraView, GenerateOptions, check_inpainting_input};
use super::rig::{
    PreparedViews, RigImage, RigView, camera_in_model_frame, pixels_to_model_frame, prepare_view,
    prepare_views, quarter_turns_to_model, range_to_lidar_frame, range_to_model_frame, scan_points,
};
use crate::error::Result;
use crate::sampler::RepaintConfig;

/// One generated scan, in the LiDAR frame of the rig's calibration.
#[derive(Debug, Clone)]
pub struct Scan {
    /// The range image on the bundle's grid (range, intensity, returns), turned into the LiDAR
    /// frame: for EXR files and range previews.
    pub range: RangeImage,
    /// Its points, one per return, with intensity.
    pub points: PointCloud,
}

/// A camera rig fitted to a bundle: the views resized to the encoders' input and turned into the
/// model's frame, once; sample from it as often as wanted. See the [module docs](self).
#[derive(Debug, Clone)]
pub struct ScanPipeline<'b> {
    bundle: &'b Bundle,
    /// The resized views, their cameras in the model's frame.
    views: PreparedViews,
    turns: i32,
}

impl<'b> ScanPipeline<'b> {
    /// Fits `rig` to `bundle`. An empty rig is accepted only where the bundle ignores images (an
    /// unconditional bundle); sampling with a conditional one then fails.
    pub fn new(bundle: &'b Bundle, rig: &[RigImage<'_>]) -> Result<Self> {
        let views = rig
            .iter()
            .map(|v| prepare_view(&bundle.config, v.image, v.camera))
            .collect::<Result<PreparedViews>>()?;
        Ok(Self::in_model_frame(
            bundle,
            views,
            rig.first().map(|v| v.camera),
        ))
    }

    /// [`ScanPipeline::new`] for views read from files: an error names the image it is about.
    pub fn from_views(bundle: &'b Bundle, views: &[RigView]) -> Result<Self> {
        let prepared = prepare_views(&bundle.config, views)?;
        Ok(Self::in_model_frame(
            bundle,
            prepared,
            views.first().map(|v| &v.camera),
        ))
    }

    /// Resized views with their cameras turned into the model's frame, counted from the first
    /// camera as it is in the LiDAR frame.
    fn in_model_frame(
        bundle: &'b Bundle,
        mut views: PreparedViews,
        first: Option<&PinholeCamera>,
    ) -> Self {
        let turns = first.map_or(0, quarter_turns_to_model);
        for (_, camera) in &mut views {
            *camera = camera_in_model_frame(camera, turns);
        }
        Self {
            bundle,
            views,
            turns,
        }
    }

    /// The bundle it samples with.
    pub fn bundle(&self) -> &'b Bundle {
        self.bundle
    }

    /// Quarter turns about `z` from the calibration's LiDAR frame into the model's (`0` for
    /// KITTI, `1` for nuScenes); the scans come back in the calibration's frame either way.
    pub fn quarter_turns(&self) -> i32 {
        self.turns
    }

    /// Number of cameras of the rig.
    pub fn num_views(&self) -> usize {
        self.views.len()
    }

    fn camera_views(&self) -> Vec<CameraView<'_>> {
        super::rig::camera_views(&self.views)
    }

    /// A sampled range image of the model's frame as a scan in the LiDAR frame.
    fn scan(&self, model_frame: &RangeImage) -> Result<Scan> {
        let range = range_to_lidar_frame(&self.bundle.config, model_frame, self.turns)?;
        let points = scan_points(&self.bundle.config, &range)?;
        Ok(Scan { range, points })
    }

    /// Draws `options.samples` scans of the rig in one batch (for many, draw
    /// [`GenerateOptions::batches`] one after the other). `on_step(done, total)` is called after
    /// each sampler step.
    pub fn generate(
        &self,
        options: &GenerateOptions,
        on_step: impl FnMut(usize, usize),
    ) -> Result<Vec<Scan>> {
        self.bundle
            .generate(&self.camera_views(), options, on_step)?
            .iter()
            .map(|s| self.scan(s))
            .collect()
    }

    /// Keeps the pixels of `known` (a scan on the bundle's grid, in the LiDAR frame) where `keep`
    /// (`rows * cols`, row-major, same frame) is true and regenerates the rest, consistent with
    /// the kept part and the rig (RePaint; the sampler must be DDPM or DDIM).
    pub fn inpaint(
        &self,
        known: &RangeImage,
        keep: &[bool],
        options: &GenerateOptions,
        repaint: &RepaintConfig,
    ) -> Result<Vec<Scan>> {
        let config = &self.bundle.config;
        let (rows, cols) = self.bundle.grid();
        check_inpainting_input(self.bundle, known, keep)?;
        let known = range_to_model_frame(config, known, self.turns)?;
        let keep = pixels_to_model_frame(config, keep, rows, cols, self.turns)?;
        self.bundle
            .inpaint(&self.camera_views(), &known, &keep, options, repaint)?
            .iter()
            .map(|s| self.scan(s))
            .collect()
    }

    /// A retrieval descriptor of the rig: [`Bundle::image_descriptor`] of each view, in order,
    /// concatenated. Rigs whose descriptors are near by cosine look alike to the model.
    pub fn image_descriptor(&self) -> Result<Vec<f32>> {
        let mut out = Vec::new();
        for v in self.camera_views() {
            out.extend(self.bundle.image_descriptor(v)?);
        }
        Ok(out)
    }
}

#[cfg(test)]
mod tests {
    use candle_core::Device;

    use super::*;
    use crate::MAX_STEPS;

    #[test]
    fn a_doors_sampler_choices_override_the_bundles_sampler() {
        use crate::app::SamplerChoice;
        use crate::{SamplerKind, SamplerName, Spacing};
        let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../models/default");
        let mut bundle = Bundle::from_dir(&dir, &Device::Cpu).unwrap();
        bundle.config.sampler.guidance_scale = 1.5;
        bundle.config.sampler.start_t = Some(0.3);
        let own = bundle.config.sampler.clone();
        assert_eq!(SamplerChoice::default().resolve(&bundle), own);
        // another rule comes with its own spacing; steps, guidance and the start level carry over
        let ddim = SamplerChoice {
            name: Some(SamplerName::Ddim),
            steps: Some(7),
            ..SamplerChoice::default()
        }
        .resolve(&bundle);
        assert_eq!(ddim.kind, SamplerKind::Ddim { eta: 0.0 });
        assert_eq!(ddim.steps, 7);
        assert_eq!(ddim.spacing, SamplerName::Ddim.config(7).spacing);
        assert_eq!((ddim.guidance_scale, ddim.start_t), (1.5, Some(0.3)));
        let each = SamplerChoice {
            name: None,
            spacing: Some(Spacing::Leading),
            steps: Some(3),
            guidance: Some(2.0),
            start_t: Some(0.9),
        };
        let c = each.resolve(&bundle);
        assert_eq!(
            (c.kind, c.spacing, c.steps, c.guidance_scale, c.start_t),
            (own.kind, Spacing::Leading, 3, 2.0, Some(0.9))
        );
        assert!(!each.ignores_guidance(&bundle));
        // an unconditional bundle has no second branch: guidance 1 whatever is asked
        bundle.config.denoiser.conditioning = None;
        assert_eq!(each.resolve(&bundle).guidance_scale, 1.0);
        assert!(each.ignores_guidance(&bundle));
        let one = SamplerChoice {
            guidance: Some(1.0),
            ..each
        };
        assert!(!one.ignores_guidance(&bundle));
    }

    #[test]
    fn options_are_checked_against_the_bundle() {
        let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../models/default");
        let bundled = Bundle::from_dir(&dir, &Device::Cpu).unwrap();
        // the bundled model has a mean network, as a residual's or as a prior's; the checks read
        // only the config, so the same weights serve all three kinds of bundle below
        let mean_net = bundled
            .config
            .mean_net()
            .expect("the bundled model has a mean network");
        let kind = |residual: bool, prior: bool| {
            let mut b = Bundle::from_dir(&dir, &Device::Cpu).unwrap();
            b.config.residual = residual.then(|| crate::app::ResidualConfig {
                mean_net: mean_net.clone(),
                scale: vec![1.0; 3],
            });
            b.config.prior = prior.then(|| crate::app::PriorConfig {
                mean_net: mean_net.clone(),
            });
            b.config.sampler.start_t = None;
            b
        };
        let (residual, prior, direct) = (kind(true, false), kind(false, true), kind(false, false));
        let ok = GenerateOptions::new(bundled.config.sampler.clone());
        ok.check(&bundled).unwrap();
        let ok = GenerateOptions::new(residual.config.sampler.clone());
        let with = |f: &dyn Fn(&mut GenerateOptions)| {
            let mut o = ok.clone();
            f(&mut o);
            o
        };
        for bundle in [&residual, &prior, &direct] {
            ok.check(bundle).unwrap();
            for bad in [
                with(&|o| o.sampler.steps = MAX_STEPS + 1),
                with(&|o| o.sampler.guidance_scale = -1.0),
                with(&|o| o.samples = 0),
                with(&|o| o.residual_weight = 1.5),
                with(&|o| o.residual_weight = f64::NAN),
                with(&|o| o.sampler.start_t = Some(0.0)),
                with(&|o| o.sampler.start_t = Some(1.5)),
            ] {
                assert!(bad.check(bundle).is_err(), "{bad:?}");
            }
        }
        // the mean network alone: 0 steps with either kind of mean network, weight 0 with a
        // residual's
        with(&|o| o.sampler.steps = 0).check(&residual).unwrap();
        with(&|o| o.sampler.steps = 0).check(&prior).unwrap();
        with(&|o| o.residual_weight = 0.0).check(&residual).unwrap();
        let e = with(&|o| o.sampler.steps = 0)
            .check(&direct)
            .unwrap_err()
            .to_string();
        assert!(e.contains("mean network"), "{e}");
        // a prior's mean network starts the draw and is not a residual's
        with(&|o| o.sampler.start_t = Some(0.5))
            .check(&prior)
            .unwrap();
        with(&|o| o.sampler.start_t = Some(1.0))
            .check(&prior)
            .unwrap();
        for bundle in [&prior, &direct] {
            let e = with(&|o| o.residual_weight = 0.5)
                .check(bundle)
                .unwrap_err()
                .to_string();
            assert!(e.contains("residual-diffusion"), "{e}");
        }
        // a start level needs a prior mean network, which a residual bundle's is not
        for bundle in [&residual, &direct] {
            let e = with(&|o| o.sampler.start_t = Some(0.5))
                .check(bundle)
                .unwrap_err()
                .to_string();
            assert!(e.contains("prior"), "{e}");
        }
    }
}
