//! Model artifacts: a bundle's `bundle.json`, its `manifest.json` and its weights, a segmenter
//! folder's files, and the weights files veila-nn reads (denoiser checkpoints, small-CNN encoder
//! files).

use std::collections::BTreeMap;
use std::path::Path;

use candle_core::{DType, Device};
use veila_diffusion::app::bundle::{
    Bundle, CONFIG_FILE, DENOISER_FILE, DEPTH_FILE, MANIFEST_FILE, MEAN_FILE, SEMANTIC_FILE,
    sha256_hex,
};
use veila_nn::encoders::small_cnn::SmallCnn;

use crate::engine::{FuzzRng, Structured, Verdict, fuzz, put, tempdir};
use crate::{mutate, seeds};

/// The files of a seed bundle saved in `dir`, by name.
fn bundle_files(dir: &Path) -> BTreeMap<String, Vec<u8>> {
    std::fs::read_dir(dir)
        .expect("the bundle folder")
        .map(|e| {
            let e = e.expect("an entry");
            (
                e.file_name().to_string_lossy().into_owned(),
                std::fs::read(e.path()).expect("a bundle file"),
            )
        })
        .collect()
}

/// `manifest.json` with the sum of `name` set to that of `bytes` (so an edit of a bundle file
/// reaches the reader's own checks instead of the integrity check).
fn resigned(manifest: &[u8], name: &str, bytes: &[u8]) -> Vec<u8> {
    let mut m: serde_json::Value = serde_json::from_slice(manifest).expect("the manifest");
    m["files"][name] = sha256_hex(bytes).into();
    serde_json::to_vec_pretty(&m).expect("the manifest")
}

/// Loads the bundle in `dir`; an error must name the folder.
fn load(dir: &Path) -> Verdict {
    let name = dir.display().to_string();
    Verdict::of(Bundle::from_dir(dir, &Device::Cpu), &[&name])
}

#[test]
fn bundle_json() {
    let tmp = tempdir();
    let dir = tmp.path().join("bundle");
    seeds::save_bundle(&dir);
    let files = bundle_files(&dir);
    let manifest = files[MANIFEST_FILE].clone();
    let json: Structured<'_> = &mutate::json;
    let run = |bytes: &[u8]| {
        put(&dir.join(CONFIG_FILE), bytes);
        put(
            &dir.join(MANIFEST_FILE),
            &resigned(&manifest, CONFIG_FILE, bytes),
        );
        load(&dir)
    };
    fuzz(
        "bundle.json",
        &[files[CONFIG_FILE].clone()],
        &[json, json, json, &mutate::text_tokens],
        &run,
    );
}

#[test]
fn bundle_manifest() {
    let tmp = tempdir();
    let dir = tmp.path().join("bundle");
    seeds::save_bundle(&dir);
    // a file outside the folder the manifest might be made to name
    seeds::write(&tmp.path().join("outside.safetensors"), b"not weights");
    let files = bundle_files(&dir);
    let paths = |b: &[u8], rng: &mut FuzzRng| -> Option<Vec<u8>> {
        use rand::seq::IndexedRandom;
        let mut m: serde_json::Value = serde_json::from_slice(b).ok()?;
        let files = m.get_mut("files")?.as_object_mut()?;
        let name = files
            .keys()
            .cloned()
            .collect::<Vec<_>>()
            .choose(rng)?
            .clone();
        let sum = files.remove(&name)?;
        let other = *[
            "../outside.safetensors",
            "/etc/passwd",
            "a/../../b",
            "",
            ".",
        ]
        .choose(rng)
        .expect("a name");
        files.insert(other.to_string(), sum);
        serde_json::to_vec(&m).ok()
    };
    let run = |bytes: &[u8]| {
        put(&dir.join(MANIFEST_FILE), bytes);
        load(&dir)
    };
    fuzz(
        "bundle manifest.json",
        &[files[MANIFEST_FILE].clone()],
        &[&mutate::json, &mutate::json, &paths],
        &run,
    );
}

/// The weight files of a bundle, the input's first byte choosing which one it replaces.
const WEIGHT_FILES: [&str; 4] = [DENOISER_FILE, MEAN_FILE, SEMANTIC_FILE, DEPTH_FILE];

