//! Scans on a segmenter's grid: a scan projected with the segmenter's sensor ([`GridScan`], what
//! prediction runs on), and the compact training frame of a labelled scan ([`SegFrame`]: the
//! network's input and each pixel's train id), with its augmentation, its batches and the class
//! weights of the loss.
//!
//! A pixel's class is that of the point the projection keeps there (the nearest), as RangeNet++
//! and CENet label their range images.

use candle_core::{Device, Tensor};
use glam::Vec3;
use serde::{Deserialize, Serialize};
use veila_geom::{Projector, RangeImage};
use veila_nn::segmenter::knn::{PointPixel, locate_points};
use veila_nn::segmenter::{IN_CHANNELS, SegmenterConfig, segmenter_input};

use crate::error::{Error, Result};

/// A scan projected on a segmenter's grid.
#[derive(Debug, Clone)]
pub struct GridScan {
    /// The range image (its `point_index` names the kept point of each pixel).
    pub image: RangeImage,
    /// The network's input, `[6, rows, cols]` row-major ([`segmenter_input`]).
    pub input: Vec<f32>,
    /// Each point's pixel and range (`None` for a point the projection rejects).
    pub pixels: Vec<Option<PointPixel>>,
}

impl GridScan {
    /// Projects `points` (with their `intensity`) with `projector`, whose sensor has the grid of
    /// `cfg`.
    pub fn new(
        points: &[Vec3],
        intensity: &[f32],
        projector: &Projector,
        cfg: &SegmenterConfig,
    ) -> Result<Self> {
        let (image, _) = projector.project(points, Some(intensity), None)?;
        let input = segmenter_input(&image, points, cfg, &Device::Cpu)?
            .flatten_all()?
            .to_vec1::<f32>()?;
        let pixels = locate_points(projector, points, None)?;
        Ok(GridScan {
            image,
            input,
            pixels,
        })
    }
}

/// One labelled training frame on a segmenter's grid.
#[derive(Debug, Clone, PartialEq)]
pub struct SegFrame {
    /// The network's input, `[6, rows, cols]` row-major ([`segmenter_input`]).
    pub input: Vec<f32>,
    /// The train id of each pixel, row-major (0 where empty).
    pub labels: Vec<u16>,
}

impl SegFrame {
    /// The frame of a scan: `points` with their `intensity` and train ids `classes` (one per
    /// point), projected with `projector` (the grid of `cfg`).
    pub fn from_points(
        points: &[Vec3],
        intensity: &[f32],
        classes: &[u32],
        projector: &Projector,
        cfg: &SegmenterConfig,
    ) -> Result<Self> {
        if classes.len() != points.len() {
            return Err(Error::Data(format!(
                "{} classes for {} points",
                classes.len(),
                points.len()
            )));
        }
        let (image, _) = projector.project(points, Some(intensity), None)?;
        let input = segmenter_input(&image, points, cfg, &Device::Cpu)?
            .flatten_all()?
            .to_vec1::<f32>()?;
        let mut labels = vec![0u16; image.num_pixels()];
        for (k, l) in labels.iter_mut().enumerate() {
            if image.mask[k] {
                let c = classes[image.point_index[k] as usize];
                *l = u16::try_from(c)
                    .ok()
                    .filter(|c| usize::from(*c) < cfg.num_classes)
                    .ok_or_else(|| {
                        Error::Data(format!(
                            "train id {c} is not below the segmenter's {} classes",
                            cfg.num_classes
                        ))
                    })?;
            }
        }
        Ok(SegFrame { input, labels })
    }

    /// This frame turned about the vertical axis by `shift` whole columns (content moves to higher
    /// columns, azimuth decreasing) and, with `mirror`, reflected left to right (`y -> -y`), as the
    /// projection of the turned / mirrored scan gives it: columns move, x and y turn with them
    /// (un-normalised and normalised again with `cfg`'s statistics), range, z and intensity stay.
    pub fn augmented(&self, cfg: &SegmenterConfig, shift: usize, mirror: bool) -> SegFrame {
        let (h, w) = (cfg.rows, cfg.cols);
        let n = h * w;
        let theta = std::f64::consts::TAU * (shift % w) as f64 / w as f64;
        let (s, c) = (theta.sin() as f32, theta.cos() as f32);
        let (mx, my) = (cfg.input_mean[1], cfg.input_mean[2]);
        let (sx, sy) = (cfg.input_std[1], cfg.input_std[2]);
        let mut input = vec![0f32; IN_CHANNELS * n];
        let mut labels = vec![0u16; n];
        for r in 0..h {
            for col in 0..w {
                let k = r * w + col;
                let moved = (col + shift) % w;
                let to = r * w + if mirror { w - 1 - moved } else { moved };
                labels[to] = self.labels[k];
                for ch in 0..IN_CHANNELS {
                    input[ch * n + to] = self.input[ch * n + k];
                }
                if self.input[5 * n + k] == 0.0 {
                    continue;
                }
                let x = self.input[n + k] * sx + mx;
                let y = self.input[2 * n + k] * sy + my;
                let (x2, y2) = (x * c + y * s, -x * s + y * c);
                let y2 = if mirror { -y2 } else { y2 };
                input[n + to] = (x2 - mx) / sx;
                input[2 * n + to] = (y2 - my) / sy;
            }
        }
        SegFrame { input, labels }
    }
}

