//! `veila project`, `veila unproject`, `veila render`: point files <-> range images, and previews.
//!
//! Every command checks its outputs first (not an input, named for the format written, absent unless
//! `--force`), renders all of them in memory and publishes them together
//! ([`staging::publish_files`]), so a failure never leaves part of the output behind.

use std::path::{Path, PathBuf};

use anyhow::{Result, bail};
use clap::{Args, Subcommand};
use veila_data::image_io::{encode_png, read_rgb_image};
use veila_data::range_exr::{encode_range_exr, read_range_exr};
use veila_data::scan::{LoadedPoints, PointFormat, read_points};
use veila_data::semantic_kitti::{LabelMap, read_labels};
use veila_data::spec::{read_calib_camera, sensor_from_spec};
use veila_data::vis::render::{
    BevOptions, OverlayOptions, RangePreview, render_bev, render_intensity, render_labels,
    render_overlay, render_range,
};
use veila_geom::{BeamLayout, LidarSensor, ProjectionOptions, Projector, RangeImage, RowSource};

use crate::staging::{self, Inputs, check_ext};

/// Data commands.
#[derive(Debug, Subcommand)]
pub(crate) enum DataCmd {
    /// Project a point file (.bin, .pcd.bin, .ply, range .exr) into a range-image EXR.
    Project(ProjectArgs),
    /// Turn a range-image EXR back into points (.ply or KITTI .bin).
    Unproject(UnprojectArgs),
    /// Render previews of a scan: bird's-eye view, range image, and points over the camera image.
    Render(RenderArgs),
}

#[derive(Debug, Args)]
pub(crate) struct ProjectArgs {
    /// The scan: KITTI .bin, nuScenes .pcd.bin, .ply or a range .exr (format detected).
    scan: PathBuf,
    #[arg(long, help = crate::choices::sensor_spec_help(
        "Default: hdl32e for nuScenes scans, the stored sensor for .exr, hdl64e otherwise."
    ))]
    sensor: Option<String>,
    /// Output range image (.exr).
    #[arg(long)]
    out: PathBuf,
    /// Also write a range preview PNG.
    #[arg(long)]
    png: Option<PathBuf>,
    /// Also write an intensity preview PNG.
    #[arg(long)]
    intensity_png: Option<PathBuf>,
    /// Per-point SemanticKITTI labels (.label) to carry into the range image.
    #[arg(long)]
    labels: Option<PathBuf>,
    /// semantic-kitti.yaml, for a label preview (needs labels from --labels or the PLY).
    #[arg(long, requires = "label_png")]
    label_map: Option<PathBuf>,
    /// Also write a label preview PNG (SemanticKITTI colours).
    #[arg(long, requires = "label_map")]
    label_png: Option<PathBuf>,
    /// Replace output files that exist.
    #[arg(long)]
    force: bool,
}

#[derive(Debug, Args)]
pub(crate) struct UnprojectArgs {
    /// A range-image EXR written by `veila project` (it carries its sensor).
    input: PathBuf,
    /// Output points: .ply (x, y, z, intensity, label) or .bin (KITTI records).
    #[arg(long)]
    out: PathBuf,
    /// Replace the output file if it exists.
    #[arg(long)]
    force: bool,
}

#[derive(Debug, Args)]
pub(crate) struct RenderArgs {
    /// The scan: KITTI .bin, nuScenes .pcd.bin, .ply or a range .exr (format detected).
    scan: PathBuf,
    /// Bird's-eye-view PNG.
    #[arg(long)]
    bev: Option<PathBuf>,
    /// Range-image preview PNG.
    #[arg(long)]
    range: Option<PathBuf>,
    #[arg(long, help = crate::choices::sensor_spec_help(
        "For the range preview; default as for `project`."
    ))]
    sensor: Option<String>,
    /// Camera image for the overlay.
    #[arg(long, requires_all = ["calib", "overlay"])]
    image: Option<PathBuf>,
    /// Calibration: KITTI object calib/*.txt, KITTI odometry calib.txt or nuScenes per-sample JSON.
    #[arg(long, requires_all = ["image", "overlay"])]
    calib: Option<PathBuf>,
    /// Overlay PNG: LiDAR points on the camera image, coloured by depth.
    #[arg(long, requires_all = ["image", "calib"])]
    overlay: Option<PathBuf>,
    /// Which camera of the calibration: the KITTI projection matrix index (0-3, default 2 =
    /// image_2) or the nuScenes channel (default CAM_FRONT).
    #[arg(long, value_name = "N")]
    camera: Option<String>,
    /// Half the side of the bird's-eye view, metres, 1 to 1000 (at most 16384 pixels a side).
    #[arg(long, default_value_t = 50.0, value_parser = crate::bounds::float32(1.0, 1000.0))]
    bev_extent_m: f32,
    /// Bird's-eye-view resolution, metres per pixel, 0.01 to 100.
    #[arg(long, default_value_t = 0.1, value_parser = crate::bounds::float32(0.01, 100.0))]
    bev_resolution_m: f32,
    /// Replace output files that exist.
    #[arg(long)]
    force: bool,
}

