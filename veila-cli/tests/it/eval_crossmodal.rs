//! `veila eval --metrics cm-dc,cm-sc` end to end on simulated frames: true scans against their own
//! camera's depth and classes score near the ideal, against another scene's maps far from it; missing
//! inputs fail cleanly, naming what is missing, and write nothing.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

fn veila() -> Command {
    Command::new(env!("CARGO_BIN_EXE_veila"))
}

fn ok(o: &Output) {
    assert!(
        o.status.success(),
        "stdout:\n{}\nstderr:\n{}",
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    );
}

/// Two frames of the bundled straight road with `seed` into `dir/name` (KITTI layout).
fn simulate(dir: &Path, name: &str, seed: u64) -> PathBuf {
    let scene = Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenes/straight_road.toml");
    simulate_scene(dir, name, seed, &scene)
}

/// Two frames of the scene file `scene` with `seed` into `dir/name` (KITTI layout).
fn simulate_scene(dir: &Path, name: &str, seed: u64, scene: &Path) -> PathBuf {
    let out = dir.join(name);
    ok(&veila()
        .args(["simulate", "--quiet", "--frames", "2", "--seed"])
        .arg(seed.to_string())
        .arg("--scene")
        .arg(scene)
        .arg("--out")
        .arg(&out)
        .output()
        .unwrap());
    out
}

/// Runs `veila eval` with the cross-modal metrics of the scans in `scans` against the maps of
/// `maps` and returns (cm-dc, cm-sc %).
fn crossmodal(tmp: &Path, scans: &Path, maps: &Path, alignment: &str) -> (f64, f64) {
    let json = tmp.join(format!("cm-{}.json", rand_name(scans, maps, alignment)));
    ok(&veila()
        .args(["eval", "--quiet", "--metrics", "cm-dc,cm-sc"])
        .arg("--generated")
        .arg(scans.join("velodyne"))
        .arg("--reference")
        .arg(scans.join("velodyne"))
        .arg("--calib")
        .arg(scans.join("calib"))
        .arg("--depth-maps")
        .arg(maps.join("depth_2"))
        .arg("--semantic-maps")
        .arg(maps.join("semantic_2"))
        .args([
            "--semantic-ids",
            "raw",
            "--depth-alignment",
            alignment,
            "--json",
        ])
        .arg(&json)
        .output()
        .unwrap());
    let v: serde_json::Value = serde_json::from_slice(&std::fs::read(&json).unwrap()).unwrap();
    let get = |name: &str| {
        v["metrics"]
            .as_array()
            .unwrap()
            .iter()
            .find(|m| m["name"] == name)
            .unwrap_or_else(|| panic!("{name} missing in {v}"))["value"]
            .as_f64()
            .unwrap()
    };
    (get("cm-dc"), get("cm-sc (%)"))
}

fn rand_name(a: &Path, b: &Path, c: &str) -> String {
    format!(
        "{}-{}-{c}",
        a.file_name().unwrap().to_string_lossy(),
        b.file_name().unwrap().to_string_lossy()
    )
}

#[test]
fn true_scans_agree_with_their_own_camera_and_not_with_another_scene() {
    let tmp = tempfile::tempdir().unwrap();
    let a = simulate(tmp.path(), "a", 7);
    let b = simulate(tmp.path(), "b", 8);

    // the scan and the depth map are the same geometry: only the map's 1/256 m steps and the
    // nearest-pixel lookup separate them
    let (dc, sc) = crossmodal(tmp.path(), &a, &a, "none");
    assert!(dc < 0.02, "true scan vs its own depth: AbsRel {dc}");
    // the range segmentation net is trained on simulator scans: most points get the image's class
    assert!(sc > 50.0, "true scan vs its own classes: {sc} %");
    // median alignment of a metric map changes little
    let (dc_med, _) = crossmodal(tmp.path(), &a, &a, "median");
    assert!(dc_med < 0.05, "median-aligned AbsRel {dc_med}");

    // another seed's scene: its depth and classes do not fit this scan
    let (dc_x, sc_x) = crossmodal(tmp.path(), &a, &b, "none");
    assert!(
        dc_x > 5.0 * dc && dc_x > 0.05,
        "mismatched maps: AbsRel {dc_x} vs {dc}"
    );
    assert!(sc_x < sc - 5.0, "mismatched maps: {sc_x} % vs {sc} %");
}

