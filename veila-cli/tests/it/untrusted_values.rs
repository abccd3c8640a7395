//! Issue 58, cases 9 to 12 against the binary: a bundle's values are held to the bounds of the
//! flags, with the bundle file and field named (never a flag nobody gave); weights of another
//! dtype or not finite are refused naming the tensor; implausible calibrations and truncated
//! images are refused saying what is wrong; a link loop as `--model` reports the OS error;
//! text from files is printed with its control characters escaped; a path that is not UTF-8 does
//! not panic.

use std::path::{Path, PathBuf};
use std::process::Output;

use crate::common::*;

/// A simulated KITTI frame: (image, calibration).
fn frame(dir: &Path) -> (PathBuf, PathBuf) {
    let sim = simulate(dir, &tiny_scene(16, 128, 1), 3);
    (sim.join("image_2/000000.png"), sim.join("calib/000000.txt"))
}

/// A copy of the bundled model in `dir/name` with `edit` applied to its `bundle.json` and the
/// manifest's sum updated, so that only the edited value is wrong.
fn edited_bundle(dir: &Path, name: &str, edit: impl FnOnce(&mut serde_json::Value)) -> PathBuf {
    let b = copy_model(dir, name);
    let mut cfg: serde_json::Value =
        serde_json::from_slice(&std::fs::read(b.join("bundle.json")).unwrap()).unwrap();
    edit(&mut cfg);
    replace_file(&b, "bundle.json", &serde_json::to_vec_pretty(&cfg).unwrap());
    b
}

/// The bundled model's files copied into `dir/name`.
fn copy_model(dir: &Path, name: &str) -> PathBuf {
    let b = dir.join(name);
    std::fs::create_dir_all(&b).unwrap();
    for e in std::fs::read_dir(model_dir()).unwrap() {
        let e = e.unwrap();
        std::fs::copy(e.path(), b.join(e.file_name())).unwrap();
    }
    b
}

/// Writes `bytes` as `file` of the bundle `b` and updates its sum in the manifest.
fn replace_file(b: &Path, file: &str, bytes: &[u8]) {
    std::fs::write(b.join(file), bytes).unwrap();
    let mp = b.join("manifest.json");
    let mut m: serde_json::Value = serde_json::from_slice(&std::fs::read(&mp).unwrap()).unwrap();
    m["files"][file] = veila_diffusion::app::bundle::sha256_hex(bytes).into();
    std::fs::write(&mp, serde_json::to_vec_pretty(&m).unwrap()).unwrap();
}

/// `veila generate --quiet --steps 1` of `image` / `calib` with the model `checkpoint`, plus
/// `extra` (`--steps` left to the bundle when `extra` has `--no-steps`).
fn generate_with(
    checkpoint: &Path,
    image: &Path,
    calib: &Path,
    out: &Path,
    extra: &[&str],
) -> Output {
    let mut c = veila();
    c.args(["generate", "--quiet"]);
    let bundle_steps = extra.contains(&"--no-steps");
    if !bundle_steps && !extra.contains(&"--steps") {
        c.args(["--steps", "1"]);
    }
    c.args(extra.iter().filter(|a| **a != "--no-steps"))
        .arg("--model")
        .arg(checkpoint)
        .arg("--image")
        .arg(image)
        .arg("--calib")
        .arg(calib)
        .arg("--out")
        .arg(out)
        .output()
        .unwrap()
}

