//! Camera rigs from files: an image and its calibration (KITTI object, KITTI odometry /
//! SemanticKITTI or a nuScenes per-sample JSON) become a [`RigView`] ([`load_view`]); a rig in
//! memory is a slice of [`RigImage`]s. [`scan_points`] turns a range image on a bundle's grid into
//! points, and [`point_colours`] colours them from a view.
//!
//! Below that, crate-private, the steps [`super::pipeline::ScanPipeline`] puts together (resizing a
//! view to a bundle's input, the turn into the model's frame and the scan's turn back): a door gets
//! scans from a rig through the pipeline only, since a step left out gives scans in the wrong frame.
//!
//! Calibration files carry no image size, so each camera takes the size of its image. The image
//! must be the one the calibration describes (full resolution): an image whose size puts the
//! calibration's principal point outside the central 20-80% of the image is rejected, because a
//! resized image needs a rescaled calibration.

use std::path::{Path, PathBuf};

use veila_data::PointCloud;
use veila_data::image::{RgbImage, imageops};
use veila_data::image_io::read_rgb_image;
use veila_data::spec::read_calib_camera;
use veila_geom::{PinholeCamera, RangeImage, RayTable};

use super::bundle::BundleConfig;
use super::generate::CameraView;
use crate::error::{Error, Result};

/// One camera of a rig, read and checked.
#[derive(Debug, Clone)]
pub struct RigView {
    /// The image file.
    pub image_path: PathBuf,
    /// The calibration file.
    pub calib_path: PathBuf,
    /// `kitti-object`, `kitti-odometry` or `nuscenes-json`.
    pub calib_kind: &'static str,
    /// Which camera of the calibration: a KITTI index or a nuScenes channel.
    pub camera_name: String,
    /// The image at full resolution.
    pub image: RgbImage,
    /// The camera at the image's full resolution.
    pub camera: PinholeCamera,
}

impl RigView {
    /// This view as one camera of a rig for [`super::pipeline::ScanPipeline`].
    pub fn rig_image(&self) -> RigImage<'_> {
        RigImage {
            image: &self.image,
            camera: &self.camera,
        }
    }
}

/// One camera of a rig in memory: an image at the resolution its calibration describes, and that
/// camera (LiDAR frame to pixels). [`RigView::rig_image`] borrows one from a view read from files.
#[derive(Debug, Clone, Copy)]
pub struct RigImage<'a> {
    /// The image, RGB.
    pub image: &'a RgbImage,
    /// Its camera: `width x height` the image's, `cam_from_lidar` from the LiDAR's own frame.
    pub camera: &'a PinholeCamera,
}

fn input(path: &Path, reason: String) -> Error {
    Error::Input {
        path: path.to_path_buf(),
        reason,
    }
}

/// Reads `image` and camera `camera` of `calib` (default: KITTI camera 2 = `image_2`, nuScenes
/// `CAM_FRONT`) with the one calibration reader, [`read_calib_camera`], and checks that the
/// calibration is for an image of this size.
pub fn load_view(image_path: &Path, calib_path: &Path, camera: Option<&str>) -> Result<RigView> {
    let image = read_rgb_image(image_path)?;
    let (w, h) = image.dimensions();
    let read = read_calib_camera(calib_path, camera, w, h)
        .map_err(|e| input(image_path, format!("the camera of this {w}x{h} image: {e}")))?;
    check_principal_point(&read.camera, image_path, calib_path)?;
    Ok(RigView {
        image_path: image_path.to_path_buf(),
        calib_path: calib_path.to_path_buf(),
        calib_kind: read.kind.name(),
        camera_name: read.name,
        image,
        camera: read.camera,
    })
}

