//! CM-DC and CM-SC on a synthetic camera with closed-form answers.

use glam::{Mat4, Vec3, Vec4};
use veila_geom::PinholeCamera;
use veila_metrics::{
    Error, Region,
    crossmodal::{
        DepthAlignment, Map2d, ProjectionFilter, cm_depth_consistency, cm_semantic_consistency,
    },
};

/// A 100 x 80 camera looking along LiDAR +x (camera z = x, camera x = -y, camera y = -z), f = 50 px.
fn camera() -> PinholeCamera {
    let cam_from_lidar = Mat4::from_cols(
        Vec4::new(0.0, 0.0, 1.0, 0.0),  // lidar x -> cam z
        Vec4::new(-1.0, 0.0, 0.0, 0.0), // lidar y -> cam -x
        Vec4::new(0.0, -1.0, 0.0, 0.0), // lidar z -> cam -y
        Vec4::new(0.0, 0.0, 0.0, 1.0),
    );
    PinholeCamera::new(
        [
            [50.0, 0.0, 50.0, 0.0],
            [0.0, 50.0, 40.0, 0.0],
            [0.0, 0.0, 1.0, 0.0],
        ],
        cam_from_lidar,
        100,
        80,
    )
    .unwrap()
}

/// Points on a grid in front of the camera at depth `x`, each landing on its own pixel.
fn points() -> Vec<Vec3> {
    let mut v = Vec::new();
    for i in 0..10 {
        for j in 0..8 {
            let depth = 5.0 + i as f32 + 0.5 * j as f32;
            // pixel (10 + 8i, 5 + 9j): u = 50 - 50 y / x, v = 40 - 50 z / x
            let u = 10.0 + 8.0 * i as f32;
            let vv = 5.0 + 9.0 * j as f32;
            v.push(Vec3::new(
                depth,
                -(u - 50.0) * depth / 50.0,
                -(vv - 40.0) * depth / 50.0,
            ));
        }
    }
    v.push(Vec3::new(-10.0, 0.0, 0.0)); // behind the camera
    v
}

fn depth_map(f: impl Fn(f32) -> f32) -> Vec<f32> {
    let cam = camera();
    let mut m = vec![f32::NAN; 100 * 80];
    for p in points() {
        if let Some(ip) = cam.try_project_in_image(p) {
            let (c, r) = ip.pixel(100, 80).unwrap();
            m[r as usize * 100 + c as usize] = f(ip.depth_m);
        }
    }
    m
}

#[test]
fn median_alignment_removes_scale() {
    let m = depth_map(|d| 0.25 * d);
    let map = Map2d::new(100, 80, &m).unwrap();
    let r = cm_depth_consistency(
        &points(),
        &camera(),
        &map,
        DepthAlignment::Median,
        &ProjectionFilter::default(),
    )
    .unwrap();
    assert_eq!(r.points, 80);
    assert!((r.scale - 4.0).abs() < 1e-6, "{r:?}");
    assert!(r.abs_rel < 1e-6, "{r:?}");
    // without alignment: |0.25 d - d| / d = 0.75
    let r = cm_depth_consistency(
        &points(),
        &camera(),
        &map,
        DepthAlignment::None,
        &ProjectionFilter::default(),
    )
    .unwrap();
    assert!((r.abs_rel - 0.75).abs() < 1e-6);
}

#[test]
fn least_squares_alignment_removes_scale_and_shift() {
    let m = depth_map(|d| 0.5 * d + 3.0);
    let map = Map2d::new(100, 80, &m).unwrap();
    let r = cm_depth_consistency(
        &points(),
        &camera(),
        &map,
        DepthAlignment::LeastSquares,
        &ProjectionFilter::default(),
    )
    .unwrap();
    assert!(
        (r.scale - 2.0).abs() < 1e-4 && (r.shift + 6.0).abs() < 1e-3,
        "{r:?}"
    );
    assert!(r.abs_rel < 1e-5, "{r:?}");
    // median scaling cannot remove a shift: known non-zero error
    let r = cm_depth_consistency(
        &points(),
        &camera(),
        &map,
        DepthAlignment::Median,
        &ProjectionFilter::default(),
    )
    .unwrap();
    assert!(r.abs_rel > 0.01);
}

#[test]
fn disparity_alignment_inverts_an_affine_inverse_depth_map() {
    // what a relative Depth-Anything-V2 predicts: an affine function of 1 / depth
    let m = depth_map(|d| 3.0 / d + 0.2);
    let map = Map2d::new(100, 80, &m).unwrap();
    let r = cm_depth_consistency(
        &points(),
        &camera(),
        &map,
        DepthAlignment::Disparity,
        &ProjectionFilter::default(),
    )
    .unwrap();
    // 1/d = (m - 0.2) / 3
    assert!(
        (r.scale - 1.0 / 3.0).abs() < 1e-4 && (r.shift + 0.2 / 3.0).abs() < 1e-4,
        "{r:?}"
    );
    assert!(r.abs_rel < 1e-4, "{r:?}");
    // depth-space least squares cannot undo the inversion
    let r = cm_depth_consistency(
        &points(),
        &camera(),
        &map,
        DepthAlignment::LeastSquares,
        &ProjectionFilter::default(),
    )
    .unwrap();
    assert!(r.abs_rel > 0.05, "{r:?}");
    // a map anti-correlated with disparity fits a negative scale: non-positive predictions score 1
    let m = depth_map(|d| d);
    let map = Map2d::new(100, 80, &m).unwrap();
    let r = cm_depth_consistency(
        &points(),
        &camera(),
        &map,
        DepthAlignment::Disparity,
        &ProjectionFilter::default(),
    )
    .unwrap();
    assert!(
        r.scale < 0.0 && r.abs_rel.is_finite() && r.abs_rel > 0.01,
        "{r:?}"
    );
}

