//! `veila._veila`: the Python extension module. Thin wrappers: every number comes from the Rust crates
//! (`veila-metrics`, `veila-geom`, `veila-data`, `veila-diffusion`); this file only converts numpy
//! arrays and errors. The public Python API, with docstrings and type hints, is `veila/__init__.py`
//! and `veila/_veila.pyi`.

use std::path::{Path, PathBuf};

use candle_core::Device;
use glam::{Mat4, Vec3};
use numpy::ndarray::{Array1, Array2, ArrayView2};
use numpy::{
    IntoPyArray, PyArray1, PyArray2, PyReadonlyArray2, PyReadonlyArrayDyn, PyUntypedArrayMethods,
};
use pyo3::exceptions::{PyRuntimeError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::PyDict;

use veila_diffusion::SamplerName;
use veila_diffusion::app::bundle::Bundle;
use veila_diffusion::app::{GenerateOptions, RigImage, SamplerChoice, ScanPipeline};
use veila_geom::{LidarSensor, PinholeCamera, RangeImage, RayTable, Region, SensorPreset};
use veila_metrics::protocol::{PeerProtocol, PeerSummary};

fn value_err(e: impl std::fmt::Display) -> PyErr {
    PyValueError::new_err(e.to_string())
}

fn runtime_err(e: impl std::fmt::Display) -> PyErr {
    PyRuntimeError::new_err(e.to_string())
}

fn protocol(name: &str) -> PyResult<PeerProtocol> {
    PeerProtocol::from_name(name).ok_or_else(|| {
        let all: Vec<_> = PeerProtocol::ALL.iter().map(|p| p.name()).collect();
        value_err(format!("unknown protocol {name:?}; one of {all:?}"))
    })
}

fn region(name: &str) -> PyResult<Region> {
    match name {
        "all" => Ok(Region::All),
        "front" => Ok(Region::Front),
        "rear" => Ok(Region::Rear),
        _ => Err(value_err(format!(
            "unknown region {name:?}; one of all, front, rear"
        ))),
    }
}

/// `(N, >=3)` float array → points (columns 0..3).
fn points_of(a: &Bound<'_, PyAny>, what: &str) -> PyResult<Vec<Vec3>> {
    let arr: PyReadonlyArray2<'_, f64> = match a.extract() {
        Ok(x) => x,
        Err(_) => {
            let f: PyReadonlyArray2<'_, f32> = a.extract().map_err(|_| {
                value_err(format!(
                    "{what}: expected a 2-D float32 or float64 array of shape (N, 3+)"
                ))
            })?;
            let v = f.as_array();
            return rows_to_points(v.mapv(|x| x as f64).view(), what);
        }
    };
    rows_to_points(arr.as_array(), what)
}

fn rows_to_points(v: ArrayView2<'_, f64>, what: &str) -> PyResult<Vec<Vec3>> {
    if v.ncols() < 3 {
        return Err(value_err(format!(
            "{what}: shape {:?}, need (N, 3+) (x, y, z columns)",
            v.shape()
        )));
    }
    Ok(v.rows()
        .into_iter()
        .map(|r| Vec3::new(r[0] as f32, r[1] as f32, r[2] as f32))
        .collect())
}

fn image_of(a: &Bound<'_, PyAny>, what: &str) -> PyResult<(Vec<f32>, Vec<usize>)> {
    if let Ok(x) = a.extract::<PyReadonlyArrayDyn<'_, f32>>() {
        return Ok((x.as_array().iter().copied().collect(), x.shape().to_vec()));
    }
    if let Ok(x) = a.extract::<PyReadonlyArrayDyn<'_, f64>>() {
        return Ok((
            x.as_array().iter().map(|&v| v as f32).collect(),
            x.shape().to_vec(),
        ));
    }
    Err(value_err(format!(
        "{what}: expected a float32 or float64 array"
    )))
}

fn prepared_to_array(py: Python<'_>, pts: &[[f64; 3]]) -> Py<PyArray2<f64>> {
    let mut a = Array2::<f64>::zeros((pts.len(), 3));
    for (i, p) in pts.iter().enumerate() {
        for k in 0..3 {
            a[[i, k]] = p[k];
        }
    }
    a.into_pyarray(py).unbind()
}

