//! Data artifacts: training shards and their manifest, range EXR, PLY, KITTI / nuScenes scans,
//! `.npy` / `.npz` sample sets, SemanticKITTI `.label` files, camera images.

use std::path::Path;

use rand::seq::IndexedRandom;
use veila_data::shard::{MANIFEST_FORMAT, Manifest, ShardReader};

use crate::engine::{FuzzRng, Verdict, fuzz, put, tempdir};
use crate::{mutate, seeds};

/// The dataset name of the decoy shard outside the folder: a reader that returns it has read
/// outside.
const DECOY: &str = "decoy-outside";

/// Every sample of the shard at `path`, decoded with its cameras as training takes them.
fn read_samples(path: &Path) -> Result<usize, String> {
    let r = ShardReader::open(path).map_err(|e| e.to_string())?;
    if r.dataset() == DECOY {
        return Err(format!("{DECOY}: read the shard outside the folder"));
    }
    for k in 0..r.len() {
        let s = r.sample(k).map_err(|e| e.to_string())?;
        // `CameraMatrices` are matrices without a file: their caller names the shard, as
        // training's does (`sample_error`)
        let named = |e: veila_data::Error| format!("{}: sample {k}: {e}", path.display());
        if let (Some(img), Some(cam)) = (&s.image, &s.camera) {
            cam.to_camera(img.width(), img.height()).map_err(named)?;
        }
        for v in &s.extra_views {
            v.camera
                .to_camera(v.image.width(), v.image.height())
                .map_err(named)?;
        }
    }
    Ok(r.len())
}

#[test]
fn shard_manifest() {
    let tmp = tempdir();
    let data = tmp.path().join("data");
    std::fs::create_dir_all(&data).expect("a folder");
    let sensor = seeds::small_sensor();
    let samples = [
        seeds::shard_sample(&sensor, "000000"),
        seeds::shard_sample(&sensor, "000001"),
    ];
    let entry = veila_data::shard::write_shard(
        &data.join("shard-00000.safetensors"),
        &sensor,
        "fuzz",
        &samples,
    )
    .expect("writing a shard");
    // the decoy: a valid shard outside the folder, and a link to it inside
    let outside = tmp.path().join("outside");
    std::fs::create_dir_all(&outside).expect("a folder");
    let decoy = outside.join("shard-00000.safetensors");
    veila_data::shard::write_shard(&decoy, &sensor, DECOY, &samples).expect("the decoy");
    #[cfg(unix)]
    std::os::unix::fs::symlink(&decoy, data.join("link-out.safetensors")).expect("a link");
    let manifest = Manifest {
        format: MANIFEST_FORMAT.into(),
        dataset: "fuzz".into(),
        sensor,
        frames_per_shard: 2,
        count: 2,
        shards: vec![entry],
    };
    let path = data.join("manifest.json");
    manifest.write(&path).expect("writing the manifest");
    let seed = std::fs::read(&path).expect("the manifest");
    let decoy_abs = decoy.display().to_string();
    let paths = move |b: &[u8], rng: &mut FuzzRng| -> Option<Vec<u8>> {
        let mut m: serde_json::Value = serde_json::from_slice(b).ok()?;
        let to = *[
            "../outside/shard-00000.safetensors",
            decoy_abs.as_str(),
            "sub/../../outside/shard-00000.safetensors",
            "link-out.safetensors",
            "./shard-00000.safetensors",
            ".",
            "",
        ]
        .choose(rng)
        .expect("a path");
        m["shards"][0]["file"] = to.into();
        serde_json::to_vec_pretty(&m).ok()
    };
    let name = data.display().to_string();
    let run = |bytes: &[u8]| {
        put(&path, bytes);
        let m = match Manifest::read(&path) {
            Ok(m) => m,
            Err(e) => return Verdict::named(e.to_string(), &[&name]),
        };
        for i in 0..m.shards.len() {
            let shard = match m.shard_path(&data, i) {
                Ok(p) => p,
                Err(e) => return Verdict::named(e.to_string(), &[&name]),
            };
            match read_samples(&shard) {
                Err(e) if e.contains(DECOY) => return Verdict::Violation(e),
                Err(e) => return Verdict::named(e, &[&name]),
                Ok(_) => {}
            }
        }
        Verdict::of(m.verify(&data), &[&name])
    };
    fuzz(
        "shard manifest.json",
        &[seed],
        &[&mutate::json, &mutate::json, &paths],
        &run,
    );
}

#[test]
fn shard_file() {
    let tmp = tempdir();
    let sensor = seeds::small_sensor();
    let samples = [
        seeds::shard_sample(&sensor, "000000"),
        seeds::shard_sample(&sensor, "000001"),
    ];
    let path = tmp.path().join("shard-00000.safetensors");
    veila_data::shard::write_shard(&path, &sensor, "fuzz", &samples).expect("writing a shard");
    let seed = std::fs::read(&path).expect("the shard");
    let name = path.display().to_string();
    let run = |bytes: &[u8]| {
        put(&path, bytes);
        // the whole file decoded, and sample by sample as streaming training reads it
        let whole = veila_data::shard::read_shard(&path);
        let streamed = read_samples(&path);
        match (whole, streamed) {
            (Ok(_), Ok(_)) => Verdict::Ok,
            (Err(e), _) => Verdict::named(e.to_string(), &[&name]),
            (_, Err(e)) => Verdict::named(e, &[&name]),
        }
    };
    fuzz(
        "shard file (safetensors)",
        &[seed],
        &[&mutate::safetensors, &mutate::safetensors],
        &run,
    );
}