#[test]
fn half_resolution_map_is_sampled_at_rescaled_pixels() {
    // a constant map at half resolution: every point compares against 2.0
    let m = vec![2.0f32; 50 * 40];
    let map = Map2d::new(50, 40, &m).unwrap();
    let r = cm_depth_consistency(
        &points(),
        &camera(),
        &map,
        DepthAlignment::None,
        &ProjectionFilter::default(),
    )
    .unwrap();
    let pts = points();
    let want: f64 = pts[..80]
        .iter()
        .map(|p| (2.0 - p.x as f64).abs() / p.x as f64)
        .sum::<f64>()
        / 80.0;
    assert!((r.abs_rel - want).abs() < 1e-6);
}

#[test]
fn semantic_agreement_percentage_and_zbuffer() {
    let cam = camera();
    let pts = points();
    let mut sem = vec![0u16; 100 * 80];
    let mut labels = vec![0u32; pts.len()];
    for (i, p) in pts.iter().enumerate() {
        labels[i] = (i % 4) as u32 + 1;
        if let Some(ip) = cam.try_project_in_image(*p) {
            let (c, r) = ip.pixel(100, 80).unwrap();
            // agree on three quarters of the points
            sem[r as usize * 100 + c as usize] = if i % 4 == 3 { 9 } else { labels[i] as u16 };
        }
    }
    let map = Map2d::new(100, 80, &sem).unwrap();
    let r =
        cm_semantic_consistency(&pts, &labels, &cam, &map, &ProjectionFilter::default()).unwrap();
    assert_eq!(r.points, 80);
    assert!((r.percent - 75.0).abs() < 1e-12);

    // an occluded point behind the first one, on the same pixel, with a wrong label: ignored by the z-buffer
    let mut pts2 = pts.clone();
    pts2.push(pts[0] * 2.0);
    let mut labels2 = labels.clone();
    labels2.push(7);
    let r =
        cm_semantic_consistency(&pts2, &labels2, &cam, &map, &ProjectionFilter::default()).unwrap();
    assert_eq!(r.points, 80);
    let no_z = ProjectionFilter {
        zbuffer: false,
        ..ProjectionFilter::default()
    };
    let r = cm_semantic_consistency(&pts2, &labels2, &cam, &map, &no_z).unwrap();
    assert_eq!(r.points, 81);

    // ignore label and regions
    let ign = ProjectionFilter {
        ignore_label: Some(1),
        ..ProjectionFilter::default()
    };
    assert_eq!(
        cm_semantic_consistency(&pts, &labels, &cam, &map, &ign)
            .unwrap()
            .points,
        60
    );
    let rear = ProjectionFilter {
        region: Region::Rear,
        ..ProjectionFilter::default()
    };
    assert!(matches!(
        cm_semantic_consistency(&pts, &labels, &cam, &map, &rear),
        Err(Error::NoPointsInWindow { .. })
    ));
    assert!(matches!(
        cm_semantic_consistency(&pts, &labels[..3], &cam, &map, &ProjectionFilter::default()),
        Err(Error::ShapeMismatch { .. })
    ));
    assert!(Map2d::new(100, 80, &sem[..10]).is_err());
}

#[test]
fn cityscapes_classes_map_to_semantickitti_train_ids() {
    use veila_metrics::crossmodal::cityscapes_to_semantickitti as map;
    // spot checks by name (SemanticKITTI: 1 car, 9 road, 11 sidewalk, 13 building, 15 vegetation)
    assert_eq!(map(0), 9);
    assert_eq!(map(1), 11);
    assert_eq!(map(2), 13);
    assert_eq!(map(3), 13);
    assert_eq!(map(8), 15);
    assert_eq!(map(10), 0, "sky has no LiDAR return");
    assert_eq!(map(13), 1);
    assert_eq!(map(18), 2);
    assert_eq!(map(19), 0);
    assert_eq!(map(u32::MAX), 0);
    // every SemanticKITTI class a camera segmenter can name is reached; none outside 0..=19
    let hit: std::collections::BTreeSet<u32> = (0..19).map(map).collect();
    assert!(hit.iter().all(|&c| c <= 19));
    for c in [1, 2, 3, 4, 5, 6, 7, 9, 11, 13, 14, 15, 17, 18, 19] {
        assert!(hit.contains(&c), "class {c}");
    }
}
