//! Clear weather is a bit-exact identity for both sensors and draws no random numbers.
//!
//! This file holds a single test so that the process-wide stream counter is not disturbed by other
//! tests running in parallel.

use glam::Vec3;
use image::RgbImage;
use proptest::prelude::*;
use veila_data::PointCloud;
use veila_data::weather::{
    CameraInput, DepthMap, Intrinsics, LidarInput, Weather, WeatherConfig, WeatherSim,
    rng_streams_created,
};

fn cloud_strategy() -> impl Strategy<Value = PointCloud> {
    (0usize..300).prop_flat_map(|n| {
        (
            proptest::collection::vec((-1e3f32..1e3, -1e3f32..1e3, -50f32..50f32, 0f32..1.0), n),
            proptest::bool::ANY,
            proptest::bool::ANY,
        )
            .prop_map(|(pts, with_ring, with_label)| {
                let n = pts.len();
                PointCloud {
                    xyz: pts.iter().map(|p| Vec3::new(p.0, p.1, p.2)).collect(),
                    intensity: pts.iter().map(|p| p.3).collect(),
                    ring: with_ring.then(|| (0..n).map(|i| (i % 64) as u16).collect()),
                    label: with_label.then(|| (0..n).map(|i| (i * 7) as u32).collect()),
                }
            })
    })
}

fn image_strategy() -> impl Strategy<Value = RgbImage> {
    (1u32..24, 1u32..16).prop_flat_map(|(w, h)| {
        proptest::collection::vec(any::<u8>(), (w * h * 3) as usize)
            .prop_map(move |raw| RgbImage::from_raw(w, h, raw).expect("size"))
    })
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 64, ..ProptestConfig::default() })]
    #[test]
    fn clear_weather_is_bit_exact_identity_without_random_draws(
        cloud in cloud_strategy(),
        img in image_strategy(),
        seed in any::<u64>(),
        vis_inf in proptest::bool::ANY,
    ) {
        let before = rng_streams_created();
        // clear, and "fog" at infinite visibility, are the same: no effect
        let weather = Weather {
            fog_visibility_m: vis_inf.then_some(f64::INFINITY),
            seed,
            ..Weather::clear()
        };
        let sim = WeatherSim::new(&weather, &WeatherConfig::default()).unwrap();
        prop_assert!(sim.plan().lidar.is_empty());
        prop_assert!(sim.plan().camera.is_empty());
        let out = sim.apply_lidar(LidarInput::new(&cloud)).unwrap();
        prop_assert!(out.records.is_empty());
        prop_assert_eq!(out.cloud.xyz.len(), cloud.xyz.len());
        for (a, b) in out.cloud.xyz.iter().zip(&cloud.xyz) {
            prop_assert_eq!(a.to_array().map(f32::to_bits), b.to_array().map(f32::to_bits));
        }
        for (a, b) in out.cloud.intensity.iter().zip(&cloud.intensity) {
            prop_assert_eq!(a.to_bits(), b.to_bits());
        }
        prop_assert_eq!(&out.cloud.ring, &cloud.ring);
        prop_assert_eq!(&out.cloud.label, &cloud.label);
        // camera: with and without depth / intrinsics
        let depth = DepthMap { width: img.width(), height: img.height(), z_m: vec![10.0; (img.width() * img.height()) as usize] };
        let k = Intrinsics { fx: 100.0, fy: 100.0, cx: 5.0, cy: 5.0 };
        for input in [
            CameraInput { image: &img, depth: None, intrinsics: None },
            CameraInput { image: &img, depth: Some(&depth), intrinsics: Some(k) },
        ] {
            let cam = sim.apply_camera(input).unwrap();
            prop_assert!(cam.records.is_empty());
            prop_assert_eq!(cam.image.as_raw(), img.as_raw());
        }
        prop_assert_eq!(rng_streams_created(), before, "a random stream was constructed in clear weather");
    }
}
