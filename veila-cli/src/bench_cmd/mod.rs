//! `veila bench`: how fast the denoiser trains and samples on this machine's device, and how much
//! memory its training takes.
//!
//! For each network (`bundled`: the bundle's denoiser config; `paper`: `DenoiserConfig::paper()`,
//! 64 x 1024 at the paper's widths), each precision (`f32`; `bf16`: mixed precision, bf16
//! activations on f32 master weights, as `[train] precision = "bf16"` trains), each activation
//! checkpointing mode (`none`; `block`: every residual block, GCMA and PFC layer recomputed in the
//! backward pass) and each batch size, with seeded random weights, random encoder features of the
//! right shapes and the GCMA geometry of a KITTI-like camera:
//!
//! - one training update (the condition fusion, forward, MSE loss, backward, AdamW), its median time
//!   and training samples per second;
//! - unless `--no-eval`, one network evaluation for sampling at batch 2 (a classifier-free guidance
//!   pair) on detached weights (no graph, as sampling runs), from which a sampler of N steps costs N
//!   evaluations per scan (`--sample-steps`);
//! - the row's peak memory: on the CPU the process's resident high-water mark (`VmHWM`, reset after
//!   the network and its inputs are built, so weights and optimizer state count but not the setup's
//!   transients); on CUDA the device's used memory, sampled every 10 ms by `nvidia-smi` while the row
//!   runs;
//! - for `bundled`, unless `--no-eval` or `--no-generate`, also the real thing: `Bundle::generate` end
//!   to end (encoders, condition, the sampler) at each step count, f32, as `veila generate` runs it.
//!
//! Every row runs in a fresh process (this binary again, with a hidden `--worker-row`), so rows do
//! not inherit each other's memory, and a row that does not fit is a result, not an abort: a failed
//! allocation (the host allocator aborts the process) or the device running out of memory (the
//! paper's network at batch 8 on a 141 GB H200 without checkpointing) becomes an `out_of_memory`
//! entry naming the row, and the other rows are still measured. With two or more batch sizes the
//! table ends with the per-sample training memory, the slope between the smallest and the largest.
//!
//! Prints a table, and with `--json FILE` writes one JSON object. Times are medians after two
//! warm-up runs; the device is synchronised before every clock reading.

mod args;
mod row;

use anyhow::{Context, Result, bail};
use veila_diffusion::Precision;

use crate::model;
pub(crate) use args::BenchArgs;
use args::{OutOfMemory, PerSample, ROW_MARKER, Report, Row, Spec, plan};
use row::{bench_generate, bench_row, network};

/// Runs row `i` of the plan in a fresh process (this binary with the same arguments and
/// `--worker-row i`): its row, or what ran out of memory.
fn measure_in_child(i: usize, spec: Spec<'_>) -> Result<std::result::Result<Row, OutOfMemory>> {
    let exe = std::env::current_exe().context("finding this veila binary to measure a row")?;
    let out = std::process::Command::new(exe)
        .args(std::env::args_os().skip(1))
        .arg("--worker-row")
        .arg(i.to_string())
        .stdin(std::process::Stdio::null())
        .output()
        .context("starting a benchmark row's process")?;
    let stderr = String::from_utf8_lossy(&out.stderr);
    eprint!("{stderr}");
    let what = format!(
        "{} {} (checkpointing {}) at batch {}",
        spec.model,
        spec.precision.name(),
        spec.checkpointing.name(),
        spec.batch
    );
    if out.status.success() {
        let stdout = String::from_utf8_lossy(&out.stdout);
        let line = stdout
            .lines()
            .find_map(|l| l.strip_prefix(ROW_MARKER))
            .with_context(|| format!("{what}: the row's process printed no result"))?;
        return Ok(Ok(serde_json::from_str(line)
            .with_context(|| format!("{what}: reading the row's result"))?));
    }
    #[cfg(unix)]
    let signal = std::os::unix::process::ExitStatusExt::signal(&out.status);
    #[cfg(not(unix))]
    let signal: Option<i32> = None;
    let last = stderr
        .lines()
        .rev()
        .find(|l| !l.trim().is_empty())
        .unwrap_or_default()
        .trim()
        .to_string();
    let lower = stderr.to_ascii_lowercase();
    // the host allocator's abort, the kernel's OOM killer (SIGKILL), or a device allocation
    let oom = lower.contains("memory allocation of")
        || lower.contains("out of memory")
        || lower.contains("out_of_memory")
        || signal == Some(9);
    if oom {
        let error = match signal {
            Some(9) if last.is_empty() => {
                "the process was killed (signal 9): out of host memory".to_string()
            }
            Some(n) => format!("{last} (the process ended on signal {n})"),
            None => last,
        };
        eprintln!("{what}: out of memory: {error}");
        return Ok(Err(OutOfMemory {
            model: spec.model.to_string(),
            precision: spec.precision.name(),
            activation_checkpointing: spec.checkpointing.name(),
            batch: spec.batch,
            error,
        }));
    }
    bail!(
        "{what}: the row's process failed ({}): {last}",
        match signal {
            Some(n) => format!("signal {n}"),
            None => format!("{}", out.status),
        }
    )
}

