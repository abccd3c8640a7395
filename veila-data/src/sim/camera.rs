//! Simulated camera images: RGB with sun and sky light, per-pixel semantics and depth, and the
//! KITTI-style calibration of the simulated rig.
//!
//! # Image model
//!
//! One primary ray per sample through the pixel (pixel `(i, j)` is centred at `(u, v) = (i, j)`, the
//! OpenCV / KITTI convention of [`PinholeCamera`]); `n x n` stratified samples per pixel when
//! `samples_per_axis = n`. At a hit with albedo `a`, unit normal `n` (facing the camera), sun direction
//! `l` and sky ambient `E_sky`, the linear radiance is
//!
//! `L = a * (E_sun * max(0, n.l) * V + E_sky * (1 + n_z) / 2)`
//!
//! where `V` is 0 when a shadow ray toward the sun hits anything (1 with shadows off). Rays that miss
//! see a sky gradient from the horizon colour to the zenith colour (by `sqrt` of the ray's
//! elevation; 0.7 times the horizon colour below it) with a sun disc of radiance
//! `20 E_sun (1 - c)^2` (`c` the cloud cover, 0 unless randomised). Pixels are tone-mapped with
//! `1 - exp(-exposure * L)`, encoded sRGB and dithered by at most half an 8-bit level.
//!
//! # Albedo
//!
//! By default `a` is the material's stock albedo, with a small hashed grain on materials that have
//! one (asphalt, grass), and `l`, `E_sun`, `E_sky` and the sky come from
//! [`LightingConfig`](super::LightingConfig). With
//! [`AppearanceConfig::randomize`](super::AppearanceConfig) the scene draws its sun (elevation,
//! azimuth, black-body colour temperature), sky (clear blue to overcast grey: cloud cover `c`
//! scales the sun's irradiance by `1 - 0.85 c` and moves the ambient toward a brighter grey),
//! class palettes and texture styles from its seed, and `a` becomes a procedural texture of the
//! surface's class evaluated at the world hit point (so it sticks to the surface when the camera
//! moves): asphalt grain, patches and cracks on road and parking; slabs or pavers with joints on
//! sidewalks; brick, panel or plaster walls; varying reflections on windows; leaf-scale noise on
//! vegetation; grass with soil patches on terrain; planks on fences; a paint per vehicle instance.
//! Every colour gets a per-surface / per-instance HSV jitter; every albedo stays in `[0, 1]`
//! (linear). Textures are band-limited to the sample's footprint on the surface (`t * angle
//! between neighbouring samples / sqrt(cos incidence)`): detail finer than the footprint fades to
//! its mean. Only the camera's albedo and light change, never geometry, semantics, depth or the
//! LiDAR.
//!
//! Semantics and depth come from the ray through the pixel centre: the hit surface's SemanticKITTI raw
//! id (0 for sky) and `z` of the hit point in the camera frame of [`PinholeCamera::cam_from_lidar`]
//! (metres; **0 for sky**, the KITTI depth convention for "no depth").

use glam::{Affine3A, Mat3, Vec3};
use rayon::prelude::*;
use veila_geom::PinholeCamera;

use super::config::CameraConfig;
use super::frame::SceneSnapshot;
use super::hash::{hash_unit, splitmix};
use super::raycast::Hit;
use crate::{Error, Result};

/// A rendered camera frame.
#[derive(Debug, Clone, PartialEq)]
pub struct SimImage {
    /// Width, pixels.
    pub width: u32,
    /// Height, pixels.
    pub height: u32,
    /// 8-bit sRGB, row-major, 3 bytes per pixel.
    pub rgb: Vec<u8>,
    /// Depth (`z` in the camera frame), metres; 0 where the pixel sees sky.
    pub depth_m: Vec<f32>,
    /// SemanticKITTI raw class id per pixel; 0 (unlabelled) for sky.
    pub semantic: Vec<u16>,
    /// Instance id per pixel (0 for stuff and sky).
    pub instance: Vec<u16>,
}