/// A calibration's principal point lies near the centre of the image it was made for (KITTI: 49% /
/// 46% of width / height, nuScenes: 50% / 50%). Outside the central 20-80% band, the image was
/// almost certainly resized (a 2x change moves it to ~25% or ~100%) or cropped without adapting the
/// calibration, and the scan would be generated for the wrong rays.
pub(crate) fn check_principal_point(
    camera: &PinholeCamera,
    image: &Path,
    calib: &Path,
) -> Result<()> {
    let k = camera.intrinsics;
    let (cx, cy) = (k.z_axis.x, k.z_axis.y);
    let (w, h) = (camera.width as f32, camera.height as f32);
    let (fx, fy) = (cx / w, cy / h);
    if !((0.2..=0.8).contains(&fx) && (0.2..=0.8).contains(&fy)) {
        return Err(input(
            image,
            format!(
                "the image is {}x{} but the principal point of {} is at ({cx:.1}, {cy:.1}) px, \
                 {:.0}% / {:.0}% of the width / height instead of near the centre: the calibration is for \
                 another image size (use the original image, or rescale the calibration with the image)",
                camera.width,
                camera.height,
                calib.display(),
                100.0 * fx,
                100.0 * fy
            ),
        ));
    }
    Ok(())
}

/// An image and its camera resized to the bundle's input size (triangle filter, antialiased).
pub(crate) fn prepare_view(
    config: &BundleConfig,
    image: &RgbImage,
    camera: &PinholeCamera,
) -> Result<(Vec<u8>, PinholeCamera)> {
    let (w, h) = (config.image_width as u32, config.image_height as u32);
    if (image.width(), image.height()) != (camera.width, camera.height) {
        return Err(Error::Shape {
            what: "camera view",
            expected: format!(
                "an image of the camera's {}x{}",
                camera.width, camera.height
            ),
            got: format!("{}x{}", image.width(), image.height()),
        });
    }
    let small = imageops::resize(image, w, h, imageops::FilterType::Triangle);
    let cam = camera.resized(w, h).ok_or_else(|| Error::InvalidConfig {
        field: "image_width",
        reason: "the model's image size has a zero dimension".into(),
    })?;
    Ok((small.into_raw(), cam))
}

/// Resized views of a rig, owned; borrow them with [`camera_views`].
pub(crate) type PreparedViews = Vec<(Vec<u8>, PinholeCamera)>;

/// [`prepare_view`] for every view of a rig (errors name the image).
pub(crate) fn prepare_views(config: &BundleConfig, views: &[RigView]) -> Result<PreparedViews> {
    views
        .iter()
        .map(|v| {
            prepare_view(config, &v.image, &v.camera)
                .map_err(|e| input(&v.image_path, e.to_string()))
        })
        .collect()
}

/// Borrowed [`CameraView`]s of prepared images.
pub(crate) fn camera_views(prepared: &[(Vec<u8>, PinholeCamera)]) -> Vec<CameraView<'_>> {
    prepared
        .iter()
        .map(|(rgb, camera)| CameraView { rgb, camera })
        .collect()
}

/// Quarter turns `q` about the LiDAR's `z` axis from a dataset's LiDAR frame into the model's,
/// whose `x` axis is the camera's optical axis (to the nearest quarter turn): the bundled models
/// learnt their prior with the front camera looking along `+x` (KITTI's LiDAR frame), while
/// nuScenes' LiDAR frame has `y` forward (`q = 1`). `p_model = R_z(-q·90°) p_lidar`; `0` for KITTI.
pub(crate) fn quarter_turns_to_model(camera: &PinholeCamera) -> i32 {
    let axis = camera
        .cam_from_lidar
        .inverse()
        .transform_vector3(glam::Vec3::Z);
    let q = (axis.y.atan2(axis.x) / std::f32::consts::FRAC_PI_2).round() as i32;
    q.rem_euclid(4)
}

/// `camera` seeing the model frame of [`quarter_turns_to_model`]: `cam_from_model =
/// cam_from_lidar · R_z(q·90°)`.
pub(crate) fn camera_in_model_frame(camera: &PinholeCamera, q: i32) -> PinholeCamera {
    let mut cam = *camera;
    if q.rem_euclid(4) != 0 {
        let turn = glam::Mat4::from_rotation_z(q as f32 * std::f32::consts::FRAC_PI_2);
        cam.cam_from_lidar *= turn;
    }
    cam
}

/// A range image of the model frame turned back into the LiDAR frame (`p_lidar = R_z(q·90°)
/// p_model`): a roll of the columns by a quarter of the width per turn, exact because the grid's
/// columns are uniform in azimuth. Needs a width divisible by 4 when `q` is not a multiple of 4.
pub(crate) fn range_to_lidar_frame(
    config: &BundleConfig,
    range: &RangeImage,
    q: i32,
) -> Result<RangeImage> {
    roll_range(config, range, q)
}