#[test]
fn bundle_values_are_held_to_the_flags_bounds_naming_the_file_and_field() {
    let tmp = tempfile::tempdir().unwrap();
    let (image, calib) = frame(tmp.path());
    type Edit = fn(&mut serde_json::Value);
    let cases: [(&str, Edit, &[&str]); 6] = [
        (
            "guidance",
            |c| c["sampler"]["guidance_scale"] = 1e300.into(),
            &["sampler.guidance_scale", "between 0 and 20"],
        ),
        (
            "steps",
            |c| c["sampler"]["steps"] = 1_000_000_000u64.into(),
            &["sampler.steps", "limit of 1000"],
        ),
        (
            "input_scale",
            |c| c["denoiser"]["time"]["input_scale"] = 1e300.into(),
            &["denoiser", "time.input_scale", "at most 100000"],
        ),
        (
            "max_range",
            |c| c["encoding"]["max_range_m"] = 1e-30.into(),
            &["encoding.max_range_m", "between 1 and 1000"],
        ),
        (
            "intensity_max",
            |c| c["encoding"]["intensity_max"] = 1e30.into(),
            &["encoding.intensity_max"],
        ),
        (
            "residual_scale",
            |c| c["residual"]["scale"][0] = 1e30.into(),
            &["residual.scale", "between"],
        ),
    ];
    for (name, edit, words) in cases {
        let b = edited_bundle(tmp.path(), name, edit);
        let out = tmp.path().join(format!("out_{name}"));
        // the bundle's own sampler: no --steps or --guidance given
        let o = generate_with(&b, &image, &calib, &out, &["--no-steps"]);
        let mut needles = vec!["bundle.json"];
        needles.extend_from_slice(words);
        fails_with(&o, &needles);
        let e = String::from_utf8_lossy(&o.stderr);
        assert!(
            !e.contains("--steps") && !e.contains("--guidance"),
            "{name}: a flag nobody gave is named: {e}"
        );
        assert!(!out.exists(), "{name}");
    }
    // the flags are held to the same bounds, and named
    let o = generate_with(
        &model_dir(),
        &image,
        &calib,
        &tmp.path().join("o"),
        &["--guidance", "1e300"],
    );
    fails_with(&o, &["--guidance", "between 0 and 20"]);
    let o = generate_with(
        &model_dir(),
        &image,
        &calib,
        &tmp.path().join("o"),
        &["--steps", "1001"],
    );
    fails_with(&o, &["--steps", "between 1 and 1000"]);
}

/// The bundled model with tensor number `index` of `denoiser.safetensors` replaced by
/// `replace(tensor)`; returns the bundle and the tensor's name.
fn with_denoiser_tensor(
    dir: &Path,
    name: &str,
    replace: impl Fn(&candle_core::Tensor) -> candle_core::Tensor,
) -> (PathBuf, String) {
    let b = copy_model(dir, name);
    let mut t =
        candle_core::safetensors::load(b.join("denoiser.safetensors"), &candle_core::Device::Cpu)
            .unwrap();
    let mut keys: Vec<String> = t.keys().cloned().collect();
    keys.sort();
    let key = keys[keys.len() / 2].clone();
    let new = replace(&t[&key]);
    t.insert(key.clone(), new);
    let tmp = dir.join(format!("{name}.safetensors"));
    candle_core::safetensors::save(&t, &tmp).unwrap();
    replace_file(&b, "denoiser.safetensors", &std::fs::read(&tmp).unwrap());
    (b, key)
}

#[test]
fn weights_of_another_dtype_or_not_finite_are_refused_naming_the_tensor() {
    let tmp = tempfile::tempdir().unwrap();
    let (image, calib) = frame(tmp.path());
    type Replace = fn(&candle_core::Tensor) -> candle_core::Tensor;
    let cases: [(&str, Replace, &str); 4] = [
        (
            "u8",
            |t| t.to_dtype(candle_core::DType::U8).unwrap(),
            "stored as U8",
        ),
        (
            "i64",
            |t| t.to_dtype(candle_core::DType::I64).unwrap(),
            "stored as I64",
        ),
        ("nan", |t| (t * f64::NAN).unwrap(), "must be finite"),
        (
            "huge",
            |t| (t.ones_like().unwrap() * 3e38).unwrap(),
            "beyond the limit",
        ),
    ];
    for (name, replace, word) in cases {
        let (b, tensor) = with_denoiser_tensor(tmp.path(), name, replace);
        let o = generate_with(&b, &image, &calib, &tmp.path().join(name), &[]);
        fails_with(
            &o,
            &[&format!("tensor `{tensor}`"), "denoiser.safetensors", word],
        );
    }
}

