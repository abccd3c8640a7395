//! `EncoderAugment`: the image and its targets move together, depth follows the zoom, the draws are
//! seeded, and the identity configuration changes nothing.

use veila_data::augment::{CropZoomRange, Photometric};
use veila_diffusion::app::{EncoderAugment, EncoderExample};

const H: usize = 24;
const W: usize = 40;

/// An example whose label and depth encode the pixel position, so any resampling is traceable.
fn example() -> EncoderExample {
    let mut rgb = Vec::with_capacity(H * W * 3);
    let mut labels = Vec::with_capacity(H * W);
    let mut depth = Vec::with_capacity(H * W);
    for v in 0..H {
        for u in 0..W {
            rgb.extend_from_slice(&[(u * 6) as u8, (v * 10) as u8, 128]);
            labels.push((v * W + u) as u32);
            depth.push(if v < 4 { 0.0 } else { 10.0 + v as f32 });
        }
    }
    EncoderExample {
        rgb,
        camera: None,
        labels: Some(labels),
        depth_m: depth,
    }
}

fn zoom_only(scale: [f32; 2]) -> EncoderAugment {
    EncoderAugment {
        photometric: Photometric::identity(),
        crop_zoom: CropZoomRange { p: 1.0, scale },
    }
}

#[test]
fn identity_changes_nothing() {
    let a = EncoderAugment {
        photometric: Photometric::identity(),
        crop_zoom: CropZoomRange::identity(),
    };
    let mut ex = example();
    a.apply(&mut ex, (H, W), 7).unwrap();
    let orig = example();
    assert_eq!(ex.rgb, orig.rgb);
    assert_eq!(ex.labels, orig.labels);
    assert_eq!(ex.depth_m, orig.depth_m);
}

#[test]
fn zoom_moves_labels_and_depth_with_the_image_and_divides_depth() {
    let s = 1.25f32;
    let a = zoom_only([s, s]);
    let mut ex = example();
    a.apply(&mut ex, (H, W), 3).unwrap();
    let orig = example();
    let labels = ex.labels.as_ref().unwrap();
    for v in 0..H {
        for u in 0..W {
            let i = v * W + u;
            // the label says which source pixel this output pixel shows
            let src = labels[i] as usize;
            let (su, sv) = (src % W, src / W);
            // depth came from the same source pixel, divided by the zoom (0 = none stays 0)
            let want = orig.depth_m[src] * (1.0 / s);
            assert_eq!(ex.depth_m[i], want, "pixel ({u}, {v}) from ({su}, {sv})");
            // and the source pixel lies within the 1/s window: neighbouring outputs step by
            // at most one source pixel (nearest sampling of a magnification)
            if u + 1 < W {
                let next = labels[i + 1] as usize % W;
                assert!(next == su || next == su + 1);
            }
        }
    }
    // the window is 1/s of the image: it shows about W/s distinct columns
    let cols: std::collections::BTreeSet<usize> =
        labels[..W].iter().map(|&l| l as usize % W).collect();
    let expect = (W as f32 / s).round() as usize;
    assert!(cols.len().abs_diff(expect) <= 1, "{} columns", cols.len());
    assert_ne!(ex.rgb, orig.rgb);
}

#[test]
fn draws_are_seeded() {
    let a = EncoderAugment::default();
    let run = |seed| {
        let mut ex = example();
        a.apply(&mut ex, (H, W), seed).unwrap();
        ex
    };
    let (x, y) = (run(11), run(11));
    assert_eq!(x.rgb, y.rgb);
    assert_eq!(x.labels, y.labels);
    assert_eq!(x.depth_m, y.depth_m);
    // some seed among a few changes the image (probabilities below 1 may skip one)
    assert!((12..20).any(|s| run(s).rgb != x.rgb));
}

#[test]
fn a_wrong_buffer_is_an_error_not_a_panic() {
    let mut ex = example();
    ex.rgb.pop();
    assert!(EncoderAugment::default().apply(&mut ex, (H, W), 1).is_err());
}

/// A level camera 1.73 m above flat ground, horizon at row 4, and an example whose depth targets
/// are that flat ground (0 above the horizon).
fn ground_example() -> (veila_geom::PinholeCamera, EncoderExample) {
    let axes = glam::Mat4::from_cols(
        glam::Vec4::new(0., 0., 1., 0.),
        glam::Vec4::new(-1., 0., 0., 0.),
        glam::Vec4::new(0., -1., 0., 0.),
        glam::Vec4::W,
    );
    let k = [
        [30.0, 0.0, W as f32 / 2.0, 0.0],
        [0.0, 30.0, 4.0, 0.0],
        [0.0, 0.0, 1.0, 0.0],
    ];
    let cam = veila_geom::PinholeCamera::new(k, axes, W as u32, H as u32).unwrap();
    let mut ex = example();
    ex.depth_m = veila_geom::flat_ground_depth_map_m(&cam, -1.73);
    ex.camera = Some(cam);
    (cam, ex)
}

#[test]
fn the_camera_follows_the_crop_so_the_ground_prior_agrees_with_the_depth_targets() {
    let (cam, orig) = ground_example();
    // no crop: the camera is left exactly as it was
    let mut ex = orig.clone();
    zoom_only([1.0, 1.0]).apply(&mut ex, (H, W), 5).unwrap();
    assert_eq!(ex.camera, Some(cam));
    for (seed, s) in [(3u64, 1.25f32), (8, 1.1), (21, 1.3)] {
        let mut ex = orig.clone();
        zoom_only([s, s]).apply(&mut ex, (H, W), seed).unwrap();
        let moved = ex.camera.unwrap();
        assert_ne!(moved, cam);
        // the flat ground through the returned camera against the (divided, nearest-resampled)
        // targets: equal up to the half-pixel of nearest sampling, never off by the zoom
        let prior = veila_geom::flat_ground_depth_map_m(&moved, -1.73);
        let mut rel = Vec::new();
        for v in 12..H {
            for u in 0..W {
                let (p, t) = (prior[v * W + u], ex.depth_m[v * W + u]);
                assert!(p > 0.0 && t > 0.0, "({u}, {v})");
                rel.push((p - t).abs() / t);
            }
        }
        rel.sort_by(f32::total_cmp);
        let median = rel[rel.len() / 2];
        let worst = rel[rel.len() - 1];
        assert!(
            median < 0.03 && worst < 0.12,
            "zoom {s}: median {median}, worst {worst}"
        );
        // both put the horizon in the same place, up to the row of nearest sampling
        let zeros = |m: &[f32]| m.iter().filter(|&&d| d == 0.0).count();
        assert!(zeros(&prior).abs_diff(zeros(&ex.depth_m)) <= W, "zoom {s}");
    }
}
