//! Pinhole cameras with a 3x4 intrinsic matrix `K` and a 4x4 extrinsic `T` (camera from LiDAR),
//! equation 2 of the paper: `[u, v, 1]^T = 1/w K T [p, 1]^T`.
//!
//! Pixel convention (OpenCV / KITTI): the centre of pixel `(i, j)` sits at `(u, v) = (i, j)`; the image
//! covers `[-0.5, W - 0.5) x [-0.5, H - 0.5)`. [`ImagePoint::pixel`] rounds to the nearest pixel.

use glam::{Mat3, Mat4, Vec3, Vec4};

use crate::{GeomError, RayTable};

/// A point projected into the image.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ImagePoint {
    /// Horizontal pixel coordinate.
    pub u_px: f32,
    /// Vertical pixel coordinate.
    pub v_px: f32,
    /// Depth: `z` of the point in the camera frame, metres.
    pub depth_m: f32,
}

impl ImagePoint {
    /// The nearest pixel `(col, row)`; `None` if outside `width x height`.
    pub fn pixel(&self, width: u32, height: u32) -> Option<(u32, u32)> {
        let c = (self.u_px + 0.5).floor();
        let r = (self.v_px + 0.5).floor();
        (c >= 0.0 && r >= 0.0 && c < width as f32 && r < height as f32)
            .then_some((c as u32, r as u32))
    }
}

/// A pinhole camera rigidly attached to the LiDAR.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PinholeCamera {
    /// `K` as a 4x4 matrix whose last row is `(0, 0, 0, 1)` (the 3x4 intrinsic / projection matrix
    /// padded). KITTI's `P2` carries a translation in its fourth column; it is kept.
    pub intrinsics: Mat4,
    /// `T`: camera frame from LiDAR frame.
    pub cam_from_lidar: Mat4,
    /// Image width in pixels.
    pub width: u32,
    /// Image height in pixels.
    pub height: u32,
    /// Points whose projective depth `w` is at or below this (metres) do not project.
    pub near_m: f32,
}

fn rows3x4(m: [[f32; 4]; 3]) -> Mat4 {
    Mat4::from_cols_array_2d(&[
        [m[0][0], m[1][0], m[2][0], 0.0],
        [m[0][1], m[1][1], m[2][1], 0.0],
        [m[0][2], m[1][2], m[2][2], 0.0],
        [m[0][3], m[1][3], m[2][3], 1.0],
    ])
}

/// The farthest a calibration file may put its camera from the LiDAR, metres: the length of the
/// translation of `T` (camera from LiDAR), and that of the offset a KITTI projection matrix carries
/// in its fourth column (`K⁻¹ p₄`, the stereo baseline: 0.06 m for `P2`), each on its own. Real
/// rigs mount camera and LiDAR within a few metres of each other (KITTI: 0.3 m, nuScenes: 1.8 m);
/// 100 m is far beyond any vehicle and well inside what `f32` holds exactly enough to project.
pub const MAX_CAMERA_OFFSET_M: f32 = 100.0;

/// How far the third row of a calibration's 3x3 `K` may be from `(0, 0, 1)` (the row that makes
/// the projective depth `w` the camera-frame depth in metres; files print it exactly).
const K_ROW3_TOLERANCE: f32 = 1e-3;

impl PinholeCamera {
    /// Default near plane, metres.
    pub const DEFAULT_NEAR_M: f32 = 0.1;

    /// The camera of these matrices with the default near plane, unchecked: what [`Self::new`] and
    /// [`Self::from_calibration`] build before their checks.
    fn assemble(
        intrinsics_3x4: [[f32; 4]; 3],
        cam_from_lidar: Mat4,
        width: u32,
        height: u32,
    ) -> Self {
        PinholeCamera {
            intrinsics: rows3x4(intrinsics_3x4),
            cam_from_lidar,
            width,
            height,
            near_m: Self::DEFAULT_NEAR_M,
        }
    }