impl SimImage {
    /// The RGB buffer as an [`image::RgbImage`]; an error if the buffer does not hold
    /// `width x height x 3` bytes.
    pub fn to_rgb_image(&self) -> Result<image::RgbImage> {
        image::RgbImage::from_raw(self.width, self.height, self.rgb.clone()).ok_or_else(|| {
            Error::Mismatch {
                context: "simulated image".into(),
                message: format!(
                    "{} RGB bytes for a {}x{} image",
                    self.rgb.len(),
                    self.width,
                    self.height
                ),
            }
        })
    }
}

/// Render quality knobs.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct CameraRenderOptions {
    /// `n` for `n x n` samples per pixel (anti-aliasing), at least 1.
    pub samples_per_axis: u32,
    /// Cast shadow rays toward the sun.
    pub shadows: bool,
}

impl Default for CameraRenderOptions {
    fn default() -> Self {
        CameraRenderOptions {
            samples_per_axis: 1,
            shadows: true,
        }
    }
}

impl From<&CameraConfig> for CameraRenderOptions {
    fn from(c: &CameraConfig) -> Self {
        CameraRenderOptions {
            samples_per_axis: c.samples_per_axis,
            shadows: c.shadows,
        }
    }
}

/// KITTI-format calibration of the simulated rig (all matrices row-major).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SimCalib {
    /// `P0..P3`: rectified projection matrices of cameras 0..3 (`P_i = K [I | t_i]`).
    pub p: [[[f32; 4]; 3]; 4],
    /// `R0_rect` (identity: the simulated cameras are already rectified).
    pub r0_rect: [[f32; 3]; 3],
    /// `Tr_velo_to_cam`: LiDAR to camera 0.
    pub tr_velo_to_cam: [[f32; 4]; 3],
    /// `Tr_imu_to_velo` (KITTI's nominal offset: the IMU 0.81 m behind, 0.32 m left of and 0.80 m
    /// below the LiDAR).
    pub tr_imu_to_velo: [[f32; 4]; 3],
    /// Image width, pixels.
    pub width: u32,
    /// Image height, pixels.
    pub height: u32,
}

impl SimCalib {
    /// The calibration of a camera configuration.
    ///
    /// Camera 0 sits at `(ahead_m, 0, up_m)` in the LiDAR frame, looking along the LiDAR's x axis
    /// pitched down by `pitch_down_deg`; cameras 1, 2, 3 are offset along camera 0's x axis by
    /// `baseline_m` (right), `-cam2_left_m` (left) and `baseline_m - cam2_left_m`, as in KITTI.
    pub fn from_config(c: &CameraConfig) -> Self {
        let (s, co) = c.pitch_down_deg.to_radians().sin_cos();
        // rows of R (camera from LiDAR): axes swap (x right = -y, y down = -z, z forward = x), then pitch
        let axes = [[0.0f32, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]];
        let pitch = [[1.0f32, 0.0, 0.0], [0.0, co, -s], [0.0, s, co]];
        let mut r = [[0.0f32; 3]; 3];
        for i in 0..3 {
            for j in 0..3 {
                r[i][j] = (0..3).map(|k| pitch[i][k] * axes[k][j]).sum();
            }
        }
        let centre = [c.ahead_m, 0.0, c.up_m];
        let mut tr = [[0.0f32; 4]; 3];
        for i in 0..3 {
            tr[i][..3].copy_from_slice(&r[i]);
            tr[i][3] = -(0..3).map(|k| r[i][k] * centre[k]).sum::<f32>();
        }
        // P_i = K [I | t_i], t_i = -(camera centre in camera-0 coordinates)
        let p_of = |cx_offset_m: f32| -> [[f32; 4]; 3] {
            let tx = -cx_offset_m;
            [
                [c.fx, 0.0, c.cx, c.fx * tx],
                [0.0, c.fy, c.cy, 0.0],
                [0.0, 0.0, 1.0, 0.0],
            ]
        };
        SimCalib {
            p: [
                p_of(0.0),
                p_of(c.baseline_m),
                p_of(-c.cam2_left_m),
                p_of(c.baseline_m - c.cam2_left_m),
            ],
            r0_rect: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
            tr_velo_to_cam: tr,
            tr_imu_to_velo: [
                [1.0, 0.0, 0.0, -0.81],
                [0.0, 1.0, 0.0, 0.32],
                [0.0, 0.0, 1.0, -0.8],
            ],
            width: c.width,
            height: c.height,
        }
    }

