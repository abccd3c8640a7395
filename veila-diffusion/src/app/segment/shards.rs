//! Converted shards (`veila convert`) as a segmenter's training frames: each sample's range image
//! back to points (one per pixel with a return, [`veila_geom::RayTable`]), projected on the
//! segmenter's grid, each point carrying its pixel's train id.
//!
//! The train ids are the shard's own (`label`, from the converter's `--label-map`), or, with a
//! label map, those the map gives the raw labels (`label_raw`). Where a shard has both, they must
//! agree: a shard converted with another label map is an error naming the shard, the sample and
//! the map ("mismatched label maps"), as is a train id the segmenter has no class for.

use std::path::Path;

use veila_data::shard::{Manifest, ShardSample};
use veila_geom::{Projector, RayTable};
use veila_nn::segmenter::SegmenterConfig;

use super::frames::SegFrame;
use super::labels::LabelSpace;
use crate::app::train_data::each_sample;
use crate::error::{Error, Result};

/// The training frames of the first `max` samples (all without it) of the shards in `dir`, their
/// train ids as the module docs say (`labels` the space of the model; `given_map` whether it comes
/// from a file, so the raw labels are mapped by it), projected with `projector` for `cfg`. Also
/// the manifest; `on_frame` is called after each frame.
pub fn shard_frames(
    dir: &Path,
    max: Option<usize>,
    labels: &LabelSpace,
    given_map: bool,
    projector: &Projector,
    cfg: &SegmenterConfig,
    mut on_frame: impl FnMut(),
) -> Result<(Vec<SegFrame>, Manifest)> {
    let manifest = Manifest::read(&dir.join("manifest.json"))?;
    let rays = RayTable::new(&manifest.sensor)?;
    let want = max.unwrap_or(manifest.count).min(manifest.count);
    let mut frames = Vec::with_capacity(want);
    each_sample(dir, &manifest, |path, s| {
        if frames.len() == want {
            return Ok(false);
        }
        let err = |reason: String| Error::Input {
            path: path.to_path_buf(),
            reason: format!("sample {}: {reason}", s.id),
        };
        let ids = pixel_train_ids(s, labels, given_map).map_err(err)?;
        let un = rays.unproject(&s.scan)?;
        let classes: Vec<u32> = un
            .pixels
            .iter()
            .map(|&(r, c)| ids[r as usize * s.scan.cols as usize + c as usize])
            .collect();
        frames.push(
            SegFrame::from_points(&un.points, &un.intensity, &classes, projector, cfg)
                .map_err(|e| err(e.to_string()))?,
        );
        on_frame();
        Ok(true)
    })?;
    if frames.is_empty() {
        return Err(Error::Input {
            path: dir.join("manifest.json"),
            reason: "the shards hold no sample".into(),
        });
    }
    Ok((frames, manifest))
}

/// The train id of every pixel of a shard sample (module docs); the error says what is wrong.
fn pixel_train_ids(
    s: &ShardSample,
    labels: &LabelSpace,
    given_map: bool,
) -> std::result::Result<Vec<u32>, String> {
    let n = labels.num_classes();
    let own: Option<Vec<u32>> = s
        .train_ids
        .as_ref()
        .map(|t| t.iter().map(|&v| u32::from(v)).collect());
    let ids = match (&s.scan.label, given_map) {
        (Some(raw), true) => {
            let mapped: Vec<u32> = raw.iter().map(|&r| labels.train_id(r)).collect();
            if let Some(own) = &own
                && let Some(k) = (0..mapped.len()).find(|&k| s.scan.mask[k] && own[k] != mapped[k])
            {
                return Err(format!(
                    "mismatched label maps: pixel {k} has train id {} in the shard, but {} maps its raw label {} to {} (convert again with this --label-map, or leave [data] label_map out)",
                    own[k],
                    labels.source(),
                    raw[k] & 0xFFFF,
                    mapped[k]
                ));
            }
            mapped
        }
        _ => own.ok_or_else(|| {
            if given_map {
                "the shard has no raw labels (`label_raw`) for the label map to map".to_string()
            } else {
                "the shard has no train ids (`label`): convert with --label-map, or give [data] label_map".to_string()
            }
        })?,
    };
    if let Some((k, t)) = ids
        .iter()
        .enumerate()
        .find(|&(k, &t)| s.scan.mask[k] && t as usize >= n)
    {
        return Err(format!(
            "mismatched label maps: pixel {k} has train id {t}, but {} has {n} train ids (give the shards' label map as [data] label_map)",
            labels.source()
        ));
    }
    Ok(ids)
}