    /// A camera from calibration data (a file, a shard, an array handed in by a user): a
    /// row-major 3x4 `K` and `T = cam_from_lidar` for a `width x height` image, checked by
    /// [`Self::check_calibration`] first (so a bad value is named as what it is), then by
    /// [`Self::validate`]. The KITTI and nuScenes constructors build on it.
    pub fn from_calibration(
        intrinsics_3x4: [[f32; 4]; 3],
        cam_from_lidar: Mat4,
        width: u32,
        height: u32,
    ) -> Result<Self, GeomError> {
        let cam = Self::assemble(intrinsics_3x4, cam_from_lidar, width, height);
        cam.check_calibration()?;
        cam.validate()?;
        Ok(cam)
    }

    /// Build from a row-major 3x4 `K` and `T = cam_from_lidar`; validates both
    /// ([`Self::validate`]: finite, invertible). Matrices that come from calibration data take
    /// [`Self::from_calibration`], which also checks that they are plausible.
    pub fn new(
        intrinsics_3x4: [[f32; 4]; 3],
        cam_from_lidar: Mat4,
        width: u32,
        height: u32,
    ) -> Result<Self, GeomError> {
        let cam = Self::assemble(intrinsics_3x4, cam_from_lidar, width, height);
        cam.validate()?;
        Ok(cam)
    }

    /// KITTI object benchmark: `K = P2`, `T = R0_rect * Tr_velo_to_cam` (both padded to 4x4).
    pub fn from_kitti(
        p2: [[f32; 4]; 3],
        r0_rect: Mat3,
        velo_to_cam: [[f32; 4]; 3],
        width: u32,
        height: u32,
    ) -> Result<Self, GeomError> {
        let t = Mat4::from_mat3(r0_rect) * rows3x4(velo_to_cam);
        Self::from_calibration(p2, t, width, height)
    }

    /// KITTI odometry / SemanticKITTI: `K = P2`, `T = Tr` (already to the rectified frame, no R0_rect).
    pub fn from_kitti_odometry(
        p2: [[f32; 4]; 3],
        tr: [[f32; 4]; 3],
        width: u32,
        height: u32,
    ) -> Result<Self, GeomError> {
        Self::from_calibration(p2, rows3x4(tr), width, height)
    }

    /// nuScenes: a 3x3 intrinsic matrix and the 4x4 `lidar2cam` transform.
    pub fn from_nuscenes(
        intrinsic: Mat3,
        lidar2cam: Mat4,
        width: u32,
        height: u32,
    ) -> Result<Self, GeomError> {
        let k = intrinsic.transpose().to_cols_array_2d(); // rows of K
        let k34 = [
            [k[0][0], k[0][1], k[0][2], 0.0],
            [k[1][0], k[1][1], k[1][2], 0.0],
            [k[2][0], k[2][1], k[2][2], 0.0],
        ];
        Self::from_calibration(k34, lidar2cam, width, height)
    }

    /// The same camera for the image resized to `width x height` pixels: `K` is scaled per axis in the
    /// pixel-centre convention (pixel `i` covers `[i - 0.5, i + 0.5]`, so `u' = s u + (s - 1) / 2`);
    /// the extrinsics are unchanged. `None` for a zero size.
    pub fn resized(&self, width: u32, height: u32) -> Option<Self> {
        if width == 0 || height == 0 {
            return None;
        }
        let sx = width as f32 / self.width as f32;
        let sy = height as f32 / self.height as f32;
        // rows of K: u' = sx u + (sx - 1)/2 w, v' = sy v + (sy - 1)/2 w
        let s = Mat4::from_cols_array_2d(&[
            [sx, 0.0, 0.0, 0.0],
            [0.0, sy, 0.0, 0.0],
            [0.5 * (sx - 1.0), 0.5 * (sy - 1.0), 1.0, 0.0],
            [0.0, 0.0, 0.0, 1.0],
        ]);
        Some(PinholeCamera {
            intrinsics: s * self.intrinsics,
            width,
            height,
            ..*self
        })
    }

    /// With another near plane.
    pub fn with_near_m(mut self, near_m: f32) -> Self {
        self.near_m = near_m;
        self
    }