#[test]
fn missing_inputs_fail_naming_what_is_missing_and_write_nothing() {
    let tmp = tempfile::tempdir().unwrap();
    let a = simulate(tmp.path(), "a", 7);
    let json = tmp.path().join("out.json");
    let run = |extra: &[&std::ffi::OsStr]| {
        let o = veila()
            .args(["eval", "--quiet", "--metrics", "cm-dc"])
            .arg("--generated")
            .arg(a.join("velodyne"))
            .arg("--reference")
            .arg(a.join("velodyne"))
            .arg("--json")
            .arg(&json)
            .args(extra)
            .output()
            .unwrap();
        assert!(!o.status.success());
        assert!(!json.exists(), "no output on failure");
        String::from_utf8_lossy(&o.stderr).into_owned()
    };
    let calib = a.join("calib");
    let depth = a.join("depth_2");
    // no calibration
    let e = run(&["--depth-maps".as_ref(), depth.as_os_str()]);
    assert!(e.contains("--calib"), "{e}");
    // no depth maps
    let e = run(&["--calib".as_ref(), calib.as_os_str()]);
    assert!(e.contains("--depth-maps"), "{e}");
    let both: [&std::ffi::OsStr; 4] = [
        "--calib".as_ref(),
        calib.as_os_str(),
        "--depth-maps".as_ref(),
        depth.as_os_str(),
    ];
    // a depth map missing for one scan: the error names the scan and the file looked for
    std::fs::remove_file(depth.join("000001.png")).unwrap();
    let e = run(&both);
    assert!(e.contains("000001.bin") && e.contains("000001.png"), "{e}");
    // an 8-bit PNG cannot hold metric depth
    veila_data::image::GrayImage::new(4, 4)
        .save(depth.join("000001.png"))
        .unwrap();
    let e = run(&both);
    assert!(e.contains("000001.png") && e.contains("16-bit"), "{e}");
    // a malformed --image-size is refused by the parser
    let e = run(&["--image-size".as_ref(), "12x".as_ref()]);
    assert!(
        e.contains("WIDTHxHEIGHT") || e.contains("whole numbers"),
        "{e}"
    );
}