/// The points a protocol's metric sees for one raw scan.
#[pyfunction]
#[pyo3(signature = (points, protocol = "r2dm"))]
fn prepare_scan(
    py: Python<'_>,
    points: &Bound<'_, PyAny>,
    protocol: &str,
) -> PyResult<Py<PyArray2<f64>>> {
    let p = self::protocol(protocol)?;
    let pts = points_of(points, "points")?;
    let out = py
        .detach(|| p.prepare_scan(&pts, "points"))
        .map_err(value_err)?;
    Ok(prepared_to_array(py, &out))
}

/// The samples of a peer range-image array, each as the points its protocol's metric sees.
fn samples_of(
    image: &Bound<'_, PyAny>,
    p: PeerProtocol,
    what: &str,
) -> PyResult<Vec<Vec<[f64; 3]>>> {
    let (data, shape) = image_of(image, what)?;
    let (n, c, h, w) = p.split_samples(&shape).map_err(value_err)?;
    let per = c * h * w;
    (0..n)
        .map(|i| {
            p.points_from_image(&data[i * per..(i + 1) * per], c, h, w, what)
                .map_err(value_err)
        })
        .collect()
}

/// Points of each sample in a peer range-image array.
#[pyfunction]
#[pyo3(signature = (image, protocol = "r2dm"))]
fn points_from_image(
    py: Python<'_>,
    image: &Bound<'_, PyAny>,
    protocol: &str,
) -> PyResult<Vec<Py<PyArray2<f64>>>> {
    let p = self::protocol(protocol)?;
    Ok(samples_of(image, p, "image")?
        .iter()
        .map(|s| prepared_to_array(py, s))
        .collect())
}

fn prepared_set(
    set: &Bound<'_, PyAny>,
    p: PeerProtocol,
    images: bool,
    what: &str,
) -> PyResult<Vec<Vec<[f64; 3]>>> {
    let mut out = Vec::new();
    for (i, item) in set.try_iter()?.enumerate() {
        let item = item?;
        let label = format!("{what}[{i}]");
        if images {
            out.extend(samples_of(&item, p, &label)?);
        } else {
            let pts = points_of(&item, &label)?;
            out.push(p.prepare_scan(&pts, &label).map_err(value_err)?);
        }
    }
    if out.is_empty() {
        return Err(value_err(format!("{what} is empty")));
    }
    Ok(out)
}

/// JSD and MMD of a protocol's whole pipeline.
#[pyfunction]
#[pyo3(signature = (generated, reference, protocol = "r2dm", region = "all", generated_images = false, reference_images = false))]
fn score<'py>(
    py: Python<'py>,
    generated: &Bound<'py, PyAny>,
    reference: &Bound<'py, PyAny>,
    protocol: &str,
    region: &str,
    generated_images: bool,
    reference_images: bool,
) -> PyResult<Bound<'py, PyDict>> {
    let p = self::protocol(protocol)?;
    let r = self::region(region)?;
    let g = prepared_set(generated, p, generated_images, "generated")?;
    let rf = prepared_set(reference, p, reference_images, "reference")?;
    let metrics = py
        .detach(|| -> veila_metrics::Result<_> {
            let summ =
                |set: &[Vec<[f64; 3]>], what: &str| -> veila_metrics::Result<Vec<PeerSummary>> {
                    set.iter()
                        .enumerate()
                        .map(|(i, s)| p.summarise(s, r, &format!("{what} scan {i}")))
                        .collect()
                };
            p.score(&summ(&g, "generated")?, &summ(&rf, "reference")?)
        })
        .map_err(value_err)?;
    let d = PyDict::new(py);
    for m in metrics {
        d.set_item(m.name, m.value)?;
    }
    Ok(d)
}

fn raw_hists(
    set: &Bound<'_, PyAny>,
    r: Region,
    what: &str,
) -> PyResult<Vec<veila_metrics::bev::BevHistogram>> {
    let cfg = veila_metrics::bev::BevConfig::r2dm();
    let mut out = Vec::new();
    for (i, item) in set.try_iter()?.enumerate() {
        let pts = points_of(&item?, &format!("{what}[{i}]"))?;
        out.push(veila_metrics::bev::bev_histogram(&pts, &cfg, r, what).map_err(value_err)?);
    }
    Ok(out)
}