#[test]
fn implausible_calibrations_and_truncated_images_are_refused_saying_why() {
    let tmp = tempfile::tempdir().unwrap();
    let (image, calib) = frame(tmp.path());
    let text = std::fs::read_to_string(&calib).unwrap();
    let p2 = text.lines().find(|l| l.starts_with("P2:")).unwrap();
    let vals: Vec<&str> = p2["P2:".len()..].split_whitespace().collect();
    let with_p2 = |i: usize, v: &str| {
        let mut v2 = vals.clone();
        v2[i] = v;
        text.replacen(p2, &format!("P2: {}", v2.join(" ")), 1)
    };
    for (name, calib_text, words) in [
        (
            "negative_focal.txt",
            with_p2(0, "-72.15"),
            &["negative_focal.txt", "focal lengths", "must be positive"][..],
        ),
        (
            "far_principal_point.txt",
            with_p2(2, "1e7"),
            &[
                "far_principal_point.txt",
                "principal point",
                "outside the 124 x 38 image",
            ][..],
        ),
    ] {
        let p = tmp.path().join(name);
        std::fs::write(&p, calib_text).unwrap();
        let o = generate_with(&model_dir(), &image, &p, &tmp.path().join("o"), &[]);
        fails_with(&o, words);
        assert!(!String::from_utf8_lossy(&o.stderr).contains("singular"));
    }
    // a LiDAR-to-camera translation of 1e30 m
    let tr = text
        .lines()
        .find(|l| l.starts_with("Tr_velo_to_cam:"))
        .unwrap();
    let mut t: Vec<String> = tr["Tr_velo_to_cam:".len()..]
        .split_whitespace()
        .map(str::to_string)
        .collect();
    t[3] = "1e30".into();
    let far = tmp.path().join("far_lidar.txt");
    std::fs::write(
        &far,
        text.replacen(tr, &format!("Tr_velo_to_cam: {}", t.join(" ")), 1),
    )
    .unwrap();
    let o = generate_with(&model_dir(), &image, &far, &tmp.path().join("o"), &[]);
    fails_with(&o, &["far_lidar.txt", "translation", "limit of 100 m"]);

    // a JPEG cut to a third decoded without an error
    let img = veila_data::image_io::read_rgb_image(&image).unwrap();
    let jpg = tmp.path().join("frame.jpg");
    img.save(&jpg).unwrap();
    let bytes = std::fs::read(&jpg).unwrap();
    let cut = tmp.path().join("cut.jpg");
    std::fs::write(&cut, &bytes[..bytes.len() / 3]).unwrap();
    ok(&generate_with(
        &model_dir(),
        &jpg,
        &calib,
        &tmp.path().join("whole"),
        &[],
    ));
    let o = generate_with(&model_dir(), &cut, &calib, &tmp.path().join("o"), &[]);
    fails_with(&o, &["cut.jpg", "truncated JPEG"]);
    assert!(!tmp.path().join("o").exists());
}

#[cfg(unix)]
#[test]
fn a_link_loop_as_checkpoint_reports_the_os_error() {
    let tmp = tempfile::tempdir().unwrap();
    let lp = tmp.path().join("loop");
    std::os::unix::fs::symlink(&lp, &lp).unwrap();
    let o = veila()
        .args(["generate", "--quiet", "--steps", "1", "--image", "x.png"])
        .args(["--calib", "x.txt", "--out"])
        .arg(tmp.path().join("o"))
        .arg("--model")
        .arg(&lp)
        .output()
        .unwrap();
    // ELOOP, as the OS words it, instead of "no model bundle"
    fails_with(&o, &["loop", "symbolic links", "os error"]);
    assert!(!String::from_utf8_lossy(&o.stderr).contains("no model bundle"));
    // a folder that is not there is still "no model bundle"
    let o = veila()
        .args(["generate", "--quiet", "--steps", "1", "--image", "x.png"])
        .args(["--calib", "x.txt", "--out"])
        .arg(tmp.path().join("o"))
        .arg("--model")
        .arg(tmp.path().join("absent"))
        .output()
        .unwrap();
    fails_with(&o, &["no model bundle"]);
}

