//! `veila bench`: the report's shape and consistency on the bundled network (CPU, tiny runs), and
//! clear errors for what it cannot do.

use crate::common::*;

#[test]
fn bench_times_the_bundled_network_and_writes_its_json() {
    let tmp = tempfile::tempdir().unwrap();
    let json = tmp.path().join("bench.json");
    let o = veila()
        .args([
            "bench",
            "--device",
            "cpu",
            "--models",
            "bundled",
            "--precision",
            "f32",
            "--batch",
            "1",
            "--train-runs",
            "1",
            "--forward-runs",
            "1",
            "--sample-steps",
            "1,3",
            "--json",
        ])
        .arg(&json)
        .output()
        .unwrap();
    ok(&o);
    let stdout = String::from_utf8_lossy(&o.stdout);
    assert!(stdout.contains("| bundled |"), "{stdout}");
    let v: serde_json::Value = serde_json::from_slice(&std::fs::read(&json).unwrap()).unwrap();
    let rows = v["rows"].as_array().unwrap();
    assert_eq!(rows.len(), 1);
    // what fit is measured; what did not is listed apart (nothing, for this small network)
    assert_eq!(v["out_of_memory"].as_array().map(Vec::len), Some(0), "{v}");
    let r = &rows[0];
    assert_eq!(r["precision"], "f32");
    assert_eq!(r["activation_checkpointing"], "none");
    // the row's own peak: at least the weights and AdamW's two moments, and far below the machine
    let peak = r["peak_memory_mib"].as_f64().unwrap();
    assert!(peak > 0.0 && peak < 8192.0, "peak {peak} MiB");
    assert_eq!(r["peak_memory_source"], "VmHWM");
    let train_ms = r["train_step_ms"].as_f64().unwrap();
    let eval_ms = r["eval_b2_ms"].as_f64().unwrap();
    assert!(train_ms > 0.0 && eval_ms > 0.0);
    let sps = r["train_samples_per_s"].as_f64().unwrap();
    assert!(
        (sps * train_ms / 1e3 - 1.0).abs() < 1e-6,
        "batch 1: {sps} x {train_ms} ms"
    );
    // the network evaluations of N steps cost N evaluations
    let cost = r["sample_s_per_scan"].as_array().unwrap();
    assert_eq!(cost.len(), 2);
    let (s1, s3) = (cost[0][1].as_f64().unwrap(), cost[1][1].as_f64().unwrap());
    assert!((s3 - 3.0 * s1).abs() < 1e-9 && (s1 - eval_ms / 1e3).abs() < 1e-9);
    // the parameter count is the bundle's denoiser's
    let weights = candle_core::safetensors::load(
        model_dir().join("denoiser.safetensors"),
        &candle_core::Device::Cpu,
    )
    .unwrap();
    let params: usize = weights.values().map(|t| t.elem_count()).sum();
    assert_eq!(r["params"].as_u64().unwrap() as usize, params);
    // an existing output is kept unless --force
    let again = veila()
        .args(["bench", "--device", "cpu", "--models", "bundled", "--json"])
        .arg(&json)
        .output()
        .unwrap();
    assert!(!again.status.success());
    assert!(String::from_utf8_lossy(&again.stderr).contains("bench.json"));
    let generate = v["generate"].as_array().unwrap();
    assert_eq!(generate.len(), 2);
    assert!(
        generate
            .iter()
            .all(|g| g["seconds_per_scan"].as_f64().unwrap() > 0.0)
    );
}

#[test]
fn bench_refuses_what_it_cannot_run() {
    for (args, want) in [
        (&["--models", "huge"][..], "huge"),
        (&["--precision", "fp8"][..], "fp8"),
        (&["--batch", "0"][..], "--batch"),
        (&["--sample-steps", "0"][..], "--sample-steps"),
    ] {
        let o = veila()
            .args(["bench", "--device", "cpu"])
            .args(args)
            .output()
            .unwrap();
        assert!(!o.status.success(), "{args:?}");
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(err.contains(want), "{args:?}: {err}");
    }
}

#[test]
fn bench_no_eval_measures_the_update_alone_at_each_batch_and_mode() {
    let tmp = tempfile::tempdir().unwrap();
    let json = tmp.path().join("bench.json");
    let o = veila()
        .args([
            "bench",
            "--device",
            "cpu",
            "--models",
            "bundled",
            "--precision",
            "f32",
            "--batch",
            "1,4",
            "--activation-checkpointing",
            "none,block",
            "--train-runs",
            "1",
            "--no-eval",
            "--json",
        ])
        .arg(&json)
        .output()
        .unwrap();
    ok(&o);
    let v: serde_json::Value = serde_json::from_slice(&std::fs::read(&json).unwrap()).unwrap();
    let rows = v["rows"].as_array().unwrap();
    assert_eq!(rows.len(), 4, "{v}");
    for r in rows {
        assert!(r["eval_b2_ms"].is_null(), "{r}");
        assert!(r["peak_memory_mib"].as_f64().unwrap() > 0.0, "{r}");
    }
    assert!(v["generate"].as_array().unwrap().is_empty());
    // one per-sample figure per mode, from batch 1 to 4
    let per = v["per_sample_memory"].as_array().unwrap();
    assert_eq!(per.len(), 2, "{v}");
    for p in per {
        assert_eq!(p["batches"], serde_json::json!([1, 4]));
        assert!(p["mib_per_sample"].as_f64().unwrap().is_finite());
    }
    let stdout = String::from_utf8_lossy(&o.stdout);
    assert!(stdout.contains("training memory per sample"), "{stdout}");
}

#[cfg(target_os = "linux")]
#[test]
fn a_row_that_does_not_fit_the_memory_is_a_row_not_an_abort() {
    // an address-space limit (3 GiB, `ulimit -v`) the paper network cannot train in: its row's
    // process fails to allocate (the allocator aborts it); the parent reports it and still
    // measures the rest
    let tmp = tempfile::tempdir().unwrap();
    let json = tmp.path().join("bench.json");
    let mut cmd = std::process::Command::new("sh");
    cmd.env_remove("VEILA_MODEL")
        .arg("-c")
        .arg("ulimit -v 3145728 && exec \"$0\" \"$@\"")
        .arg(env!("CARGO_BIN_EXE_veila"))
        .args([
            "bench",
            "--device",
            "cpu",
            "--models",
            "bundled,paper",
            "--precision",
            "f32",
            "--batch",
            "1",
            "--train-runs",
            "1",
            "--no-eval",
            "--json",
        ])
        .arg(&json);
    let o = cmd.output().unwrap();
    ok(&o);
    let v: serde_json::Value = serde_json::from_slice(&std::fs::read(&json).unwrap()).unwrap();
    let rows = v["rows"].as_array().unwrap();
    assert_eq!(rows.len(), 1, "{v}");
    assert_eq!(rows[0]["model"], "bundled");
    let oom = v["out_of_memory"].as_array().unwrap();
    assert_eq!(oom.len(), 1, "{v}");
    assert_eq!(oom[0]["model"], "paper");
    assert!(!oom[0]["error"].as_str().unwrap().is_empty(), "{v}");
    let stdout = String::from_utf8_lossy(&o.stdout);
    assert!(stdout.contains("out of memory"), "{stdout}");
}