/// R2DM's BEV JSD on raw points (no projection, no range caps).
#[pyfunction]
#[pyo3(signature = (generated, reference, region = "all"))]
fn jsd_raw(
    generated: &Bound<'_, PyAny>,
    reference: &Bound<'_, PyAny>,
    region: &str,
) -> PyResult<f64> {
    let r = self::region(region)?;
    veila_metrics::dist::jsd(
        &raw_hists(generated, r, "generated")?,
        &raw_hists(reference, r, "reference")?,
    )
    .map_err(value_err)
}

/// R2DM's BEV MMD on raw points (no projection, no range caps).
#[pyfunction]
#[pyo3(signature = (generated, reference, region = "all"))]
fn mmd_raw(
    generated: &Bound<'_, PyAny>,
    reference: &Bound<'_, PyAny>,
    region: &str,
) -> PyResult<f64> {
    let r = self::region(region)?;
    veila_metrics::dist::mmd_r2dm_dense(
        &raw_hists(generated, r, "generated")?,
        &raw_hists(reference, r, "reference")?,
        veila_metrics::dist::MMD_SIGMA,
    )
    .map_err(value_err)
}

/// PyTorch3D-convention Chamfer distance of two point sets.
#[pyfunction]
fn chamfer_distance(a: &Bound<'_, PyAny>, b: &Bound<'_, PyAny>) -> PyResult<f64> {
    let (a, b) = (points_of(a, "a")?, points_of(b, "b")?);
    Ok(veila_metrics::chamfer::chamfer_distance(&a, &b)
        .map_err(value_err)?
        .value())
}

/// Fréchet distance of two feature matrices (rows = samples).
#[pyfunction]
#[pyo3(signature = (a, b, newton_schulz = None))]
fn frechet_distance(
    a: PyReadonlyArray2<'_, f64>,
    b: PyReadonlyArray2<'_, f64>,
    newton_schulz: Option<usize>,
) -> PyResult<f64> {
    let (a, b) = (a.as_array(), b.as_array());
    if a.ncols() != b.ncols() {
        return Err(value_err(format!(
            "a has {} columns, b has {}",
            a.ncols(),
            b.ncols()
        )));
    }
    let fa: Vec<f64> = a.iter().copied().collect();
    let fb: Vec<f64> = b.iter().copied().collect();
    let method = match newton_schulz {
        Some(iterations) => veila_metrics::fd::SqrtMethod::NewtonSchulz { iterations },
        None => veila_metrics::fd::SqrtMethod::Eigen,
    };
    veila_metrics::fd::frechet_distance_rows(&fa, &fb, a.ncols(), method).map_err(value_err)
}

fn sensor_of(name: &str, rows: Option<u32>, cols: Option<u32>) -> PyResult<LidarSensor> {
    // the presets are the library's one list (`SENSOR_PRESETS`)
    let mut s = name
        .parse::<SensorPreset>()
        .map_err(|e| value_err(format!("unknown sensor: {e}")))?
        .sensor();
    if let Some(r) = rows {
        s.rows = r;
    }
    if let Some(c) = cols {
        s.cols = c;
    }
    s.validate().map_err(value_err)?;
    Ok(s)
}

fn image2d<T: numpy::Element + Copy>(
    py: Python<'_>,
    v: &[T],
    rows: u32,
    cols: u32,
) -> PyResult<Py<PyArray2<T>>> {
    Ok(
        Array2::from_shape_vec((rows as usize, cols as usize), v.to_vec())
            .map_err(runtime_err)?
            .into_pyarray(py)
            .unbind(),
    )
}