/// The inverse of [`range_to_lidar_frame`]: a range image of the LiDAR frame (a scan to edit)
/// turned into the model frame, `p_model = R_z(-q·90°) p_lidar`.
pub(crate) fn range_to_model_frame(
    config: &BundleConfig,
    range: &RangeImage,
    q: i32,
) -> Result<RangeImage> {
    roll_range(config, range, -q)
}

/// Per-pixel values (row-major, `rows x cols`, e.g. an edit's keep mask) of the LiDAR frame moved
/// into the model frame, as [`range_to_model_frame`] moves a range image.
pub(crate) fn pixels_to_model_frame<T: Copy>(
    config: &BundleConfig,
    values: &[T],
    rows: usize,
    cols: usize,
    q: i32,
) -> Result<Vec<T>> {
    match column_shift(config, rows, cols, values.len(), -q)? {
        0 => Ok(values.to_vec()),
        shift => Ok(roll(values, cols, shift)),
    }
}

/// Output pixel `(r, c)` is input pixel `(r, (c + shift) mod cols)` for a turn of the output
/// frame by `p_out = R_z(q·90°) p_in`; 0 when `q` is a multiple of 4.
fn column_shift(
    config: &BundleConfig,
    rows: usize,
    cols: usize,
    len: usize,
    q: i32,
) -> Result<usize> {
    let q = q.rem_euclid(4);
    if q == 0 {
        return Ok(0);
    }
    if !cols.is_multiple_of(4) || len != rows * cols {
        return Err(Error::InvalidConfig {
            field: "sensor.cols",
            reason: format!(
                "turning a {rows} x {cols} range image by quarter turns needs a width divisible by 4"
            ),
        });
    }
    // which way the columns run: the input column whose ray is output column 0's, turned
    let rays = RayTable::new(&config.denoiser.sensor)?;
    let row = (rows / 2) as u32;
    let turn = glam::Mat3::from_rotation_z(-(q as f32) * std::f32::consts::FRAC_PI_2);
    let want = turn * rays.dir(row, 0);
    Ok((0..cols)
        .max_by(|&a, &b| {
            want.dot(rays.dir(row, a as u32))
                .total_cmp(&want.dot(rays.dir(row, b as u32)))
        })
        .unwrap_or(0))
}

fn roll<T: Copy>(v: &[T], cols: usize, shift: usize) -> Vec<T> {
    (0..v.len())
        .map(|i| v[(i / cols) * cols + (i % cols + shift) % cols])
        .collect()
}

fn roll_range(config: &BundleConfig, range: &RangeImage, q: i32) -> Result<RangeImage> {
    let (rows, cols) = (range.rows as usize, range.cols as usize);
    let shift = column_shift(config, rows, cols, range.range_m.len(), q)?;
    if shift == 0 {
        return Ok(range.clone());
    }
    let mut out = range.clone();
    out.range_m = roll(&range.range_m, cols, shift);
    out.intensity = roll(&range.intensity, cols, shift);
    out.mask = roll(&range.mask, cols, shift);
    out.point_index = roll(&range.point_index, cols, shift);
    out.label = range.label.as_ref().map(|l| roll(l, cols, shift));
    Ok(out)
}

/// The points of a generated range image in the LiDAR frame (one per return, with intensity).
pub fn scan_points(config: &BundleConfig, range: &RangeImage) -> Result<PointCloud> {
    let rays = RayTable::new(&config.denoiser.sensor)?;
    let un = rays.unproject(range)?;
    Ok(PointCloud {
        xyz: un.points,
        intensity: un.intensity,
        ring: None,
        label: None,
    })
}