pub(crate) fn run(cmd: DataCmd) -> Result<()> {
    match cmd {
        DataCmd::Project(a) => project(a),
        DataCmd::Unproject(a) => unproject(a),
        DataCmd::Render(a) => render(a),
    }
}

fn load(scan: &Path) -> Result<LoadedPoints> {
    // the error already names the file and the problem
    let l = read_points(scan)?;
    println!(
        "{}: {} points ({}), {} non-finite dropped",
        scan.display(),
        l.cloud.len(),
        l.format,
        l.dropped_non_finite
    );
    Ok(l)
}

fn pick_sensor(spec: Option<&str>, loaded: &LoadedPoints) -> Result<LidarSensor> {
    Ok(match (spec, &loaded.sensor) {
        (Some(s), _) => sensor_from_spec(s)?,
        (None, Some(stored)) => stored.clone(),
        (None, None) if loaded.format == PointFormat::NuScenesPcdBin => LidarSensor::hdl32e(),
        (None, None) => LidarSensor::hdl64e(),
    })
}

fn project_points(scan: &Path, loaded: &LoadedPoints, sensor: &LidarSensor) -> Result<RangeImage> {
    let projector = Projector::new(sensor, ProjectionOptions::default())?;
    let ring_mode = matches!(
        sensor.beams,
        BeamLayout::PerBeam {
            row_source: RowSource::Ring,
            ..
        }
    );
    let rings = loaded.cloud.ring.as_deref();
    if ring_mode && rings.is_none() {
        bail!(
            "{}: the sensor takes rows from ring indices, but this scan has none (use a uniform sensor)",
            scan.display()
        );
    }
    let (mut img, stats) = projector.project(
        &loaded.cloud.xyz,
        Some(&loaded.cloud.intensity),
        if ring_mode { rings } else { None },
    )?;
    if let Some(l) = &loaded.cloud.label {
        img.gather_labels(l)?;
    }
    println!(
        "projected into {}x{}: {} pixels, {} occluded, {} rejected (range/field of view)",
        sensor.rows,
        sensor.cols,
        stats.written,
        stats.occluded,
        stats.rejected.total()
    );
    Ok(img)
}

fn intensity_max(loaded: &LoadedPoints) -> f32 {
    if loaded.format == PointFormat::NuScenesPcdBin {
        255.0
    } else {
        1.0
    }
}

/// Check a command's outputs before any work: names, inputs, existing files.
fn preflight(outputs: &[(&Path, &str, &[&str])], inputs: &Inputs, force: bool) -> Result<()> {
    for (p, what, exts) in outputs {
        check_ext(p, what, exts)?;
    }
    let dests: Vec<&Path> = outputs.iter().map(|(p, _, _)| *p).collect();
    staging::check_outputs(&dests, inputs, force, false)
}

fn project(a: ProjectArgs) -> Result<()> {
    let mut inputs = Inputs::new();
    inputs
        .add(&a.scan)
        .add_opt(a.labels.as_ref())
        .add_opt(a.label_map.as_ref());
    if let Some(s) = &a.sensor {
        inputs.add(Path::new(s));
    }
    let mut outs: Vec<(&Path, &str, &[&str])> =
        vec![(a.out.as_path(), "--out (a range image)", &["exr"][..])];
    for p in [&a.png, &a.intensity_png, &a.label_png]
        .into_iter()
        .flatten()
    {
        outs.push((p.as_path(), "a preview", &["png"][..]));
    }
    preflight(&outs, &inputs, a.force)?;
    let mut loaded = load(&a.scan)?;
    if let Some(lp) = &a.labels {
        // labels index the file's records: only valid when no record was dropped
        if loaded.dropped_non_finite > 0 {
            bail!(
                "{}: {} non-finite points were dropped, so per-point labels from {} no longer line up",
                a.scan.display(),
                loaded.dropped_non_finite,
                lp.display()
            );
        }
        loaded.cloud.label = Some(read_labels(lp, Some(loaded.cloud.len()))?);
    }
    let sensor = pick_sensor(a.sensor.as_deref(), &loaded)?;
    let img = project_points(&a.scan, &loaded, &sensor)?;
    let mut outputs: Vec<(PathBuf, Vec<u8>)> =
        vec![(a.out.clone(), encode_range_exr(&sensor, &img)?)];
    if let Some(p) = &a.png {
        let preview = RangePreview {
            far_m: sensor.max_range_m.min(80.0),
            ..Default::default()
        };
        outputs.push((p.clone(), encode_png(&render_range(&img, &preview))?));
    }
    if let Some(p) = &a.intensity_png {
        outputs.push((
            p.clone(),
            encode_png(&render_intensity(&img, intensity_max(&loaded), 4))?,
        ));
    }
    if let (Some(p), Some(mp)) = (&a.label_png, &a.label_map) {
        let map = LabelMap::read(mp)?;
        let Some(png) = render_labels(&img, &map, 4) else {
            bail!(
                "--label-png needs labels: pass --labels FILE.label or a PLY with a label property"
            );
        };
        outputs.push((p.clone(), encode_png(&png)?));
    }
    write_all(&outputs, &inputs, a.force)
}