/// Spherical projection of points to a Veila range image.
#[pyfunction]
#[pyo3(signature = (points, intensity = None, sensor = "hdl64e", rows = None, cols = None, rings = None))]
fn project<'py>(
    py: Python<'py>,
    points: &Bound<'py, PyAny>,
    intensity: Option<Vec<f32>>,
    sensor: &str,
    rows: Option<u32>,
    cols: Option<u32>,
    rings: Option<Vec<u16>>,
) -> PyResult<Bound<'py, PyDict>> {
    let s = sensor_of(sensor, rows, cols)?;
    let pts = points_of(points, "points")?;
    let (img, _) = veila_geom::Projector::new(&s, veila_geom::ProjectionOptions::default())
        .and_then(|p| p.project(&pts, intensity.as_deref(), rings.as_deref()))
        .map_err(value_err)?;
    let d = PyDict::new(py);
    d.set_item("range", image2d(py, &img.range_m, img.rows, img.cols)?)?;
    d.set_item(
        "intensity",
        image2d(py, &img.intensity, img.rows, img.cols)?,
    )?;
    d.set_item("mask", image2d(py, &img.mask, img.rows, img.cols)?)?;
    Ok(d)
}

/// Points of a Veila range image (one per pixel with a positive range).
#[pyfunction]
#[pyo3(signature = (range, intensity = None, sensor = "hdl64e"))]
fn unproject<'py>(
    py: Python<'py>,
    range: PyReadonlyArray2<'py, f32>,
    intensity: Option<PyReadonlyArray2<'py, f32>>,
    sensor: &str,
) -> PyResult<(Py<PyArray2<f32>>, Py<PyArray1<f32>>)> {
    let r = range.as_array();
    let (rows, cols) = (r.nrows() as u32, r.ncols() as u32);
    let s = sensor_of(sensor, Some(rows), Some(cols))?;
    let mut img = RangeImage::new_empty(rows, cols);
    img.range_m = r.iter().copied().collect();
    img.mask = img
        .range_m
        .iter()
        .map(|&v| v > 0.0 && v.is_finite())
        .collect();
    if let Some(i) = intensity {
        let i = i.as_array();
        if i.shape() != r.shape() {
            return Err(value_err("intensity must have the shape of range"));
        }
        img.intensity = i.iter().copied().collect();
    }
    for k in 0..img.range_m.len() {
        if !img.mask[k] {
            img.range_m[k] = 0.0;
            img.intensity[k] = 0.0;
        }
    }
    let un = RayTable::new(&s)
        .map_err(value_err)?
        .unproject(&img)
        .map_err(value_err)?;
    Ok(points_and_intensity(py, &un.points, &un.intensity))
}

fn points_and_intensity(
    py: Python<'_>,
    xyz: &[Vec3],
    intensity: &[f32],
) -> (Py<PyArray2<f32>>, Py<PyArray1<f32>>) {
    let mut a = Array2::<f32>::zeros((xyz.len(), 3));
    for (i, p) in xyz.iter().enumerate() {
        a[[i, 0]] = p.x;
        a[[i, 1]] = p.y;
        a[[i, 2]] = p.z;
    }
    (
        a.into_pyarray(py).unbind(),
        Array1::from(intensity.to_vec()).into_pyarray(py).unbind(),
    )
}

/// Reads a point file (KITTI .bin, nuScenes .pcd.bin, PLY, range EXR).
#[pyfunction]
#[pyo3(signature = (path, keep_nan_intensity = false))]
fn read_points(
    py: Python<'_>,
    path: PathBuf,
    keep_nan_intensity: bool,
) -> PyResult<(Py<PyArray2<f32>>, Py<PyArray1<f32>>)> {
    let keep = if keep_nan_intensity {
        veila_data::scan::Keep::FiniteXyz
    } else {
        veila_data::scan::Keep::FiniteRecords
    };
    let l = veila_data::scan::read_points_with(&path, keep).map_err(value_err)?;
    Ok(points_and_intensity(py, &l.cloud.xyz, &l.cloud.intensity))
}

/// Reads the float arrays of a peer's `.npy` / `.npz` sample set (pickles refused).
#[pyfunction]
fn read_sample_arrays<'py>(py: Python<'py>, path: PathBuf) -> PyResult<Bound<'py, PyDict>> {
    let arrays = veila_data::peer_samples::read_sample_arrays(&path).map_err(value_err)?;
    let d = PyDict::new(py);
    for a in arrays {
        let arr =
            numpy::ndarray::ArrayD::from_shape_vec(a.shape.clone(), a.data).map_err(runtime_err)?;
        d.set_item(a.name, arr.into_pyarray(py))?;
    }
    Ok(d)
}

