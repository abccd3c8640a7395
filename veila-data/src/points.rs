//! An owned point cloud in the LiDAR frame (x forward, y left, z up; metres).

use glam::Vec3;

/// Points in the LiDAR frame with per-point attributes. Attribute vectors, when present, have exactly
/// one entry per point (checked by [`PointCloud::validate`]).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct PointCloud {
    /// Coordinates in the LiDAR frame, metres.
    pub xyz: Vec<Vec3>,
    /// Intensity / reflectance per point, in the dataset's own scale (KITTI 0..1, nuScenes 0..255).
    pub intensity: Vec<f32>,
    /// Laser ring (beam) index per point, where the dataset stores it (nuScenes).
    pub ring: Option<Vec<u16>>,
    /// SemanticKITTI raw label per point (semantic in the low 16 bits, instance in the high 16 bits).
    pub label: Option<Vec<u32>>,
}

impl PointCloud {
    /// Number of points.
    pub fn len(&self) -> usize {
        self.xyz.len()
    }

    /// True when there are no points.
    pub fn is_empty(&self) -> bool {
        self.xyz.is_empty()
    }

    /// Check that every attribute has one entry per point.
    pub fn validate(&self) -> crate::Result<()> {
        let n = self.xyz.len();
        let check = |what: &str, len: usize| {
            if len == n {
                Ok(())
            } else {
                Err(crate::Error::Mismatch {
                    context: "point cloud".into(),
                    message: format!("{n} points but {len} {what} values"),
                })
            }
        };
        check("intensity", self.intensity.len())?;
        if let Some(r) = &self.ring {
            check("ring", r.len())?;
        }
        if let Some(l) = &self.label {
            check("label", l.len())?;
        }
        Ok(())
    }

    /// Drop points with a non-finite coordinate or intensity, keeping attributes aligned.
    /// Returns how many were dropped.
    pub fn retain_finite(&mut self) -> usize {
        let keep: Vec<bool> = self
            .xyz
            .iter()
            .zip(&self.intensity)
            .map(|(p, i)| p.is_finite() && i.is_finite())
            .collect();
        self.retain_mask(&keep)
    }

    /// Drop points with a non-finite coordinate only: a point whose intensity alone is NaN keeps its
    /// place (and its NaN intensity), as geometry consumers (the metrics) need. Returns how many were
    /// dropped.
    pub fn retain_finite_xyz(&mut self) -> usize {
        let keep: Vec<bool> = self.xyz.iter().map(|p| p.is_finite()).collect();
        self.retain_mask(&keep)
    }

    fn retain_mask(&mut self, keep: &[bool]) -> usize {
        let dropped = keep.iter().filter(|k| !**k).count();
        if dropped == 0 {
            return 0;
        }
        fn filter<T: Copy>(v: &[T], keep: &[bool]) -> Vec<T> {
            v.iter()
                .zip(keep)
                .filter(|(_, k)| **k)
                .map(|(x, _)| *x)
                .collect()
        }
        self.xyz = filter(&self.xyz, keep);
        self.intensity = filter(&self.intensity, keep);
        if let Some(r) = &self.ring {
            self.ring = Some(filter(r, keep));
        }
        if let Some(l) = &self.label {
            self.label = Some(filter(l, keep));
        }
        dropped
    }
}