/// Text a hostile file carries: clear the screen, go home, overwrite the line, print a line.
const HOSTILE: &str = "tiny\u{1b}[2J\u{1b}[H\rFAKE: all checks passed\n\u{9b}31m\u{7}";

fn assert_no_controls(what: &str, text: &[u8]) {
    let s = String::from_utf8_lossy(text);
    assert!(
        !s.chars().any(|c| c.is_control() && c != '\n' && c != '\t'),
        "{what} holds raw control characters: {s:?}"
    );
    assert!(
        !s.lines().any(|l| l.starts_with("FAKE")),
        "{what} printed the file's own line: {s}"
    );
}

#[test]
fn text_from_files_is_printed_with_control_characters_escaped() {
    let tmp = tempfile::tempdir().unwrap();
    let (image, calib) = frame(tmp.path());
    // the bundle's name, printed by generate
    let b = edited_bundle(tmp.path(), "named", |c| c["name"] = HOSTILE.into());
    let out = tmp.path().join("out");
    let o = generate_with(&b, &image, &calib, &out, &[]);
    ok(&o);
    assert_no_controls("stdout", &o.stdout);
    let s = String::from_utf8_lossy(&o.stdout);
    assert!(
        s.contains(r"model `tiny\u{1b}[2J\u{1b}[H\rFAKE: all checks passed\n\u{9b}31m\u{7}`"),
        "{s}"
    );
    // a calibration line in an error message
    let bad = tmp.path().join("bad_calib.txt");
    let good = std::fs::read_to_string(&calib).unwrap();
    std::fs::write(&bad, format!("{good}P9{HOSTILE}\n")).unwrap();
    let o = generate_with(&model_dir(), &image, &bad, &tmp.path().join("o"), &[]);
    fails_with(&o, &["bad_calib.txt", r"\u{1b}[2J"]);
    assert_no_controls("stderr", &o.stderr);
}

#[cfg(unix)]
#[test]
fn an_eval_folder_whose_name_is_not_utf8_does_not_panic() {
    use std::os::unix::ffi::OsStrExt;
    let tmp = tempfile::tempdir().unwrap();
    let name = std::ffi::OsStr::from_bytes(b"gen-\xff\xfe-latin1-\xe9");
    let gen_ = tmp.path().join(name);
    let scans = tmp.path().join("ref");
    for d in [&gen_, &scans] {
        std::fs::create_dir(d).unwrap();
    }
    // three ring-shaped KITTI scans per folder
    for i in 0..3u32 {
        for (d, seed) in [(&gen_, i), (&scans, 100 + i)] {
            let mut bytes = Vec::new();
            for k in 0..2000u32 {
                let a = (k * 7919 + seed * 104_729) as f32 * 0.001;
                let r = 4.0 + (k % 40) as f32;
                for v in [r * a.cos(), r * a.sin(), -1.7 + 0.01 * (k % 20) as f32, 0.5] {
                    bytes.extend_from_slice(&v.to_le_bytes());
                }
            }
            std::fs::write(d.join(format!("{i:06}.bin")), bytes).unwrap();
        }
    }
    let report = tmp.path().join("r.html");
    let o = veila()
        .args(["--quiet", "eval", "--metrics", "jsd,mmd", "--generated"])
        .arg(&gen_)
        .arg("--reference")
        .arg(&scans)
        .arg("--report")
        .arg(&report)
        .output()
        .unwrap();
    assert_ne!(
        o.status.code(),
        Some(101),
        "{}",
        String::from_utf8_lossy(&o.stderr)
    );
    ok(&o);
    let html = std::fs::read_to_string(&report).unwrap();
    // the command line of the report shows the invalid bytes as U+FFFD
    assert!(
        html.contains("gen-\u{fffd}\u{fffd}-latin1-\u{fffd}"),
        "{html}"
    );
}