    /// The `image_2` camera (`K = P2`, `T = R0_rect Tr_velo_to_cam`).
    pub fn camera(&self) -> Result<PinholeCamera> {
        let r0 = Mat3::from_cols_array_2d(&self.r0_rect).transpose();
        Ok(PinholeCamera::from_kitti(
            self.p[2],
            r0,
            self.tr_velo_to_cam,
            self.width,
            self.height,
        )?)
    }

    /// `Tr = R0_rect Tr_velo_to_cam`: LiDAR to rectified camera 0, as a rigid transform.
    pub fn rect_cam0_from_lidar(&self) -> Affine3A {
        let r0 = Mat3::from_cols_array_2d(&self.r0_rect).transpose();
        let t = &self.tr_velo_to_cam;
        let rot = Mat3::from_cols_array_2d(&[
            [t[0][0], t[1][0], t[2][0]],
            [t[0][1], t[1][1], t[2][1]],
            [t[0][2], t[1][2], t[2][2]],
        ]);
        Affine3A::from_mat3_translation(r0 * rot, r0 * Vec3::new(t[0][3], t[1][3], t[2][3]))
    }

    /// The calibration as KITTI odometry text (`sequences/NN/calib.txt`: `P0..P3` and
    /// `Tr = R0_rect Tr_velo_to_cam`).
    pub fn to_odometry_text(&self) -> String {
        let tr = self.rect_cam0_from_lidar();
        let (m, t) = (tr.matrix3, tr.translation);
        let rows = [
            [m.x_axis.x, m.y_axis.x, m.z_axis.x, t.x],
            [m.x_axis.y, m.y_axis.y, m.z_axis.y, t.y],
            [m.x_axis.z, m.y_axis.z, m.z_axis.z, t.z],
        ];
        let mut s = String::new();
        for (key, vals) in (0..4)
            .map(|i| {
                (
                    format!("P{i}"),
                    self.p[i].iter().flatten().copied().collect::<Vec<_>>(),
                )
            })
            .chain(std::iter::once((
                "Tr".to_string(),
                rows.iter().flatten().copied().collect(),
            )))
        {
            s.push_str(&key);
            s.push(':');
            for v in vals {
                s.push_str(&format!(" {v:.12e}"));
            }
            s.push('\n');
        }
        s
    }

    /// The calibration as KITTI object-benchmark text (`calib/NNNNNN.txt`).
    pub fn to_kitti_text(&self) -> String {
        let mut s = String::new();
        let mut line = |key: &str, vals: &mut dyn Iterator<Item = f32>| {
            s.push_str(key);
            s.push(':');
            for v in vals {
                s.push_str(&format!(" {:.12e}", v));
            }
            s.push('\n');
        };
        for (i, p) in self.p.iter().enumerate() {
            line(&format!("P{i}"), &mut p.iter().flatten().copied());
        }
        line("R0_rect", &mut self.r0_rect.iter().flatten().copied());
        line(
            "Tr_velo_to_cam",
            &mut self.tr_velo_to_cam.iter().flatten().copied(),
        );
        line(
            "Tr_imu_to_velo",
            &mut self.tr_imu_to_velo.iter().flatten().copied(),
        );
        s
    }
}

/// Pixel-to-ray geometry of a pinhole camera in the LiDAR frame.
#[derive(Debug, Clone, Copy)]
pub(crate) struct CameraRays {
    /// Inverse of the 3x3 part of `K T`.
    a_inv: Mat3,
    /// Projection centre in the LiDAR frame.
    pub(crate) centre_lidar: Vec3,
    /// Third row of `T` (depth = `row_z . p + t_z`).
    row_z: Vec3,
    t_z: f32,
}

impl CameraRays {
    pub(crate) fn new(camera: &PinholeCamera) -> Result<Self> {
        camera.validate()?;
        let m = camera.image_from_lidar();
        let a = Mat3::from_mat4(m);
        if a.determinant().abs() < 1e-12 {
            return Err(Error::Invalid {
                what: "camera".into(),
                message: "K T is singular".into(),
            });
        }
        let a_inv = a.inverse();
        let b = m.w_axis.truncate();
        let centre_lidar = -(a_inv * b);
        let t = camera.cam_from_lidar;
        let row_z = Vec3::new(t.x_axis.z, t.y_axis.z, t.z_axis.z);
        Ok(CameraRays {
            a_inv,
            centre_lidar,
            row_z,
            t_z: t.w_axis.z,
        })
    }