/// A colour per point of `cloud`: the colour of `view`'s image where the point projects into it
/// (nearest pixel), elsewhere a grey of the point's intensity (0 to 1 maps to black to white).
pub fn point_colours(view: &RigView, cloud: &PointCloud) -> Vec<[u8; 3]> {
    let (w, h) = view.image.dimensions();
    cloud
        .xyz
        .iter()
        .zip(&cloud.intensity)
        .map(|(p, i)| {
            let pixel = view.camera.try_project_in_image(*p).and_then(|ip| {
                let (u, v) = ((ip.u_px + 0.5).floor(), (ip.v_px + 0.5).floor());
                (u >= 0.0 && v >= 0.0 && u < w as f32 && v < h as f32)
                    .then(|| view.image.get_pixel(u as u32, v as u32).0)
            });
            pixel.unwrap_or_else(|| {
                let g = (i.clamp(0.0, 1.0) * 255.0).round() as u8;
                [g, g, g]
            })
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::{Mat4, Vec3};

    #[test]
    fn points_in_the_image_take_its_colour_others_a_grey_of_intensity() {
        // a camera looking along LiDAR +x (camera z), f = 10 px, principal point (4, 3), 8x6 image
        let cam_from_lidar = Mat4::from_cols_array_2d(&[
            [0.0, 0.0, 1.0, 0.0],
            [-1.0, 0.0, 0.0, 0.0],
            [0.0, -1.0, 0.0, 0.0],
            [0.0, 0.0, 0.0, 1.0],
        ]);
        let k = [
            [10.0, 0.0, 4.0, 0.0],
            [0.0, 10.0, 3.0, 0.0],
            [0.0, 0.0, 1.0, 0.0],
        ];
        let camera = PinholeCamera::new(k, cam_from_lidar, 8, 6).unwrap();
        let mut image = RgbImage::new(8, 6);
        image.put_pixel(4, 3, veila_data::image::Rgb([200, 10, 30]));
        image.put_pixel(5, 3, veila_data::image::Rgb([1, 2, 3]));
        let view = RigView {
            image_path: "img.png".into(),
            calib_path: "calib.txt".into(),
            calib_kind: "kitti-object",
            camera_name: "2".into(),
            image,
            camera,
        };
        let cloud = PointCloud {
            // straight ahead -> pixel (4, 3); 0.1 m to the right at 1 m -> u = 4 + 10 * 0.1 = 5;
            // behind the camera; far to the side (outside the image)
            xyz: vec![
                Vec3::new(10.0, 0.0, 0.0),
                Vec3::new(1.0, -0.1, 0.0),
                Vec3::new(-5.0, 0.0, 0.0),
                Vec3::new(1.0, 5.0, 0.0),
            ],
            intensity: vec![0.0, 0.0, 0.5, 2.0],
            ring: None,
            label: None,
        };
        assert_eq!(
            point_colours(&view, &cloud),
            [[200, 10, 30], [1, 2, 3], [128, 128, 128], [255, 255, 255]]
        );
    }

    /// KITTI's axes (x forward) and a nuScenes-like LiDAR (y forward: the camera's optical axis
    /// is LiDAR +y).
    fn axes(y_forward: bool) -> Mat4 {
        let kitti = Mat4::from_cols_array_2d(&[
            [0.0, 0.0, 1.0, 0.0],
            [-1.0, 0.0, 0.0, 0.0],
            [0.0, -1.0, 0.0, 0.0],
            [0.0, 0.0, 0.0, 1.0],
        ]);
        if y_forward {
            // p_kitti = R_z(-90°) p_nusc takes nuScenes' +y to +x
            kitti * Mat4::from_rotation_z(-std::f32::consts::FRAC_PI_2)
        } else {
            kitti
        }
    }

    fn cam(cam_from_lidar: Mat4) -> PinholeCamera {
        let k = [
            [50.0, 0.0, 40.0, 0.0],
            [0.0, 50.0, 30.0, 0.0],
            [0.0, 0.0, 1.0, 0.0],
        ];
        PinholeCamera::new(k, cam_from_lidar, 80, 60).unwrap()
    }

    #[test]
    fn a_y_forward_lidar_is_turned_so_the_camera_looks_along_model_x() {
        assert_eq!(quarter_turns_to_model(&cam(axes(false))), 0);
        let nusc = cam(axes(true));
        let q = quarter_turns_to_model(&nusc);
        assert_eq!(q, 1);
        // the camera in the model frame sees model +x where the dataset's camera saw lidar +y
        let m = camera_in_model_frame(&nusc, q);
        let ahead = m.try_project(Vec3::new(10.0, 0.0, 0.0)).unwrap();
        let same = nusc.try_project(Vec3::new(0.0, 10.0, 0.0)).unwrap();
        assert!((ahead.u_px - 40.0).abs() < 1e-4 && (ahead.v_px - 30.0).abs() < 1e-4);
        assert!(
            (ahead.u_px - same.u_px).abs() < 1e-4 && (ahead.depth_m - same.depth_m).abs() < 1e-4
        );
        assert_eq!(
            camera_in_model_frame(&nusc, 0).cam_from_lidar,
            nusc.cam_from_lidar
        );
    }

    #[test]
    fn turning_a_range_image_back_rolls_its_points_about_z() {
        let config = BundleConfig::cpu_default(super::super::bundle::Variant::Full);
        let sensor = &config.denoiser.sensor;
        let (rows, cols) = (sensor.rows, sensor.cols);
        let n = (rows * cols) as usize;
        // a structured scan: range and intensity vary with row and column, some pixels empty
        let mut range = RangeImage::new_empty(rows, cols);
        for i in 0..n {
            if i % 7 != 3 {
                range.range_m[i] =
                    5.0 + (i % cols as usize) as f32 * 0.1 + (i / cols as usize) as f32;
                range.intensity[i] = (i % 11) as f32 / 10.0;
                range.mask[i] = true;
            }
        }
        for q in 0..4 {
            let model_pts = scan_points(&config, &range).unwrap();
            let lidar = range_to_lidar_frame(&config, &range, q).unwrap();
            let lidar_pts = scan_points(&config, &lidar).unwrap();
            assert_eq!(model_pts.len(), lidar_pts.len());
            // p_lidar = R_z(q·90°) p_model, point for point (up to float rounding of the rays);
            // compare as sets: sort both by their coordinates
            let turn = glam::Mat3::from_rotation_z(q as f32 * std::f32::consts::FRAC_PI_2);
            let key = |p: &Vec3| {
                (
                    (p.x * 100.0).round() as i64,
                    (p.y * 100.0).round() as i64,
                    (p.z * 100.0).round() as i64,
                )
            };
            let mut want: Vec<_> = model_pts.xyz.iter().map(|p| key(&(turn * *p))).collect();
            let mut got: Vec<_> = lidar_pts.xyz.iter().map(key).collect();
            want.sort_unstable();
            got.sort_unstable();
            let mismatched = want.iter().zip(&got).filter(|(a, b)| a != b).count();
            assert!(
                mismatched <= n / 1000,
                "q = {q}: {mismatched} of {} points differ",
                want.len()
            );
        }
        let mut odd = config.clone();
        odd.denoiser.sensor.cols = 258;
        let r = RangeImage::new_empty(rows, 258);
        assert!(range_to_lidar_frame(&odd, &r, 1).is_err());
        assert!(range_to_lidar_frame(&odd, &r, 4).is_ok());
    }

    #[test]
    fn into_the_model_frame_and_back_is_the_identity() {
        let config = BundleConfig::cpu_default(super::super::bundle::Variant::Full);
        let sensor = &config.denoiser.sensor;
        let (rows, cols) = (sensor.rows as usize, sensor.cols as usize);
        let mut range = RangeImage::new_empty(rows as u32, cols as u32);
        for i in 0..rows * cols {
            if i % 5 != 1 {
                range.range_m[i] = 3.0 + (i % cols) as f32 * 0.05 + (i / cols) as f32;
                range.mask[i] = true;
            }
        }
        let index: Vec<usize> = (0..rows * cols).collect();
        for q in 0..4 {
            let model = range_to_model_frame(&config, &range, q).unwrap();
            let back = range_to_lidar_frame(&config, &model, q).unwrap();
            assert_eq!(back.range_m, range.range_m, "q = {q}");
            assert_eq!(back.mask, range.mask, "q = {q}");
            // per-pixel values (an edit's keep mask) move exactly as the scan does
            let moved = pixels_to_model_frame(&config, &index, rows, cols, q).unwrap();
            for (k, &from) in moved.iter().enumerate() {
                assert_eq!(model.range_m[k], range.range_m[from], "q = {q}, pixel {k}");
                assert_eq!(model.mask[k], range.mask[from], "q = {q}, pixel {k}");
            }
            // a turn of a quarter moves the columns by a quarter of the width
            if q != 0 {
                assert_ne!(model.range_m, range.range_m, "q = {q}");
            }
        }
        assert!(pixels_to_model_frame(&config, &index, rows, cols + 1, 1).is_err());
    }
}