/// `edit` on a tagged input's payload (its first byte says which file it is).
fn tagged(edit: Structured<'_>) -> impl Fn(&[u8], &mut FuzzRng) -> Option<Vec<u8>> + '_ {
    move |b, rng| {
        let (tag, rest) = b.split_first()?;
        let mut out = vec![*tag];
        out.extend(edit(rest, rng)?);
        Some(out)
    }
}

#[test]
fn bundle_weights() {
    let tmp = tempdir();
    let dir = tmp.path().join("bundle");
    seeds::save_bundle(&dir);
    let files = bundle_files(&dir);
    let manifest = files[MANIFEST_FILE].clone();
    let seeds: Vec<Vec<u8>> = WEIGHT_FILES
        .iter()
        .enumerate()
        .map(|(i, f)| {
            let mut b = vec![i as u8];
            b.extend_from_slice(&files[*f]);
            b
        })
        .collect();
    let run = |bytes: &[u8]| {
        let (tag, payload) = bytes.split_first().unwrap_or((&0, &[]));
        let name = WEIGHT_FILES[*tag as usize % WEIGHT_FILES.len()];
        // every file back to its seed, then the input in place of one, the manifest re-signed
        for f in WEIGHT_FILES {
            put(&dir.join(f), &files[f]);
        }
        put(&dir.join(name), payload);
        put(
            &dir.join(MANIFEST_FILE),
            &resigned(&manifest, name, payload),
        );
        load(&dir)
    };
    let st = tagged(&mutate::safetensors);
    fuzz("bundle weights (safetensors)", &seeds, &[&st, &st], &run);
}

#[test]
fn checkpoint_and_encoder_weights() {
    let tmp = tempdir();
    let ckpt = tmp.path().join("ckpt");
    seeds::save_checkpoint(&ckpt);
    let weights = std::fs::read(ckpt.join(veila_nn::checkpoint::WEIGHTS_FILE)).expect("weights");
    let (cnn, cnn_bytes) = seeds::small_cnn_file();
    let cnn_path = tmp.path().join("semantic_encoder.safetensors");
    let seeds = vec![
        [vec![0u8], weights].concat(),
        [vec![1u8], cnn_bytes].concat(),
    ];
    let dir_name = tmp.path().display().to_string();
    let run = |bytes: &[u8]| {
        let (tag, payload) = bytes.split_first().unwrap_or((&0, &[]));
        if tag % 2 == 0 {
            put(&ckpt.join(veila_nn::checkpoint::WEIGHTS_FILE), payload);
            Verdict::of(
                veila_nn::checkpoint::read_checkpoint(&ckpt, DType::F32, &Device::Cpu),
                &[&dir_name],
            )
        } else {
            put(&cnn_path, payload);
            Verdict::of(
                veila_nn::encoders::load_checked(
                    &cnn_path,
                    DType::F32,
                    &Device::Cpu,
                    |_| true,
                    |vb| SmallCnn::new(&cnn, vb),
                ),
                &[&dir_name],
            )
        }
    };
    let st = tagged(&mutate::safetensors);
    fuzz(
        "checkpoint and encoder weights (safetensors)",
        &seeds,
        &[&st, &st],
        &run,
    );
}

/// A segmenter folder's files, the input's first byte choosing which one it replaces.
const SEGMENTER_FILES: [&str; 3] = ["segmenter.json", "segmenter.safetensors", MANIFEST_FILE];

#[test]
fn segmenter_folder() {
    let tmp = tempdir();
    let dir = tmp.path().join("segmenter");
    seeds::save_segmenter(&dir);
    let files = bundle_files(&dir);
    let manifest = files[MANIFEST_FILE].clone();
    let seeds: Vec<Vec<u8>> = SEGMENTER_FILES
        .iter()
        .enumerate()
        .map(|(i, f)| [vec![i as u8], files[*f].clone()].concat())
        .collect();
    let name = dir.display().to_string();
    let run = |bytes: &[u8]| {
        let (tag, payload) = bytes.split_first().unwrap_or((&0, &[]));
        let file = SEGMENTER_FILES[*tag as usize % SEGMENTER_FILES.len()];
        for f in SEGMENTER_FILES {
            put(&dir.join(f), &files[f]);
        }
        put(&dir.join(file), payload);
        if file != MANIFEST_FILE {
            put(
                &dir.join(MANIFEST_FILE),
                &resigned(&manifest, file, payload),
            );
        }
        Verdict::of(
            veila_diffusion::app::segment::SegmenterModel::from_dir(&dir, &Device::Cpu),
            &[&name],
        )
    };
    let json = tagged(&mutate::json);
    let st = tagged(&mutate::safetensors);
    fuzz(
        "segmenter folder (segmenter.json, weights, manifest)",
        &seeds,
        &[&json, &json, &st],
        &run,
    );
}