pub(crate) fn run(args: BenchArgs) -> Result<()> {
    if args.batch.is_empty() || args.batch.iter().any(|&b| b == 0 || b > 4096) {
        bail!("--batch takes batch sizes in 1..=4096");
    }
    if args.train_runs == 0 || args.forward_runs == 0 {
        bail!("--train-runs and --forward-runs must be at least 1");
    }
    if args.train_runs > 1000 || args.forward_runs > 1000 {
        bail!("--train-runs and --forward-runs are at most 1000");
    }
    if args.sample_steps.iter().any(|&n| n == 0 || n > 10_000) {
        bail!("--sample-steps must be in 1..=10000");
    }
    for m in &args.models {
        if m != "bundled" && m != "paper" {
            bail!("--models: unknown network `{m}` (bundled, paper)");
        }
    }
    let rows = plan(&args);
    if rows.len() > 256 {
        bail!(
            "{} rows (--models x --precision x --activation-checkpointing x --batch): at most 256",
            rows.len()
        );
    }
    let dev = model::device()?;
    if let Some(i) = args.worker_row {
        let spec = *rows
            .get(i)
            .with_context(|| format!("--worker-row {i}: the plan has {} rows", rows.len()))?;
        let (cfg, hw) = network(spec, &args, &dev)?;
        let row = bench_row(&cfg, hw, spec, &args, &dev)
            .with_context(|| format!("timing the {} network", spec.model))?;
        println!("{ROW_MARKER}{}", serde_json::to_string(&row)?);
        return Ok(());
    }
    let mut inputs = crate::staging::Inputs::new();
    inputs.add_opt(args.model.as_ref());
    if let Some(path) = &args.json {
        // refuse the output before the minutes of timing
        crate::staging::check_outputs(&[path.as_path()], &inputs, args.force, false)?;
    }
    if args.precision.contains(&Precision::Bf16) && dev.is_cpu() {
        eprintln!(
            "note: bf16 on the CPU runs candle's reference ops and widens its matrix products to \
             f32, so it is slower than f32 here; it is meant for GPUs (--device cuda)"
        );
    }
    let mut report = Report {
        device: format!("{dev:?}"),
        threads: rayon::current_num_threads(),
        rows: Vec::new(),
        out_of_memory: Vec::new(),
        per_sample_memory: Vec::new(),
        generate: Vec::new(),
    };
    for (i, &spec) in rows.iter().enumerate() {
        match measure_in_child(i, spec)? {
            Ok(row) => {
                eprintln!(
                    "{} {} (checkpointing {}): training update {:.1} ms at batch {}, peak memory {}",
                    row.model,
                    row.precision,
                    row.activation_checkpointing,
                    row.train_step_ms,
                    row.batch,
                    row.peak_memory_mib
                        .map_or_else(|| "unavailable".to_string(), |m| format!("{m:.0} MiB"))
                );
                report.rows.push(row);
            }
            Err(oom) => report.out_of_memory.push(oom),
        }
    }
    report.per_sample_memory = per_sample(&report.rows);
    if args.models.iter().any(|m| m == "bundled") && !args.no_generate && !args.no_eval {
        let bundle = model::load_bundle(args.model.as_deref(), &dev)?;
        report.generate = bench_generate(&bundle, &args, &dev)?;
    }
    print_report(&report, &args);
    if let Some(path) = &args.json {
        let text = serde_json::to_string_pretty(&report)?;
        crate::staging::publish_files(
            &[(path.clone(), text.into_bytes())],
            &inputs,
            args.force,
            false,
        )?;
        println!("wrote {}", path.display());
    }
    Ok(())
}

/// The per-sample training memory of every network, precision and checkpointing mode measured
/// at two or more batch sizes: the slope between the smallest and the largest batch.
fn per_sample(rows: &[Row]) -> Vec<PerSample> {
    let mut out: Vec<PerSample> = Vec::new();
    for r in rows {
        let same = |o: &&Row| {
            o.model == r.model
                && o.precision == r.precision
                && o.activation_checkpointing == r.activation_checkpointing
        };
        let group: Vec<&Row> = rows.iter().filter(same).collect();
        let (Some(lo), Some(hi)) = (
            group.iter().min_by_key(|o| o.batch),
            group.iter().max_by_key(|o| o.batch),
        ) else {
            continue;
        };
        let (Some(a), Some(b)) = (lo.peak_memory_mib, hi.peak_memory_mib) else {
            continue;
        };
        let done = out.iter().any(|p| {
            p.model == r.model
                && p.precision == r.precision
                && p.activation_checkpointing == r.activation_checkpointing
        });
        if lo.batch < hi.batch && !done {
            out.push(PerSample {
                model: r.model.clone(),
                precision: r.precision.clone(),
                activation_checkpointing: r.activation_checkpointing.clone(),
                batches: [lo.batch, hi.batch],
                mib_per_sample: (b - a) / (hi.batch - lo.batch) as f64,
            });
        }
    }
    out
}