/// How the classes of the loss are weighted ([`class_weights`]).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum ClassWeighting {
    /// RangeNet++'s and CENet's: `1 / (f + 0.001)`, `f` the class's share of the labelled pixels
    /// of the training frames.
    #[default]
    InverseFrequency,
    /// `1 / sqrt(f + 0.001)`: milder on the rare classes.
    InverseSqrtFrequency,
    /// Every class 1.
    Uniform,
}

/// RangeNet++'s `epsilon_w`, the share added to every class's before it is inverted.
pub const WEIGHT_EPSILON: f64 = 0.001;

/// Pixels of each train id over `frames` (`num_classes` counts; empty pixels are not counted).
pub fn class_counts(frames: &[SegFrame], num_classes: usize) -> Vec<u64> {
    let mut counts = vec![0u64; num_classes];
    for f in frames {
        let mask = &f.input[5 * f.labels.len()..];
        for (l, m) in f.labels.iter().zip(mask) {
            if *m != 0.0
                && let Some(c) = counts.get_mut(usize::from(*l))
            {
                *c += 1;
            }
        }
    }
    counts
}

/// The loss weight of each class from its pixel `counts` ([`class_counts`]): `weighting`'s
/// formula on the class's share of every pixel with a return, 0 for the `ignored` classes.
pub fn class_weights(counts: &[u64], weighting: ClassWeighting, ignored: &[usize]) -> Vec<f32> {
    let total = counts.iter().sum::<u64>().max(1) as f64;
    counts
        .iter()
        .enumerate()
        .map(|(c, &n)| {
            if ignored.contains(&c) {
                return 0.0;
            }
            let f = n as f64 / total + WEIGHT_EPSILON;
            (match weighting {
                ClassWeighting::InverseFrequency => 1.0 / f,
                ClassWeighting::InverseSqrtFrequency => 1.0 / f.sqrt(),
                ClassWeighting::Uniform => 1.0,
            }) as f32
        })
        .collect()
}

/// The tensors of a batch of frames: the input `[B, 6, rows, cols]`, each pixel's train id `[B
/// rows cols]` (u32) and its loss weight (the class's from `weights`, 0 where empty), for
/// `veila_nn::feature_nets::train::masked_cross_entropy`.
pub fn batch_tensors(
    frames: &[SegFrame],
    weights: &[f32],
    cfg: &SegmenterConfig,
    device: &Device,
) -> Result<(Tensor, Tensor, Tensor)> {
    let (b, n) = (frames.len(), cfg.rows * cfg.cols);
    let mut input = Vec::with_capacity(b * IN_CHANNELS * n);
    let mut labels = Vec::with_capacity(b * n);
    let mut w = Vec::with_capacity(b * n);
    for f in frames {
        if f.input.len() != IN_CHANNELS * n || f.labels.len() != n {
            return Err(Error::Data(format!(
                "a frame of {} pixels for a {} x {} segmenter",
                f.labels.len(),
                cfg.rows,
                cfg.cols
            )));
        }
        input.extend_from_slice(&f.input);
        for (k, &l) in f.labels.iter().enumerate() {
            labels.push(u32::from(l));
            let valid = f.input[5 * n + k] != 0.0;
            w.push(if valid {
                weights.get(usize::from(l)).copied().unwrap_or(0.0)
            } else {
                0.0
            });
        }
    }
    Ok((
        Tensor::from_vec(input, (b, IN_CHANNELS, cfg.rows, cfg.cols), device)?,
        Tensor::from_vec(labels, b * n, device)?,
        Tensor::from_vec(w, b * n, device)?,
    ))
}