#[test]
fn range_exr() {
    let tmp = tempdir();
    let path = tmp.path().join("scan.exr");
    let name = path.display().to_string();
    let run = |bytes: &[u8]| {
        put(&path, bytes);
        let r = veila_data::range_exr::read_range_exr(&path).and_then(|x| x.to_points());
        Verdict::of(r, &[&name])
    };
    fuzz(
        "range image (EXR)",
        &[seeds::range_exr()],
        &[&mutate::exr, &mutate::exr],
        &run,
    );
}

#[test]
fn ply() {
    let tmp = tempdir();
    let path = tmp.path().join("scan.ply");
    let mut seed = Vec::new();
    veila_data::ply::encode_ply(&seeds::cloud(), &mut seed).expect("a PLY");
    let name = path.display().to_string();
    let run = |bytes: &[u8]| {
        put(&path, bytes);
        Verdict::of(veila_data::scan::read_points(&path), &[&name])
    };
    fuzz("points (PLY)", &[seed], &[&mutate::ply, &mutate::ply], &run);
}

#[test]
fn kitti_and_nuscenes_scans() {
    let tmp = tempdir();
    let bin = tmp.path().join("000000.bin");
    let pcd = tmp.path().join("x.pcd.bin");
    let c = seeds::cloud();
    let seeds = vec![
        [vec![0u8], veila_data::scan::encode_kitti_bin(&c)].concat(),
        [vec![1u8], seeds::pcd_bin(&c)].concat(),
    ];
    let name = tmp.path().display().to_string();
    let run = |bytes: &[u8]| {
        let (tag, payload) = bytes.split_first().unwrap_or((&0, &[]));
        let path = if tag % 2 == 0 { &bin } else { &pcd };
        put(path, payload);
        Verdict::of(veila_data::scan::read_points(path), &[&name])
    };
    fuzz("points (KITTI .bin, nuScenes .pcd.bin)", &seeds, &[], &run);
}

/// Both readers of `.npy` files: the feature matrices of `veila fd` and the sample sets of the
/// peer protocols.
#[test]
fn npy() {
    let tmp = tempdir();
    let path = tmp.path().join("samples.npy");
    let name = path.display().to_string();
    let run = |bytes: &[u8]| {
        put(&path, bytes);
        let matrix = Verdict::of(veila_data::npy::read_matrix_f64(&path), &[&name]);
        let arrays = Verdict::of(
            veila_data::peer_samples::read_sample_arrays(&path),
            &[&name],
        );
        match (matrix, arrays) {
            (v @ Verdict::Violation(_), _) | (_, v @ Verdict::Violation(_)) => v,
            (Verdict::Ok, Verdict::Ok) => Verdict::Ok,
            (Verdict::Err(e), _) | (_, Verdict::Err(e)) => Verdict::Err(e),
        }
    };
    fuzz(
        "sample sets (.npy)",
        &[seeds::npy(3, 5, false), seeds::npy(4, 2, true)],
        &[&mutate::npy, &mutate::npy],
        &run,
    );
}

#[test]
fn npz() {
    let tmp = tempdir();
    let path = tmp.path().join("samples.npz");
    let a = seeds::npy(3, 5, false);
    let b = seeds::npy(2, 8, false);
    let stored = mutate::zip_of(&[("arr_0.npy".into(), a.clone())], false).expect("a zip");
    let deflated =
        mutate::zip_of(&[("arr_0.npy".into(), a), ("arr_1.npy".into(), b)], true).expect("a zip");
    let name = path.display().to_string();
    let run = |bytes: &[u8]| {
        put(&path, bytes);
        Verdict::of(
            veila_data::peer_samples::read_sample_arrays(&path),
            &[&name],
        )
    };
    fuzz(
        "sample sets (.npz)",
        &[stored, deflated],
        &[&mutate::npz, &mutate::npz],
        &run,
    );
}

#[test]
fn semantic_kitti_label_file() {
    let tmp = tempdir();
    let path = tmp.path().join("000000.label");
    let seed: Vec<u8> = (0..200u32)
        .flat_map(|i| ((i % 5) | (i << 16)).to_le_bytes())
        .collect();
    let name = path.display().to_string();
    let run = |bytes: &[u8]| {
        put(&path, bytes);
        let a = veila_data::semantic_kitti::read_labels(&path, Some(200));
        let b = veila_data::semantic_kitti::read_labels(&path, None);
        match (a, b) {
            (Ok(_), Ok(_)) => Verdict::Ok,
            (Err(e), _) | (_, Err(e)) => Verdict::named(e.to_string(), &[&name]),
        }
    };
    fuzz("labels (SemanticKITTI .label)", &[seed], &[], &run);
}

#[test]
fn camera_image() {
    let tmp = tempdir();
    let png = tmp.path().join("img.png");
    let jpg = tmp.path().join("img.jpg");
    let img = seeds::image(24, 12);
    let seeds = vec![
        [
            vec![0u8],
            veila_data::image_io::encode_png(&img).expect("a PNG"),
        ]
        .concat(),
        [vec![1u8], seeds::jpeg(&img)].concat(),
    ];
    let name = tmp.path().display().to_string();
    let run = |bytes: &[u8]| {
        let (tag, payload) = bytes.split_first().unwrap_or((&0, &[]));
        let path = if tag % 2 == 0 { &png } else { &jpg };
        put(path, payload);
        Verdict::of(veila_data::image_io::read_rgb_image(path), &[&name])
    };
    fuzz("camera images (PNG, JPEG)", &seeds, &[], &run);
}