/// `--depth-model` / `--semantic-model`: Depth-Anything-V2 and SegFormer run on the camera images
/// inside `eval` (random weights in Hugging Face layout here: the numbers only have to be finite
/// and in range); wrong kinds, missing files and missing images fail naming what is wrong.
#[test]
fn networks_predict_the_maps_when_asked() {
    use candle_core::{DType, Device};
    let tmp = tempfile::tempdir().unwrap();
    // the straight road through a square camera: Depth-Anything-V2's processor fits the image's
    // nearer side to 518 px, so a KITTI frame (1242 x 375) would be 518 x 1722 px, 4,551 tokens
    // (a minute of this test on two cores); 376 x 376 px is 1,369 tokens
    let bundled = Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenes/straight_road.toml");
    let scene = tmp.path().join("square_camera.toml");
    std::fs::write(
        &scene,
        std::fs::read_to_string(bundled).unwrap()
            + "\n[camera]\nwidth = 376\nheight = 376\nfx = 260.0\nfy = 260.0\ncx = 188.0\ncy = 188.0\n",
    )
    .unwrap();
    let sim = simulate_scene(tmp.path(), "a", 3, &scene);
    // one frame is enough here (the networks are the slow part)
    for entry in std::fs::read_dir(sim.join("velodyne")).unwrap() {
        let p = entry.unwrap().path();
        if !p.ends_with("000000.bin") {
            std::fs::remove_file(p).unwrap();
        }
    }
    let weights = tmp.path().join("w");
    std::fs::create_dir_all(&weights).unwrap();
    let save = |name: &str, build: &dyn Fn(candle_nn::VarBuilder<'_>)| {
        let vm = candle_nn::VarMap::new();
        build(veila_nn::seeded_var_builder(
            &vm,
            5,
            DType::F32,
            &Device::Cpu,
        ));
        vm.save(weights.join(name)).unwrap();
    };
    save("da.safetensors", &|vb| {
        veila_nn::encoders::depth_anything::DepthAnythingV2::new(
            &veila_nn::encoders::depth_anything::DepthAnythingV2Config::small(),
            vb,
        )
        .unwrap();
    });
    save("seg.safetensors", &|vb| {
        veila_nn::encoders::mit::SegFormer::new(
            &veila_nn::encoders::mit::SegFormerConfig::b0_cityscapes(),
            vb,
        )
        .unwrap();
    });
    let run = |extra: &[&str]| {
        veila()
            .args(["eval", "--quiet"])
            .arg("--generated")
            .arg(sim.join("velodyne"))
            .arg("--reference")
            .arg(sim.join("velodyne"))
            .arg("--calib")
            .arg(sim.join("calib"))
            .args(extra)
            .output()
            .unwrap()
    };
    let da = format!(
        "depth-anything-v2-small={}",
        weights.join("da.safetensors").display()
    );
    let seg = format!("segformer-b0={}", weights.join("seg.safetensors").display());
    let images = sim.join("image_2");
    let json = tmp.path().join("m.json");
    let o = run(&[
        "--metrics",
        "cm-dc,cm-sc",
        "--images",
        images.to_str().unwrap(),
        "--depth-model",
        &da,
        "--semantic-model",
        &seg,
        "--json",
        json.to_str().unwrap(),
    ]);
    ok(&o);
    let v: serde_json::Value = serde_json::from_slice(&std::fs::read(&json).unwrap()).unwrap();
    let get = |name: &str| {
        v["metrics"]
            .as_array()
            .unwrap()
            .iter()
            .find(|m| m["name"] == name)
            .unwrap_or_else(|| panic!("{name} missing in {v}"))["value"]
            .as_f64()
            .unwrap()
    };
    let (dc, sc) = (get("cm-dc"), get("cm-sc (%)"));
    assert!(dc.is_finite() && dc >= 0.0, "{dc}");
    assert!((0.0..=100.0).contains(&sc), "{sc}");

    // no images; a model of the wrong family; a missing weights file; both maps and a model
    let o = run(&["--depth-model", &da, "--metrics", "cm-dc"]);
    assert!(!o.status.success());
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("pass --images DIR"), "{err}");
    let wrong = format!("segformer-b0={}", weights.join("da.safetensors").display());
    let o = run(&[
        "--images",
        images.to_str().unwrap(),
        "--metrics",
        "cm-dc",
        "--depth-model",
        &wrong,
    ]);
    assert!(!o.status.success());
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("not a Depth-Anything-V2 kind"), "{err}");
    let missing = format!(
        "segformer-b1={}",
        weights.join("nope.safetensors").display()
    );
    let o = run(&[
        "--images",
        images.to_str().unwrap(),
        "--metrics",
        "cm-sc",
        "--semantic-model",
        &missing,
    ]);
    assert!(!o.status.success());
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        err.contains("nope.safetensors")
            && err.contains("nvidia/segformer-b1-finetuned-cityscapes-1024-1024"),
        "{err}"
    );
    let o = run(&[
        "--images",
        images.to_str().unwrap(),
        "--metrics",
        "cm-dc",
        "--depth-model",
        &da,
        "--depth-maps",
        sim.join("depth_2").to_str().unwrap(),
    ]);
    assert!(!o.status.success());
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("not both"), "{err}");
}
