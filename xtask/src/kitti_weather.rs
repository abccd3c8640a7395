//! `cargo xtask kitti-weather`: the KITTI-Weather benchmark from a KITTI-layout dataset: clean, night,
//! fog and snow variants of every frame, with physical weather (`veila_data::weather`).
//!
//! Output: `OUT/<variant>/{velodyne,image_2,calib,effects}/NNNNNN.*` and `OUT/<variant>/weather.json`.
//! Frame `k` uses seed `seed + k`, so every frame draws its own particles and noise, reproducibly.

use std::path::PathBuf;

use anyhow::{Context, Result, bail};
use clap::Args;
use indicatif::{ProgressBar, ProgressStyle};
use veila_data::kitti::KittiObjectDataset;
use veila_data::weather::files::{FrameFiles, FrameOutputs, process_frame};
use veila_data::weather::{Preset, WeatherConfig, WeatherSim};

/// Arguments of `cargo xtask kitti-weather`.
#[derive(Debug, Args)]
pub struct KittiWeatherArgs {
    /// KITTI object root (holding training/, or a split folder with velodyne/, image_2/, calib/).
    #[arg(long)]
    pub root: PathBuf,
    /// Output folder.
    #[arg(long)]
    pub out: PathBuf,
    /// Variants to build (comma separated): clean, night, fog, snow.
    #[arg(long, value_delimiter = ',', default_value = "clean,night,fog,snow")]
    pub variants: Vec<String>,
    /// Base seed (frame k uses seed + k).
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Only the first N frames.
    #[arg(long)]
    pub limit: Option<usize>,
}

fn preset_of(name: &str) -> Result<Preset> {
    Ok(match name {
        "clean" => Preset::KittiClean,
        "night" => Preset::KittiNight,
        "fog" => Preset::KittiFog,
        "snow" => Preset::KittiSnow,
        other => {
            bail!("unknown KITTI-Weather variant '{other}' (expected clean, night, fog, snow)")
        }
    })
}

/// Build the variants.
pub fn run(a: KittiWeatherArgs) -> Result<()> {
    let ds = KittiObjectDataset::open(&a.root)?;
    let base = ds.base().to_path_buf();
    let ids: Vec<String> = ds
        .ids()
        .iter()
        .take(a.limit.unwrap_or(usize::MAX))
        .cloned()
        .collect();
    if ids.is_empty() {
        bail!("{}: no scans in velodyne/", base.display());
    }
    let presets = a
        .variants
        .iter()
        .map(|v| Ok((v.clone(), preset_of(v)?)))
        .collect::<Result<Vec<_>>>()?;
    // every input must exist before anything is written
    for id in &ids {
        for (dir, ext) in [("image_2", "png"), ("calib", "txt")] {
            let p = base.join(dir).join(format!("{id}.{ext}"));
            if !p.is_file() {
                bail!(
                    "{}: missing (every frame needs velodyne/, image_2/ and calib/)",
                    p.display()
                );
            }
        }
    }
    let cfg = WeatherConfig::default();
    let bar = ProgressBar::new((ids.len() * presets.len()) as u64);
    bar.set_style(
        ProgressStyle::with_template(
            "{prefix:>8.bold} [{bar:30}] {pos}/{len} {per_sec} eta {eta} {msg}",
        )
        .unwrap_or_else(|_| ProgressStyle::default_bar())
        .progress_chars("=> "),
    );
    bar.set_prefix("weather");
    for (name, preset) in &presets {
        let vdir = a.out.join(name);
        for sub in ["velodyne", "image_2", "calib", "effects"] {
            std::fs::create_dir_all(vdir.join(sub))
                .with_context(|| format!("cannot create {}", vdir.display()))?;
        }
        let sim = WeatherSim::new(&preset.weather(), &cfg)?;
        let json = serde_json::to_string_pretty(&preset.weather())?;
        veila_data::atomic::write_atomic(&vdir.join("weather.json"), json.as_bytes())?;
        for (k, id) in ids.iter().enumerate() {
            bar.set_message(format!("{name} {id}"));
            let frame_sim = sim.with_seed(a.seed.wrapping_add(k as u64));
            let files = FrameFiles {
                scan: base.join("velodyne").join(format!("{id}.bin")),
                image: Some(base.join("image_2").join(format!("{id}.png"))),
                calib: Some(base.join("calib").join(format!("{id}.txt"))),
                labels: None,
            };
            let outs = FrameOutputs {
                scan: vdir.join("velodyne").join(format!("{id}.bin")),
                image: Some(vdir.join("image_2").join(format!("{id}.png"))),
            };
            let report = process_frame(&frame_sim, &files, &outs)
                .with_context(|| format!("frame {id} ({name})"))?;
            let calib_src = files.calib.as_ref().expect("set above");
            let calib = std::fs::read(calib_src)
                .with_context(|| format!("cannot read {}", calib_src.display()))?;
            veila_data::atomic::write_atomic(
                &vdir.join("calib").join(format!("{id}.txt")),
                &calib,
            )?;
            veila_data::atomic::write_atomic(
                &vdir.join("effects").join(format!("{id}.json")),
                report.to_json()?.as_bytes(),
            )?;
            bar.inc(1);
        }
    }
    bar.finish_with_message("done");
    eprintln!(
        "wrote {} frames x {} variants to {}",
        ids.len(),
        presets.len(),
        a.out.display()
    );
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn builds_variants_of_the_real_kitti_frames() {
        let root =
            std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/data/real/kitti");
        if !root.join("training/velodyne/000000.bin").is_file() {
            eprintln!("skipping: {} not found", root.display());
            return;
        }
        let out = std::env::temp_dir().join(format!("veila-kitti-weather-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&out);
        run(KittiWeatherArgs {
            root: root.clone(),
            out: out.clone(),
            variants: vec!["clean".into(), "night".into()],
            seed: 0,
            limit: Some(1),
        })
        .unwrap();
        let src = root.join("training");
        let read = |p: std::path::PathBuf| {
            std::fs::read(&p).unwrap_or_else(|e| panic!("{}: {e}", p.display()))
        };
        assert_eq!(
            read(out.join("clean/velodyne/000000.bin")),
            read(src.join("velodyne/000000.bin"))
        );
        assert_eq!(
            read(out.join("clean/image_2/000000.png")),
            read(src.join("image_2/000000.png"))
        );
        assert_eq!(
            read(out.join("night/velodyne/000000.bin")),
            read(src.join("velodyne/000000.bin"))
        );
        assert_ne!(
            read(out.join("night/image_2/000000.png")),
            read(src.join("image_2/000000.png"))
        );
        assert_eq!(
            read(out.join("night/calib/000000.txt")),
            read(src.join("calib/000000.txt"))
        );
        let fx: serde_json::Value =
            serde_json::from_slice(&read(out.join("night/effects/000000.json"))).unwrap();
        assert_eq!(fx["camera"][0]["effect"], "darken");
        assert!(!out.join("clean/velodyne/000001.bin").exists(), "--limit 1");
        assert!(
            run(KittiWeatherArgs {
                root,
                out: out.clone(),
                variants: vec!["rainbow".into()],
                seed: 0,
                limit: None
            })
            .is_err()
        );
        let _ = std::fs::remove_dir_all(&out);
    }
}