/// A calibration file's camera for an image of `width x height`: `(K 3x4, cam_from_lidar 4x4)`.
#[pyfunction]
#[pyo3(signature = (path, width, height, camera = None))]
fn read_calibration(
    py: Python<'_>,
    path: PathBuf,
    width: u32,
    height: u32,
    camera: Option<&str>,
) -> PyResult<(Py<PyArray2<f32>>, Py<PyArray2<f32>>)> {
    let cam = veila_data::spec::read_calib_camera(&path, camera, width, height)
        .map_err(value_err)?
        .camera;
    let k = cam.intrinsics.transpose().to_cols_array_2d(); // rows
    let t = cam.cam_from_lidar.transpose().to_cols_array_2d();
    let k34 = Array2::from_shape_fn((3, 4), |(i, j)| k[i][j]);
    let t44 = Array2::from_shape_fn((4, 4), |(i, j)| t[i][j]);
    Ok((k34.into_pyarray(py).unbind(), t44.into_pyarray(py).unbind()))
}

// `DEFAULT_MODEL`: `(file name, bytes)` of `models/default`, written by build.rs
include!(concat!(env!("OUT_DIR"), "/default_model.rs"));

fn load_bundle(model_dir: Option<&Path>) -> Result<Bundle, String> {
    match model_dir {
        Some(d) => Bundle::from_dir(d, &Device::Cpu).map_err(|e| format!("{}: {e}", d.display())),
        None => Bundle::from_files(
            DEFAULT_MODEL,
            Path::new("<bundled models/default>"),
            &Device::Cpu,
        )
        .map_err(|e| e.to_string()),
    }
}

/// Generates a 360° scan from one camera image and its calibration with the bundled model.
#[pyfunction]
#[pyo3(signature = (image, intrinsics, cam_from_lidar, steps = None, seed = 0, model_dir = None, sampler = None, guidance = None, start_t = None))]
#[allow(clippy::too_many_arguments)] // a Python function's keyword arguments
fn generate<'py>(
    py: Python<'py>,
    image: numpy::PyReadonlyArray3<'py, u8>,
    intrinsics: PyReadonlyArray2<'py, f32>,
    cam_from_lidar: PyReadonlyArray2<'py, f32>,
    steps: Option<usize>,
    seed: u64,
    model_dir: Option<PathBuf>,
    sampler: Option<&str>,
    guidance: Option<f64>,
    start_t: Option<f64>,
) -> PyResult<Bound<'py, PyDict>> {
    let name = sampler
        .map(|s| s.parse::<SamplerName>())
        .transpose()
        .map_err(value_err)?;
    let img = image.as_array();
    let (h, w, c) = img.dim();
    if c != 3 || h == 0 || w == 0 {
        return Err(value_err(format!(
            "image: shape {:?}, need (H, W, 3) uint8 RGB",
            img.shape()
        )));
    }
    let k = intrinsics.as_array();
    let k34: [[f32; 4]; 3] = match k.dim() {
        (3, 3) => std::array::from_fn(|i| [k[[i, 0]], k[[i, 1]], k[[i, 2]], 0.0]),
        (3, 4) => std::array::from_fn(|i| [k[[i, 0]], k[[i, 1]], k[[i, 2]], k[[i, 3]]]),
        d => {
            return Err(value_err(format!(
                "intrinsics: shape {d:?}, need (3, 3) or (3, 4)"
            )));
        }
    };
    let t = cam_from_lidar.as_array();
    if t.dim() != (4, 4) {
        return Err(value_err(format!(
            "cam_from_lidar: shape {:?}, need (4, 4)",
            t.shape()
        )));
    }
    let t = Mat4::from_cols_array_2d(&std::array::from_fn(|j| std::array::from_fn(|i| t[[i, j]])));
    // a calibration handed in: checked as one read from a file is (positive focal lengths, the
    // principal point in the image, sane offsets)
    let camera = PinholeCamera::from_calibration(k34, t, w as u32, h as u32).map_err(value_err)?;
    if steps == Some(0) {
        return Err(value_err("steps must be at least 1"));
    }
    let rgb: Vec<u8> = img.iter().copied().collect();
    let bundle = py
        .detach(|| load_bundle(model_dir.as_deref()))
        .map_err(value_err)?;
    // the bundle's sampler with the caller's choices, as `veila generate`'s flags make it
    let choice = SamplerChoice {
        name,
        spacing: None,
        steps,
        guidance,
        start_t,
    };
    let options = GenerateOptions {
        sampler: choice.resolve(&bundle),
        samples: 1,
        seed,
        unconditional: false,
        residual_weight: 1.0,
    };
    options.check(&bundle).map_err(value_err)?;
    let scan = py
        .detach(|| -> Result<_, String> {
            let full = veila_data::image::RgbImage::from_raw(w as u32, h as u32, rgb)
                .ok_or("image buffer size")?;
            // the library's one path: fitted to the encoders, sampled in the model's frame, the
            // scan back in the calibration's LiDAR frame
            let rig = [RigImage {
                image: &full,
                camera: &camera,
            }];
            ScanPipeline::new(&bundle, &rig)
                .and_then(|p| p.generate(&options, |_, _| {}))
                .map_err(|e| e.to_string())?
                .into_iter()
                .next()
                .ok_or_else(|| "no scan generated".to_string())
        })
        .map_err(runtime_err)?;
    let (range, points) = (&scan.range, &scan.points);
    let d = PyDict::new(py);
    let (pts, inten) = points_and_intensity(py, &points.xyz, &points.intensity);
    d.set_item("points", pts)?;
    d.set_item("intensity", inten)?;
    d.set_item(
        "range",
        image2d(py, &range.range_m, range.rows, range.cols)?,
    )?;
    d.set_item("mask", image2d(py, &range.mask, range.rows, range.cols)?)?;
    Ok(d)
}

