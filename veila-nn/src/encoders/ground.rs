//! The flat-ground prior as an extra input channel of the small CNN encoders (issue 18, item 4:
//! geometry that transfers).
//!
//! Where flat ground would be in an image follows from the calibration alone: the camera's
//! intrinsics, its pose relative to the LiDAR (`cam_from_lidar`) and the LiDAR's height above the
//! ground ([`veila_geom::flat_ground_depth_map_m`]). On real data the calibration is exact, while
//! the pixels look different from the simulator's; a network told where the ground plane lies
//! need not infer the camera's height and pitch from pixels.
//!
//! **The encoding.** The channel holds the scaled *inverse* flat-ground depth,
//! `min(inverse_depth_scale_m / depth_m, GROUND_PRIOR_MAX)`, and `0` where the pixel's ray misses
//! the ground (at and above the horizon). Inverse depth is well conditioned where depth is not: it
//! falls smoothly to 0 at the horizon (depth there goes to infinity) and is continuous across it,
//! so the channel has no jump and no unbounded value; it is proportional to the ray's depression
//! below the horizon for a level camera. With the default scale of 4 m a KITTI image's bottom rows
//! (ground about 5-6 m ahead) read about 0.7, the same order as the ImageNet-normalised colours.
//! The cap only matters for cameras that look steeply down (ground nearer than 1 m).
//!
//! ```
//! use glam::{Mat4, Vec4};
//! use veila_geom::PinholeCamera;
//! use veila_nn::encoders::ground::GroundPrior;
//!
//! let axes = Mat4::from_cols(
//!     Vec4::new(0., 0., 1., 0.),
//!     Vec4::new(-1., 0., 0., 0.),
//!     Vec4::new(0., -1., 0., 0.),
//!     Vec4::W,
//! );
//! let k = [[100.0, 0.0, 32.0, 0.0], [0.0, 100.0, 24.0, 0.0], [0.0, 0.0, 1.0, 0.0]];
//! let cam = PinholeCamera::new(k, axes, 64, 48)?;
//! let prior = GroundPrior { lidar_height_m: 1.5, inverse_depth_scale_m: 4.0 };
//! let plane = prior.channel(&cam)?;
//! // row 34 sees the ground at 100 * 1.5 / 10 = 15 m: 4 / 15
//! assert!((plane[34 * 64 + 5] - 4.0 / 15.0).abs() < 1e-6);
//! assert_eq!(plane[10 * 64 + 5], 0.0); // above the horizon
//! # Ok::<(), veila_nn::Error>(())
//! ```

use candle_core::{Device, Tensor};
use veila_geom::PinholeCamera;

/// Largest value of the channel (flat ground nearer than `inverse_depth_scale_m / 4`).
pub const GROUND_PRIOR_MAX: f32 = 4.0;

/// The flat-ground prior channel of a small CNN ([`super::small_cnn::SmallCnnConfig::ground_prior`]).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct GroundPrior {
    /// Height of the LiDAR above the flat ground, metres: the plane is `z = -lidar_height_m` in
    /// the LiDAR frame (KITTI's HDL-64E and the simulator's default rig: 1.73).
    pub lidar_height_m: f32,
    /// The channel is `inverse_depth_scale_m / depth_m` (capped at [`GROUND_PRIOR_MAX`]).
    pub inverse_depth_scale_m: f32,
}

impl Default for GroundPrior {
    fn default() -> Self {
        Self {
            lidar_height_m: 1.73,
            inverse_depth_scale_m: 4.0,
        }
    }
}

impl GroundPrior {
    /// Checks both values are finite and positive.
    pub fn validate(&self) -> crate::Result<()> {
        let (h, s) = (self.lidar_height_m, self.inverse_depth_scale_m);
        if !(h.is_finite() && h > 0.0 && s.is_finite() && s > 0.0) {
            config_bail!(
                "GroundPrior: lidar_height_m and inverse_depth_scale_m must be finite and positive, got {h} and {s}"
            );
        }
        Ok(())
    }

