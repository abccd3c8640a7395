//! Appearance randomisation of the scene simulator's camera: renders frame 0 of
//! `scenes/straight_road.toml` (and the junction) at the default 1242x375 with randomisation off and
//! on for a few seeds, writes the images to a folder and prints the render times.
//!
//! ```sh
//! cargo run -p veila-data --features sim --example sim_appearance -- /tmp/veila_appearance
//! ```

use std::path::{Path, PathBuf};
use std::time::Instant;

use veila_data::sim::{CameraRenderOptions, Scene, SceneConfig, SimCalib, SimImage};

/// Best-of-three wall time of a render, seconds, and the image.
fn timed(scene: &Scene, cfg: &SceneConfig) -> Result<(f64, SimImage), veila_data::Error> {
    let snap = scene.snapshot(0);
    let cam = SimCalib::from_config(&cfg.camera).camera()?;
    let opts = CameraRenderOptions::from(&cfg.camera);
    let mut best = f64::INFINITY;
    let mut img = None;
    for _ in 0..3 {
        let t = Instant::now();
        let i = snap.render_camera(&cam, &opts)?;
        best = best.min(t.elapsed().as_secs_f64());
        img = Some(i);
    }
    Ok((best, img.expect("three renders")))
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let out = std::env::args()
        .nth(1)
        .map_or_else(|| PathBuf::from("/tmp/veila_appearance"), PathBuf::from);
    std::fs::create_dir_all(&out)?;
    let scenes = Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenes");
    for (name, seeds) in [
        ("straight_road", &[0u64, 1, 2, 3][..]),
        ("junction", &[5, 6][..]),
    ] {
        let off = SceneConfig::from_file(&scenes.join(format!("{name}.toml")))?;
        let mut on = off.clone();
        on.appearance.randomize = true;
        for &seed in seeds {
            for (tag, cfg) in [("off", &off), ("on", &on)] {
                if tag == "off" && !matches!(seed, 0 | 1 | 5) {
                    continue;
                }
                let scene = Scene::generate(cfg, seed)?;
                let (t, img) = timed(&scene, cfg)?;
                let l = scene.snapshot(0).lighting;
                let file = out.join(format!("{name}_{seed}_{tag}.png"));
                img.to_rgb_image()?.save(&file)?;
                println!(
                    "{name} seed {seed} randomize {tag}: {t:.3} s (best of 3), sun el {:.1} az {:.1} -> {}",
                    l.sun_elevation_deg,
                    l.sun_azimuth_deg,
                    file.display()
                );
            }
        }
    }
    Ok(())
}