    /// Check that the matrices are finite and invertible, the image non-empty and the near plane sane.
    pub fn validate(&self) -> Result<(), GeomError> {
        let bad = |m: String| Err(GeomError::InvalidCamera(m));
        if self.width == 0 || self.height == 0 {
            return bad(format!(
                "image size must be positive, got {}x{}",
                self.width, self.height
            ));
        }
        if !self.intrinsics.is_finite() || !self.cam_from_lidar.is_finite() {
            return bad("matrices must be finite".into());
        }
        if !(self.near_m.is_finite() && self.near_m > 0.0) {
            return bad(format!(
                "near plane must be finite and positive, got {}",
                self.near_m
            ));
        }
        let k3 = Mat3::from_mat4(self.intrinsics);
        let scale = k3
            .to_cols_array()
            .iter()
            .fold(0.0f32, |a, v| a.max(v.abs()));
        let det = k3.determinant();
        if scale.is_nan() || scale <= 0.0 || det.abs() <= 1e-9 * scale * scale * scale {
            return bad(format!("the 3x3 part of K is singular (det {det})"));
        }
        if self.cam_from_lidar.row(3) != Vec4::new(0.0, 0.0, 0.0, 1.0) {
            return bad("the last row of T must be (0, 0, 0, 1)".into());
        }
        if Mat3::from_mat4(self.cam_from_lidar).determinant().abs() < 1e-6 {
            return bad("the rotation part of T is singular".into());
        }
        Ok(())
    }

    /// Checks that the camera is one a calibration file can describe for its `width x height`
    /// image, beyond what [`Self::validate`] checks of every camera: finite matrices; `K`'s 3x3
    /// part with third row `(0, 0, 1)`, positive focal lengths `fx`, `fy` and the principal point
    /// `(cx, cy)` inside the image `[0, W] x [0, H]` (a calibration made for the image puts it
    /// near the centre; outside, it belongs to an image of another size, or is corrupt); the
    /// translation of `T` and the offset in `K`'s fourth column each within
    /// [`MAX_CAMERA_OFFSET_M`]. [`Self::from_calibration`] and the constructors from KITTI and
    /// nuScenes calibrations ([`Self::from_kitti`], [`Self::from_kitti_odometry`],
    /// [`Self::from_nuscenes`]) run it.
    pub fn check_calibration(&self) -> Result<(), GeomError> {
        let bad = |m: String| Err(GeomError::InvalidCamera(m));
        if !self.intrinsics.is_finite() || !self.cam_from_lidar.is_finite() {
            return bad("matrices must be finite".into());
        }
        let k = self.intrinsics;
        let row3 = Vec3::new(k.x_axis.z, k.y_axis.z, k.z_axis.z);
        if (row3 - Vec3::Z).abs().max_element() > K_ROW3_TOLERANCE {
            return bad(format!(
                "the third row of K is ({}, {}, {}), it must be (0, 0, 1)",
                row3.x, row3.y, row3.z
            ));
        }
        let (fx, fy) = (k.x_axis.x, k.y_axis.y);
        if !(fx > 0.0 && fy > 0.0) {
            return bad(format!(
                "focal lengths fx {fx}, fy {fy} px: both must be positive"
            ));
        }
        let (cx, cy) = (k.z_axis.x, k.z_axis.y);
        let (w, h) = (self.width as f32, self.height as f32);
        if !((0.0..=w).contains(&cx) && (0.0..=h).contains(&cy)) {
            return bad(format!(
                "the principal point ({cx}, {cy}) px lies outside the {} x {} image: the \
                 calibration is for an image of another size, or corrupt",
                self.width, self.height
            ));
        }
        let t = self.cam_from_lidar.w_axis.truncate();
        if t.length() > MAX_CAMERA_OFFSET_M {
            return bad(format!(
                "the LiDAR-to-camera translation ({}, {}, {}) m is {} m long, more than the \
                 limit of {MAX_CAMERA_OFFSET_M} m",
                t.x,
                t.y,
                t.z,
                t.length()
            ));
        }
        // K's fourth column (a KITTI stereo camera's baseline): the offset K⁻¹ p₄, in metres
        let off = Mat3::from_mat4(k).inverse() * k.w_axis.truncate();
        if off.is_nan() || off.length() > MAX_CAMERA_OFFSET_M {
            return bad(format!(
                "the fourth column of the projection matrix ({}, {}, {}) moves the camera by {} m, \
                 more than the limit of {MAX_CAMERA_OFFSET_M} m",
                k.w_axis.x,
                k.w_axis.y,
                k.w_axis.z,
                off.length()
            ));
        }
        Ok(())
    }