/// Reads a PNG or JPEG image as `(H, W, 3)` uint8 RGB.
#[pyfunction]
fn read_image(py: Python<'_>, path: PathBuf) -> PyResult<Py<numpy::PyArray3<u8>>> {
    let img = veila_data::image_io::read_rgb_image(&path).map_err(value_err)?;
    let (w, h) = img.dimensions();
    Ok(
        numpy::ndarray::Array3::from_shape_vec((h as usize, w as usize, 3), img.into_raw())
            .map_err(runtime_err)?
            .into_pyarray(py)
            .unbind(),
    )
}

/// The extension module.
#[pymodule]
fn _veila(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add(
        "PROTOCOLS",
        PeerProtocol::ALL
            .iter()
            .map(|p| p.name())
            .collect::<Vec<_>>(),
    )?;
    m.add(
        "SENSOR_PRESETS",
        SensorPreset::ALL.map(SensorPreset::as_str).to_vec(),
    )?;
    m.add_function(wrap_pyfunction!(prepare_scan, m)?)?;
    m.add_function(wrap_pyfunction!(points_from_image, m)?)?;
    m.add_function(wrap_pyfunction!(score, m)?)?;
    m.add_function(wrap_pyfunction!(jsd_raw, m)?)?;
    m.add_function(wrap_pyfunction!(mmd_raw, m)?)?;
    m.add_function(wrap_pyfunction!(chamfer_distance, m)?)?;
    m.add_function(wrap_pyfunction!(frechet_distance, m)?)?;
    m.add_function(wrap_pyfunction!(project, m)?)?;
    m.add_function(wrap_pyfunction!(unproject, m)?)?;
    m.add_function(wrap_pyfunction!(read_points, m)?)?;
    m.add_function(wrap_pyfunction!(read_sample_arrays, m)?)?;
    m.add_function(wrap_pyfunction!(read_calibration, m)?)?;
    m.add_function(wrap_pyfunction!(read_image, m)?)?;
    m.add_function(wrap_pyfunction!(generate, m)?)?;
    Ok(())
}