    /// Unit ray direction (LiDAR frame) through image point `(u, v)`.
    pub(crate) fn dir(&self, u: f32, v: f32) -> Vec3 {
        (self.a_inv * Vec3::new(u, v, 1.0)).normalize()
    }

    /// Camera-frame depth of a LiDAR-frame point.
    pub(crate) fn depth(&self, p_lidar: Vec3) -> f32 {
        self.row_z.dot(p_lidar) + self.t_z
    }
}

fn cell_noise(p: Vec3, scale: f32) -> f32 {
    let q = (p * scale).floor();
    let key = (q.x as i64 as u64).wrapping_mul(0x9E37_79B9)
        ^ (q.y as i64 as u64).wrapping_mul(0x85EB_CA6B_0000_0001)
        ^ (q.z as i64 as u64).wrapping_mul(0xC2B2_AE35);
    (splitmix(key) >> 40) as f32 / (1u64 << 24) as f32
}

/// One rendered pixel: sRGB, depth, class, instance.
type PixelOut = ([u8; 3], f32, u16, u16);

struct Shading {
    sun_dir: Vec3,
    sun: Vec3,
    /// Radiance added inside the sun disc.
    sun_disc: Vec3,
    /// Angle between neighbouring pixels' (or samples') rays, radians: the texture footprint.
    sample_angle: f32,
    ambient: Vec3,
    zenith: Vec3,
    horizon: Vec3,
    exposure: f32,
    shadows: bool,
}

impl SceneSnapshot {
    fn shading(&self, shadows: bool, sample_angle: f32) -> Shading {
        let l = &self.lighting;
        let (az, el) = (
            l.sun_azimuth_deg.to_radians(),
            l.sun_elevation_deg.to_radians(),
        );
        let sun = Vec3::from(l.sun_rgb);
        // clouds hide the disc (the stock lighting has none)
        let clear = (1.0 - self.overcast).powi(2);
        Shading {
            sun_dir: Vec3::new(el.cos() * az.cos(), el.cos() * az.sin(), el.sin()),
            sun,
            sun_disc: sun * 20.0 * clear,
            sample_angle,
            ambient: Vec3::from(l.sky_ambient_rgb),
            zenith: Vec3::from(l.sky_zenith_rgb),
            horizon: Vec3::from(l.sky_horizon_rgb),
            exposure: l.exposure,
            shadows,
        }
    }

    fn radiance(&self, sh: &Shading, origin: Vec3, dir: Vec3, hit: Option<&Hit>) -> Vec3 {
        let Some(hit) = hit else {
            let e = dir.z;
            let mut sky = if e >= 0.0 {
                sh.horizon.lerp(sh.zenith, e.sqrt())
            } else {
                sh.horizon * 0.7
            };
            if dir.dot(sh.sun_dir) > 0.99995 {
                sky += sh.sun_disc;
            }
            return sky;
        };
        let p = origin + dir * hit.t;
        let mat = hit.surface.material;
        let n = hit.normal;
        let albedo = match &self.appearance {
            Some(a) => {
                // the sample's footprint on the surface: its width across the ray times the
                // geometric mean of the stretch along the surface (1 and 1 / cos incidence)
                let cos_i = n.dot(dir).abs().max(0.02);
                a.albedo(&hit.surface, p, n, hit.t * sh.sample_angle / cos_i.sqrt())
            }
            None => {
                let mut albedo = Vec3::from(mat.albedo);
                if mat.grain > 0.0 {
                    let g = 0.6 * (cell_noise(p, 4.0) - 0.5) + 0.4 * (cell_noise(p, 23.0) - 0.5);
                    albedo *= 1.0 + mat.grain * g;
                }
                albedo
            }
        };
        let ndotl = n.dot(sh.sun_dir);
        let mut direct = Vec3::ZERO;
        if ndotl > 0.0 && sh.sun_dir.z > 0.0 {
            let lit = !sh.shadows || {
                let eps = 2e-3 + 1e-4 * hit.t;
                !self.accel.occluded(p + n * eps, sh.sun_dir, 0.0, 1.0e4)
            };
            if lit {
                direct = sh.sun * ndotl;
            }
        }
        albedo * (direct + sh.ambient * (0.5 + 0.5 * n.z))
    }