#[cfg(test)]
mod tests {
    use super::*;
    use veila_geom::{LidarSensor, ProjectionOptions};

    fn tiny_setup() -> (SegmenterConfig, Projector) {
        let cfg = SegmenterConfig::tiny();
        let sensor = LidarSensor {
            rows: cfg.rows as u32,
            cols: cfg.cols as u32,
            ..LidarSensor::hdl64e()
        };
        (
            cfg,
            Projector::new(&sensor, ProjectionOptions::default()).unwrap(),
        )
    }

    /// Points on a ring of walls at 5-25 m, below the horizon, each with a class by azimuth.
    fn scene(n: usize) -> (Vec<Vec3>, Vec<f32>, Vec<u32>) {
        let mut pts = Vec::new();
        let mut inten = Vec::new();
        let mut cls = Vec::new();
        for i in 0..n {
            let az = (i as f32 + 0.37) * std::f32::consts::TAU / n as f32 - std::f32::consts::PI;
            let r = 5.0 + 20.0 * ((i * 7) % 13) as f32 / 13.0;
            let el = -0.02 - 0.4 * ((i * 3) % 11) as f32 / 11.0;
            pts.push(Vec3::new(
                r * el.cos() * az.cos(),
                r * el.cos() * az.sin(),
                r * el.sin(),
            ));
            inten.push(0.1 + 0.05 * (i % 5) as f32);
            cls.push(1 + (i % 4) as u32);
        }
        (pts, inten, cls)
    }

    #[test]
    fn a_turned_and_mirrored_frame_is_the_frame_of_the_turned_and_mirrored_scan() {
        let (cfg, proj) = tiny_setup();
        let (pts, inten, cls) = scene(900);
        let frame = SegFrame::from_points(&pts, &inten, &cls, &proj, &cfg).unwrap();
        assert!(frame.labels.iter().any(|&l| l > 0));
        for (shift, mirror) in [(0, false), (5, false), (17, true), (0, true)] {
            let theta = std::f32::consts::TAU * shift as f32 / cfg.cols as f32;
            let turned: Vec<Vec3> = pts
                .iter()
                .map(|p| {
                    let (s, c) = theta.sin_cos();
                    let q = Vec3::new(p.x * c + p.y * s, -p.x * s + p.y * c, p.z);
                    if mirror { Vec3::new(q.x, -q.y, q.z) } else { q }
                })
                .collect();
            let want = SegFrame::from_points(&turned, &inten, &cls, &proj, &cfg).unwrap();
            let got = frame.augmented(&cfg, shift, mirror);
            // the points sit well inside their columns, so the pixels agree exactly
            assert_eq!(got.labels, want.labels, "shift {shift} mirror {mirror}");
            let worst = got
                .input
                .iter()
                .zip(&want.input)
                .map(|(a, b)| (a - b).abs())
                .fold(0f32, f32::max);
            assert!(worst < 1e-4, "shift {shift} mirror {mirror}: {worst}");
        }
    }

    #[test]
    fn class_weights_follow_rangenet_and_skip_the_ignored_class() {
        let counts = [500, 300, 100, 100, 0];
        let w = class_weights(&counts, ClassWeighting::InverseFrequency, &[0]);
        assert_eq!(w[0], 0.0);
        assert!((f64::from(w[1]) - 1.0 / (0.3 + 0.001)).abs() < 1e-3);
        assert!((f64::from(w[4]) - 1000.0).abs() < 1e-2);
        let s = class_weights(&counts, ClassWeighting::InverseSqrtFrequency, &[0]);
        assert!((f64::from(s[2]) - 1.0 / (0.101f64).sqrt()).abs() < 1e-4);
        assert_eq!(
            class_weights(&counts, ClassWeighting::Uniform, &[0]),
            vec![0.0, 1.0, 1.0, 1.0, 1.0]
        );
        let (cfg, proj) = tiny_setup();
        let (pts, inten, cls) = scene(400);
        let frame = SegFrame::from_points(&pts, &inten, &cls, &proj, &cfg).unwrap();
        let counts = class_counts(std::slice::from_ref(&frame), cfg.num_classes);
        let valid = frame.input[5 * frame.labels.len()..]
            .iter()
            .filter(|m| **m != 0.0)
            .count() as u64;
        assert_eq!(counts.iter().sum::<u64>(), valid);
        let bad = SegFrame::from_points(&pts, &inten, &vec![9; pts.len()], &proj, &cfg);
        assert!(bad.unwrap_err().to_string().contains("train id 9"));
    }
}
