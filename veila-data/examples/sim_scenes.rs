//! The open-country scenes of the simulator: renders frame 0 of `scenes/open_road.toml` and
//! `scenes/suburban.toml` for a few seeds at the scene's camera size (with the rig drawn for the
//! seed, on the road's grade where one is drawn), writes the images and a bird's-eye view of each LiDAR scan coloured by class to a folder,
//! and prints the drawn rig.
//!
//! ```sh
//! cargo run -p veila-data --features sim --example sim_scenes -- /tmp/veila_scenes
//! ```

use std::path::{Path, PathBuf};

use veila_data::semantic_kitti::class;
use veila_data::sim::{Scene, SceneConfig, SimScan};

/// A 400 x 400 px bird's-eye view of a scan (80 m ahead and behind, 80 m to each side), coloured by
/// class: buildings red, vegetation green, terrain olive, fences (guardrails) yellow, road grey.
fn birds_eye(scan: &SimScan) -> image::RgbImage {
    let mut img = image::RgbImage::new(400, 400);
    let labels = scan.points.label.as_deref().unwrap_or(&[]);
    for (p, l) in scan.points.xyz.iter().zip(labels) {
        let (u, v) = (200.0 - p.y * 2.5, 200.0 - p.x * 2.5);
        if !(0.0..400.0).contains(&u) || !(0.0..400.0).contains(&v) {
            continue;
        }
        let c = match (l & 0xFFFF) as u16 {
            class::BUILDING => [230, 40, 40],
            class::VEGETATION | class::TRUNK => [40, 200, 60],
            class::TERRAIN => [120, 120, 40],
            class::FENCE => [250, 230, 40],
            class::ROAD | class::LANE_MARKING => [120, 120, 120],
            class::SIDEWALK => [200, 160, 200],
            _ => [80, 160, 250],
        };
        img.put_pixel(u as u32, v as u32, image::Rgb(c));
    }
    img
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let out = std::env::args()
        .nth(1)
        .map_or_else(|| PathBuf::from("/tmp/veila_scenes"), PathBuf::from);
    std::fs::create_dir_all(&out)?;
    let scenes = Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenes");
    for (name, seeds) in [
        ("open_road", &[0u64, 1, 2, 3][..]),
        ("suburban", &[0, 1, 2, 3][..]),
    ] {
        let cfg = SceneConfig::from_file(&scenes.join(format!("{name}.toml")))?;
        for &seed in seeds {
            let scene = Scene::generate(&cfg, seed)?;
            let frame = scene.render_frame(0)?;
            let file = out.join(format!("{name}_{seed}.png"));
            frame.image.to_rgb_image()?.save(&file)?;
            birds_eye(&frame.scan).save(out.join(format!("{name}_{seed}_bev.png")))?;
            let c = scene.camera_config();
            println!(
                "{name} seed {seed}: grade {:+.2} %, LiDAR {:.3} m, camera {:+.3} m, pitch {:+.2} deg, \
                 {} points -> {}",
                scene.grade_percent(),
                scene.lidar_height_m(),
                c.up_m,
                c.pitch_down_deg,
                frame.scan.points.len(),
                file.display()
            );
        }
    }
    Ok(())
}