    /// Render `camera` (its `cam_from_lidar` relative to this snapshot's LiDAR pose).
    pub fn render_camera(
        &self,
        camera: &PinholeCamera,
        opts: &CameraRenderOptions,
    ) -> Result<SimImage> {
        self.render_camera_at(camera, opts, self.world_from_lidar)
    }

    /// Render `camera` with the LiDAR at `world_from_lidar`.
    pub fn render_camera_at(
        &self,
        camera: &PinholeCamera,
        opts: &CameraRenderOptions,
        world_from_lidar: Affine3A,
    ) -> Result<SimImage> {
        if !(1..=16).contains(&opts.samples_per_axis) {
            return Err(Error::Invalid {
                what: "camera samples_per_axis".into(),
                message: format!("{} not in 1..=16", opts.samples_per_axis),
            });
        }
        let rays = CameraRays::new(camera)?;
        let (w, h) = (camera.width, camera.height);
        let n = opts.samples_per_axis;
        let (uc, vc) = (w as f32 / 2.0, h as f32 / 2.0);
        let sample_angle = rays.dir(uc, vc).angle_between(rays.dir(uc + 1.0, vc)) / n as f32;
        let sh = self.shading(opts.shadows, sample_angle);
        let origin_w = world_from_lidar.transform_point3(rays.centre_lidar);
        let rows: Vec<Vec<PixelOut>> = (0..h)
            .into_par_iter()
            .map(|row| {
                (0..w)
                    .map(|col| {
                        let (u, v) = (col as f32, row as f32);
                        let dir_l = rays.dir(u, v);
                        let dir_w = world_from_lidar.transform_vector3(dir_l).normalize();
                        let hit = self.accel.closest_hit(origin_w, dir_w, 0.0, f32::INFINITY);
                        let (depth, sem, inst) = match &hit {
                            Some(hh) => {
                                let p_l = rays.centre_lidar + dir_l * hh.t;
                                (
                                    rays.depth(p_l).max(0.0),
                                    hh.surface.material.class,
                                    hh.surface.instance,
                                )
                            }
                            None => (0.0, 0, 0),
                        };
                        let mut acc = Vec3::ZERO;
                        if n == 1 {
                            acc = self.radiance(&sh, origin_w, dir_w, hit.as_ref());
                        } else {
                            for sy in 0..n {
                                for sx in 0..n {
                                    let du = (sx as f32 + 0.5) / n as f32 - 0.5;
                                    let dv = (sy as f32 + 0.5) / n as f32 - 0.5;
                                    let d = world_from_lidar
                                        .transform_vector3(rays.dir(u + du, v + dv))
                                        .normalize();
                                    let hs =
                                        self.accel.closest_hit(origin_w, d, 0.0, f32::INFINITY);
                                    acc += self.radiance(&sh, origin_w, d, hs.as_ref());
                                }
                            }
                            acc /= (n * n) as f32;
                        }
                        // a faint per-pixel dither breaks banding in the sky gradient
                        let dither =
                            (hash_unit(0x5157, u64::from(row) * u64::from(w) + u64::from(col), 7)
                                - 0.5)
                                / 255.0;
                        let px = (Vec3::ONE - (-acc * sh.exposure).exp())
                            .to_array()
                            .map(|c| {
                                ((crate::srgb::linear_to_srgb(c.clamp(0.0, 1.0)) + dither) * 255.0)
                                    .round()
                                    .clamp(0.0, 255.0) as u8
                            });
                        (px, depth, sem, inst)
                    })
                    .collect()
            })
            .collect();
        let npx = w as usize * h as usize;
        let mut img = SimImage {
            width: w,
            height: h,
            rgb: Vec::with_capacity(npx * 3),
            depth_m: Vec::with_capacity(npx),
            semantic: Vec::with_capacity(npx),
            instance: Vec::with_capacity(npx),
        };
        for (px, d, s, i) in rows.into_iter().flatten() {
            img.rgb.extend_from_slice(&px);
            img.depth_m.push(d);
            img.semantic.push(s);
            img.instance.push(i);
        }
        Ok(img)
    }
}