fn write_all(outputs: &[(PathBuf, Vec<u8>)], inputs: &Inputs, force: bool) -> Result<()> {
    staging::publish_files(outputs, inputs, force, false)?;
    for (p, _) in outputs {
        println!("wrote {}", p.display());
    }
    Ok(())
}

fn unproject(a: UnprojectArgs) -> Result<()> {
    let mut inputs = Inputs::new();
    inputs.add(&a.input);
    preflight(
        &[(a.out.as_path(), "--out (points)", &["ply", "bin"][..])],
        &inputs,
        a.force,
    )?;
    let exr = read_range_exr(&a.input)?;
    let cloud = exr.to_points()?;
    let name = a
        .out
        .file_name()
        .map(|n| n.to_string_lossy().to_lowercase())
        .unwrap_or_default();
    let bytes = if name.ends_with(".ply") {
        let mut buf = Vec::new();
        veila_data::ply::encode_ply(&cloud, &mut buf)?;
        buf
    } else if name.ends_with(".bin") && !name.ends_with(".pcd.bin") {
        veila_data::scan::encode_kitti_bin(&cloud)
    } else {
        bail!("{}: the output must end in .ply or .bin", a.out.display());
    };
    println!(
        "{}: {} points from a {}x{} range image",
        a.input.display(),
        cloud.len(),
        exr.sensor.rows,
        exr.sensor.cols
    );
    write_all(&[(a.out, bytes)], &inputs, a.force)
}

fn render(a: RenderArgs) -> Result<()> {
    if a.bev.is_none() && a.range.is_none() && a.overlay.is_none() {
        bail!("nothing to render: give --bev, --range and/or --overlay");
    }
    let mut inputs = Inputs::new();
    inputs
        .add(&a.scan)
        .add_opt(a.image.as_ref())
        .add_opt(a.calib.as_ref());
    if let Some(s) = &a.sensor {
        inputs.add(Path::new(s));
    }
    let outs: Vec<(&Path, &str, &[&str])> = [&a.bev, &a.range, &a.overlay]
        .into_iter()
        .flatten()
        .map(|p| (p.as_path(), "a preview", &["png"][..]))
        .collect();
    preflight(&outs, &inputs, a.force)?;
    let loaded = load(&a.scan)?;
    let mut outputs: Vec<(PathBuf, Vec<u8>)> = Vec::new();
    if let Some(p) = &a.bev {
        let opts = BevOptions {
            half_extent_m: a.bev_extent_m,
            resolution_m: a.bev_resolution_m,
            ..Default::default()
        };
        outputs.push((p.clone(), encode_png(&render_bev(&loaded.cloud, &opts)?)?));
    }
    if let Some(p) = &a.range {
        let img = if loaded.format == PointFormat::RangeExr && a.sensor.is_none() {
            read_range_exr(&a.scan)?.image
        } else {
            let sensor = pick_sensor(a.sensor.as_deref(), &loaded)?;
            project_points(&a.scan, &loaded, &sensor)?
        };
        outputs.push((
            p.clone(),
            encode_png(&render_range(&img, &RangePreview::default()))?,
        ));
    }
    if let (Some(ip), Some(cp), Some(op)) = (&a.image, &a.calib, &a.overlay) {
        let image = read_rgb_image(ip)?;
        let camera =
            read_calib_camera(cp, a.camera.as_deref(), image.width(), image.height())?.camera;
        let min_depth = if loaded.format == PointFormat::NuScenesPcdBin {
            1.0
        } else {
            0.1
        };
        let ov = render_overlay(
            &image,
            &camera,
            &loaded.cloud.xyz,
            &OverlayOptions {
                min_depth_m: min_depth,
                ..Default::default()
            },
        )?;
        println!(
            "overlay: {} points land in the {}x{} image",
            ov.drawn,
            image.width(),
            image.height()
        );
        outputs.push((op.clone(), encode_png(&ov.image)?));
    }
    write_all(&outputs, &inputs, a.force)
}