    /// The channel for `camera`'s image, row-major `height x width` of the camera.
    ///
    /// # Errors
    /// An invalid prior or camera.
    pub fn channel(&self, camera: &PinholeCamera) -> crate::Result<Vec<f32>> {
        self.validate()?;
        camera
            .validate()
            .map_err(|e| crate::Error::Input(format!("ground prior: {e}")))?;
        let depth = veila_geom::flat_ground_depth_map_m(camera, -self.lidar_height_m);
        let s = self.inverse_depth_scale_m;
        Ok(depth
            .into_iter()
            .map(|d| {
                if d > 0.0 {
                    (s / d).min(GROUND_PRIOR_MAX)
                } else {
                    0.0
                }
            })
            .collect())
    }

    /// [`Self::channel`] as a `[1, 1, height, width]` tensor; a camera of another size is scaled
    /// to `width x height` first ([`PinholeCamera::resized`]).
    pub fn tensor(
        &self,
        camera: &PinholeCamera,
        height: usize,
        width: usize,
        device: &Device,
    ) -> crate::Result<Tensor> {
        let resized;
        let camera = if (camera.width as usize, camera.height as usize) == (width, height) {
            camera
        } else {
            resized = camera.resized(width as u32, height as u32).ok_or_else(|| {
                crate::Error::Input(format!(
                    "ground prior: image size {width}x{height} has a zero dimension"
                ))
            })?;
            &resized
        };
        let plane = self.channel(camera)?;
        Ok(Tensor::from_vec(plane, (1, 1, height, width), device)?)
    }
}

#[cfg(test)]
mod tests {
    use glam::{Mat4, Vec4};

    use super::*;

    fn camera(w: u32, h: u32) -> PinholeCamera {
        let axes = Mat4::from_cols(
            Vec4::new(0., 0., 1., 0.),
            Vec4::new(-1., 0., 0., 0.),
            Vec4::new(0., -1., 0., 0.),
            Vec4::W,
        );
        let (fx, cx, cy) = (w as f32 * 0.6, w as f32 / 2.0 - 0.5, h as f32 / 2.0 - 0.5);
        let k = [[fx, 0.0, cx, 0.0], [0.0, fx, cy, 0.0], [0.0, 0.0, 1.0, 0.0]];
        PinholeCamera::new(k, axes, w, h).unwrap()
    }

    #[test]
    fn channel_is_scaled_inverse_depth_and_zero_above_the_horizon() {
        let cam = camera(40, 20);
        let prior = GroundPrior {
            lidar_height_m: 2.0,
            inverse_depth_scale_m: 3.0,
        };
        let ch = prior.channel(&cam).unwrap();
        let (f, cy) = (24.0f32, 9.5f32);
        for v in 0..20usize {
            for u in 0..40usize {
                let got = ch[v * 40 + u];
                let dv = v as f32 - cy;
                // closed form: depth f h / (v - cy), so the channel is 3 (v - cy) / (f h)
                let want = if dv > 0.0 {
                    (3.0 * dv / (f * 2.0)).min(GROUND_PRIOR_MAX)
                } else {
                    0.0
                };
                assert!((got - want).abs() < 1e-5, "({u}, {v}): {got} vs {want}");
            }
        }
        // bounded and increasing downwards
        assert!(ch.iter().all(|&x| (0.0..=GROUND_PRIOR_MAX).contains(&x)));
        assert!(ch[19 * 40] > ch[15 * 40] && ch[15 * 40] > ch[11 * 40]);
    }

    fn small_cnn(prior: Option<GroundPrior>) -> crate::encoders::small_cnn::SmallCnn {
        use crate::encoders::small_cnn::{SmallCnn, SmallCnnConfig};
        let cfg = SmallCnnConfig {
            channels: [8, 8, 8, 8],
            head_channels: 8,
            semantic_head: false,
            ground_prior: prior,
            ..SmallCnnConfig::default()
        };
        let vm = candle_nn::VarMap::new();
        SmallCnn::new(
            &cfg,
            crate::seeded_var_builder(&vm, 5, candle_core::DType::F32, &Device::Cpu),
        )
        .unwrap()
    }