    /// `K T`, the full LiDAR-to-image matrix (last row padding).
    pub fn image_from_lidar(&self) -> Mat4 {
        self.intrinsics * self.cam_from_lidar
    }

    /// Project a LiDAR-frame point. `None` for non-finite input, for points at or behind the near plane
    /// (never a mirrored pixel) and for non-finite results. The point may fall outside the image.
    pub fn try_project(&self, p_lidar: Vec3) -> Option<ImagePoint> {
        if !p_lidar.is_finite() {
            return None;
        }
        let p_cam = self.cam_from_lidar * p_lidar.extend(1.0);
        let q = self.intrinsics * p_cam;
        let w = q.z;
        if !(w > self.near_m && p_cam.z > 0.0) {
            return None;
        }
        let ip = ImagePoint {
            u_px: q.x / w,
            v_px: q.y / w,
            depth_m: p_cam.z,
        };
        (ip.u_px.is_finite() && ip.v_px.is_finite()).then_some(ip)
    }

    /// Whether pixel coordinates lie inside the image (`[-0.5, W - 0.5) x [-0.5, H - 0.5)`).
    #[inline]
    pub fn contains(&self, u_px: f32, v_px: f32) -> bool {
        u_px >= -0.5
            && v_px >= -0.5
            && u_px < self.width as f32 - 0.5
            && v_px < self.height as f32 - 0.5
    }

    /// [`PinholeCamera::try_project`], and `None` outside the image too.
    pub fn try_project_in_image(&self, p_lidar: Vec3) -> Option<ImagePoint> {
        self.try_project(p_lidar)
            .filter(|ip| self.contains(ip.u_px, ip.v_px))
    }

    /// The LiDAR-frame point seen at pixel `(u_px, v_px)` with camera-frame depth `depth_m`; `None` if
    /// the pixel's ray is parallel to the image plane or the input is not finite. Inverse of
    /// [`PinholeCamera::try_project`].
    pub fn try_back_project(&self, u_px: f32, v_px: f32, depth_m: f32) -> Option<Vec3> {
        if !(u_px.is_finite() && v_px.is_finite() && depth_m.is_finite()) {
            return None;
        }
        let k3 = Mat3::from_mat4(self.intrinsics);
        let t = self.intrinsics.w_axis.truncate();
        let k_inv = k3.inverse();
        let ray = k_inv * Vec3::new(u_px, v_px, 1.0);
        let off = k_inv * t;
        // p_cam = w * ray - off, with p_cam.z = depth
        if ray.z.abs() < f32::EPSILON {
            return None;
        }
        let w = (depth_m + off.z) / ray.z;
        let p_cam = ray * w - off;
        let p = self.cam_from_lidar.inverse() * p_cam.extend(1.0);
        let p = p.truncate();
        p.is_finite().then_some(p)
    }