fn print_report(report: &Report, args: &BenchArgs) {
    println!(
        "veila bench on {} ({} threads), medians:",
        report.device, report.threads
    );
    println!(
        "| network | grid | params | precision | checkpointing | batch | training update (ms) | samples / s | peak memory (MiB) | evaluation, batch 2 (ms) | {} |",
        args.sample_steps
            .iter()
            .map(|n| format!("s / scan, {n} steps"))
            .collect::<Vec<_>>()
            .join(" | ")
    );
    for r in &report.rows {
        println!(
            "| {} | {} x {} | {} | {} | {} | {} | {:.1} | {:.3} | {} | {} | {} |",
            r.model,
            r.grid[0],
            r.grid[1],
            r.params,
            r.precision,
            r.activation_checkpointing,
            r.batch,
            r.train_step_ms,
            r.train_samples_per_s,
            r.peak_memory_mib
                .map_or_else(|| "-".to_string(), |m| format!("{m:.0}")),
            r.eval_b2_ms
                .map_or_else(|| "-".to_string(), |m| format!("{m:.1}")),
            if r.sample_s_per_scan.is_empty() {
                vec!["-"; args.sample_steps.len()].join(" | ")
            } else {
                r.sample_s_per_scan
                    .iter()
                    .map(|(_, s)| format!("{s:.3}"))
                    .collect::<Vec<_>>()
                    .join(" | ")
            }
        );
    }
    for o in &report.out_of_memory {
        println!(
            "| {} | | | {} | {} | {} | out of memory: {} | | | | |",
            o.model, o.precision, o.activation_checkpointing, o.batch, o.error
        );
    }
    for p in &report.per_sample_memory {
        println!(
            "training memory per sample, {} {} (checkpointing {}), batch {} to {}: {:.0} MiB",
            p.model,
            p.precision,
            p.activation_checkpointing,
            p.batches[0],
            p.batches[1],
            p.mib_per_sample
        );
    }
    if !report.generate.is_empty() {
        println!("bundled model end to end (Bundle::generate, f32, one scan):");
        for g in &report.generate {
            println!("  {} steps: {:.3} s", g.steps, g.seconds_per_scan);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::row::{reset_hwm, vm_hwm_mib};
    use super::*;

    fn row(model: &str, ckpt: &str, batch: usize, mib: Option<f64>) -> Row {
        Row {
            model: model.into(),
            precision: "f32".into(),
            activation_checkpointing: ckpt.into(),
            grid: [64, 1024],
            params: 1,
            batch,
            train_step_ms: 1.0,
            train_samples_per_s: 1.0,
            eval_b2_ms: None,
            sample_s_per_scan: Vec::new(),
            peak_memory_mib: mib,
            peak_memory_source: "VmHWM".into(),
        }
    }

    #[test]
    fn per_sample_memory_is_the_slope_between_the_extreme_batches_of_one_setting() {
        let rows = vec![
            row("paper", "none", 1, Some(1000.0)),
            row("paper", "none", 4, Some(2500.0)),
            row("paper", "none", 2, Some(1400.0)),
            row("paper", "block", 1, Some(800.0)),
            row("paper", "block", 2, None),
            row("bundled", "none", 2, Some(100.0)),
        ];
        let p = per_sample(&rows);
        // one setting at two or more batches with both peaks: paper/none only
        assert_eq!(p.len(), 1, "{p:?}");
        assert_eq!(p[0].batches, [1, 4]);
        assert!((p[0].mib_per_sample - 500.0).abs() < 1e-9);
    }

    /// The process's resident size in MiB (`VmRSS`).
    fn vm_rss_mib() -> f64 {
        let status = std::fs::read_to_string("/proc/self/status").unwrap();
        let kb: f64 = status
            .lines()
            .find_map(|l| l.strip_prefix("VmRSS:"))
            .unwrap()
            .trim()
            .trim_end_matches("kB")
            .trim()
            .parse()
            .unwrap();
        kb / 1024.0
    }

    #[test]
    fn the_high_water_mark_reads_and_resets() {
        if !reset_hwm() {
            eprintln!("skipped: /proc/self/clear_refs is not writable here");
            return;
        }
        let before = vm_hwm_mib().expect("VmHWM on Linux");
        let big = vec![1u8; 256 << 20];
        std::hint::black_box(&big);
        let touched = vm_hwm_mib().unwrap();
        assert!(touched >= before + 200.0, "{before} -> {touched} MiB");
        drop(big);
        // the allocator may keep the freed pages a while: a reset brings the mark down to what
        // is resident now (the other tests of this process allocate meanwhile, hence the slack)
        assert!(reset_hwm());
        let (after, rss) = (vm_hwm_mib().unwrap(), vm_rss_mib());
        assert!(after <= touched + 32.0, "reset: {touched} -> {after} MiB");
        assert!(
            (after - rss).abs() < 64.0,
            "reset: mark {after}, resident {rss} MiB"
        );
    }
}