    #[test]
    fn a_small_cnn_with_the_prior_takes_four_channels_and_needs_the_camera() {
        use crate::encoders::{Normalization, rgb8_to_tensor};
        let dev = Device::Cpu;
        let (h, w) = (20usize, 40usize);
        let rgb: Vec<u8> = (0..h * w * 3).map(|i| (i * 37 % 251) as u8).collect();
        let cam = camera(w as u32, h as u32);
        // off: the input is exactly the normalised colours, with or without a camera
        let off = small_cnn(None);
        assert_eq!(off.config().input_channels(), 3);
        let want = rgb8_to_tensor(&rgb, h, w, &Normalization::IMAGENET, &dev)
            .unwrap()
            .flatten_all()
            .unwrap()
            .to_vec1::<f32>()
            .unwrap();
        for c in [None, Some(&cam)] {
            let got = off.config().input_tensor(&rgb, h, w, c, &dev).unwrap();
            assert_eq!(got.flatten_all().unwrap().to_vec1::<f32>().unwrap(), want);
        }
        // on: colours then the channel of this camera
        let on = small_cnn(Some(GroundPrior::default()));
        assert_eq!(on.config().input_channels(), 4);
        let x = on
            .config()
            .input_tensor(&rgb, h, w, Some(&cam), &dev)
            .unwrap();
        assert_eq!(x.dims(), &[1, 4, h, w]);
        let v = x.flatten_all().unwrap().to_vec1::<f32>().unwrap();
        assert_eq!(&v[..3 * h * w], &want[..]);
        assert_eq!(
            &v[3 * h * w..],
            &GroundPrior::default().channel(&cam).unwrap()[..]
        );
        let err = on
            .config()
            .input_tensor(&rgb, h, w, None, &dev)
            .unwrap_err()
            .to_string();
        assert!(err.contains("camera"), "{err}");
        // the network reads the channel: another camera height changes the predicted depth
        let d1 = on.predict_maps(&x).unwrap()[0].depth_m.clone().unwrap();
        let raised = PinholeCamera {
            cam_from_lidar: glam::Mat4::from_translation(glam::Vec3::new(0.0, 0.7, 0.0))
                * cam.cam_from_lidar,
            ..cam
        };
        let x2 = on
            .config()
            .input_tensor(&rgb, h, w, Some(&raised), &dev)
            .unwrap();
        let d2 = on.predict_maps(&x2).unwrap()[0].depth_m.clone().unwrap();
        assert_ne!(d1, d2);
        // a 3-channel tensor is refused by the 4-channel network, and the other way round
        let rgb_only = off.config().input_tensor(&rgb, h, w, None, &dev).unwrap();
        assert!(on.predict_maps(&rgb_only).is_err());
        assert!(off.predict_maps(&x).is_err());
    }

    #[test]
    fn configs_without_the_field_read_as_off_and_write_it_only_when_on() {
        use crate::encoders::small_cnn::SmallCnnConfig;
        let off = SmallCnnConfig::default();
        let json = serde_json::to_value(&off).unwrap();
        assert!(json.get("ground_prior").is_none(), "{json}");
        let back: SmallCnnConfig = serde_json::from_value(json).unwrap();
        assert_eq!(back, off);
        let on = SmallCnnConfig {
            ground_prior: Some(GroundPrior::default()),
            ..off
        };
        let json = serde_json::to_value(&on).unwrap();
        let h = json["ground_prior"]["lidar_height_m"].as_f64().unwrap();
        assert_eq!(h as f32, 1.73);
        assert_eq!(serde_json::from_value::<SmallCnnConfig>(json).unwrap(), on);
        let bad = SmallCnnConfig {
            ground_prior: Some(GroundPrior {
                inverse_depth_scale_m: 0.0,
                ..GroundPrior::default()
            }),
            ..SmallCnnConfig::default()
        };
        assert!(bad.validate().is_err());
    }

    #[test]
    fn tensor_scales_a_camera_of_another_size_and_checks_the_prior() {
        let dev = Device::Cpu;
        let prior = GroundPrior::default();
        let big = camera(80, 40);
        let t = prior.tensor(&big, 20, 40, &dev).unwrap();
        assert_eq!(t.dims(), &[1, 1, 20, 40]);
        let want = prior.channel(&big.resized(40, 20).unwrap()).unwrap();
        assert_eq!(t.flatten_all().unwrap().to_vec1::<f32>().unwrap(), want);
        let bad = GroundPrior {
            lidar_height_m: f32::NAN,
            ..prior
        };
        assert!(bad.channel(&big).is_err());
        assert!(prior.tensor(&big, 0, 40, &dev).is_err());
    }
}