    /// Per range pixel: whether the pixel's ray, followed to infinity, is seen by the camera (the
    /// panorama's camera-frustum mask). Uses only the rotation of `T` and the 3x3 part of `K`.
    pub fn frustum_mask(&self, rays: &RayTable) -> Vec<bool> {
        let rot = Mat3::from_mat4(self.cam_from_lidar);
        let k3 = Mat3::from_mat4(self.intrinsics);
        rays.dirs()
            .iter()
            .map(|d| {
                let q = k3 * (rot * *d);
                q.z > 0.0 && self.contains(q.x / q.z, q.y / q.z)
            })
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// KITTI's `P2` and `Tr_velo_to_cam` of frame 000008 (rounded), for a 1242 x 375 image.
    const P2: [[f32; 4]; 3] = [
        [721.5377, 0.0, 609.5593, 44.85728],
        [0.0, 721.5377, 172.854, 0.2163791],
        [0.0, 0.0, 1.0, 0.002745884],
    ];
    const TR: [[f32; 4]; 3] = [
        [7.533745e-3, -0.9999714, -6.16602e-4, -4.069766e-3],
        [1.480249e-2, 7.280733e-4, -0.9998902, -7.631618e-2],
        [0.9998621, 7.52379e-3, 1.480755e-2, -0.2717806],
    ];

    fn kitti(p2: [[f32; 4]; 3], tr: [[f32; 4]; 3]) -> Result<PinholeCamera, GeomError> {
        PinholeCamera::from_kitti_odometry(p2, tr, 1242, 375)
    }

    fn refused(p2: [[f32; 4]; 3], tr: [[f32; 4]; 3], words: &[&str]) {
        let e = kitti(p2, tr).unwrap_err().to_string();
        for w in words {
            assert!(e.contains(w), "`{w}` not in: {e}");
        }
    }

    #[test]
    fn a_real_calibration_is_plausible() {
        let cam = kitti(P2, TR).unwrap();
        cam.check_calibration().unwrap();
        // a camera that is not from a file keeps only validate's checks
        let mut k = P2;
        k[0][2] = 1e7;
        assert!(PinholeCamera::new(k, Mat4::IDENTITY, 1242, 375).is_err());
    }

    #[test]
    fn from_calibration_checks_what_new_leaves_alone() {
        let t = rows3x4(TR);
        // a negative focal length is a valid (mirroring) camera, not a plausible calibration
        let mut k = P2;
        k[0][0] = -721.5377;
        assert!(PinholeCamera::new(k, t, 1242, 375).is_ok());
        let e = PinholeCamera::from_calibration(k, t, 1242, 375).unwrap_err();
        assert!(e.to_string().contains("focal lengths"), "{e}");
        // the same matrices build the same camera either way
        let a = PinholeCamera::new(P2, t, 1242, 375).unwrap();
        let b = PinholeCamera::from_calibration(P2, t, 1242, 375).unwrap();
        assert_eq!(a, b);
        assert_eq!(b, kitti(P2, TR).unwrap());
        // validate's checks still run after the plausibility checks
        let mut singular = t;
        singular.x_axis = Vec4::ZERO;
        let e = PinholeCamera::from_calibration(P2, singular, 1242, 375).unwrap_err();
        assert!(
            e.to_string().contains("rotation part of T is singular"),
            "{e}"
        );
    }

    #[test]
    fn implausible_calibrations_are_refused_saying_what_is_wrong() {
        for (i, j) in [(0, 0), (1, 1)] {
            for v in [-721.5377, 0.0] {
                let mut k = P2;
                k[i][j] = v;
                refused(k, TR, &["focal lengths", "must be positive"]);
            }
        }
        // the principal point of 1e7 was "the 3x3 part of K is singular"
        let mut k = P2;
        k[0][2] = 1e7;
        refused(
            k,
            TR,
            &["principal point (10000000, 172.854)", "1242 x 375 image"],
        );
        let mut k = P2;
        k[1][2] = -3.0;
        refused(k, TR, &["principal point", "outside"]);
        let mut k = P2;
        k[2] = [0.0, 0.0, -1.0, 0.0];
        refused(k, TR, &["third row of K", "(0, 0, 1)"]);
        let mut t = TR;
        t[0][3] = 1e30;
        refused(P2, t, &["LiDAR-to-camera translation", "limit of 100 m"]);
        // 99 m is allowed, 101 m is not
        t[0][3] = 99.0;
        assert!(kitti(P2, t).is_ok());
        t[0][3] = 101.0;
        refused(P2, t, &["translation", "limit of 100 m"]);
        let mut k = P2;
        k[0][3] = 721.5377 * 500.0;
        refused(
            k,
            TR,
            &[
                "fourth column",
                "moves the camera by 499.99",
                "limit of 100 m",
            ],
        );
    }
}
