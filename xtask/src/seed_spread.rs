//! `cargo xtask seed-spread`: recipes ranked by the mean over their seeds on the real frames.
//!
//! One `bench-real` report says what one trained network does on four real frames, and on those
//! frames two seeds of the same recipe differ by more than any two recipes do (BENCHMARKS.md, issue
//! 18). So a recipe is judged by several seeds: each `--recipe LABEL=DIR,DIR,...` names the
//! `bench-real` output folders of one recipe's seeds, and this command prints, per real frame and
//! recipe, the chosen method's range MAE in view (mean ± sample std over the seeds and the number
//! of seeds below the mean scan), its front-half MAE, the depth encoder's AbsRel, and the
//! recipe's own mean scan; then each recipe's difference to the first one with its standard error
//! `sqrt(s1²/n1 + s2²/n2)`. A last row per recipe averages each seed over every frame first (and
//! counts the frames it wins against its mean scan), then over the seeds: one figure to rank
//! recipes by, next to the per-frame rows it summarises. It reads the reports only: nothing is
//! trained or sampled.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use clap::Args;

use crate::bench_real::RealReport;

/// Arguments of `cargo xtask seed-spread`.
#[derive(Debug, Args)]
pub struct SeedSpreadArgs {
    /// One recipe: `LABEL=DIR,DIR,...`, the `bench-real --out` folders of its seeds (each holds
    /// `report.json`). Repeat for every recipe; differences are taken to the first.
    #[arg(long = "recipe", required = true)]
    recipes: Vec<String>,
    /// Method row to aggregate: `mean-network` (the residual bundle's mean network alone, the
    /// short probe runs' only trained part) or `model` (the sampled scans).
    #[arg(long, default_value = "mean-network")]
    method: String,
    /// Also write the table to this Markdown file (written whole or not at all).
    #[arg(long)]
    out: Option<PathBuf>,
}

/// One recipe: its label and its seeds' reports.
#[derive(Debug)]
pub struct Recipe {
    /// Label as given.
    pub label: String,
    /// One report per seed, with the folder it came from.
    pub runs: Vec<(PathBuf, RealReport)>,
}

/// Mean, sample standard deviation and count of some values.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Stat {
    /// Mean.
    pub mean: f64,
    /// Sample standard deviation (`n - 1` in the denominator; 0 for one value).
    pub std: f64,
    /// Number of values.
    pub n: usize,
}

impl Stat {
    /// `None` for no values.
    pub fn of(v: &[f64]) -> Option<Self> {
        if v.is_empty() {
            return None;
        }
        let (mean, std) = crate::simdata::mean_std(v);
        Some(Self {
            mean,
            std,
            n: v.len(),
        })
    }
}

/// One recipe's figures on one frame, over its seeds.
#[derive(Debug, Clone, PartialEq)]
pub struct FrameStat {
    /// The method's range MAE in view, m (each seed's mean over its samples).
    pub view: Stat,
    /// Seeds whose view MAE is below their own mean scan's.
    pub below_mean_scan: usize,
    /// The method's front-half MAE, m (`None` for a cropped frame).
    pub front: Option<Stat>,
    /// Depth encoder AbsRel (`None` without a depth head).
    pub abs_rel: Option<Stat>,
    /// The mean scan's view MAE (the same for every seed of one scene list).
    pub mean_scan_view: Option<Stat>,
    /// The mean scan's front-half MAE.
    pub mean_scan_front: Option<Stat>,
}

/// Parses `LABEL=DIR,DIR,...` and reads every folder's `report.json`.
pub fn read_recipe(spec: &str) -> Result<Recipe> {
    let (label, dirs) = spec
        .split_once('=')
        .with_context(|| format!("--recipe {spec:?}: expected LABEL=DIR,DIR,..."))?;
    let label = label.trim();
    if label.is_empty() {
        bail!("--recipe {spec:?}: the label is empty");
    }
    let dirs: Vec<&str> = dirs
        .split(',')
        .map(str::trim)
        .filter(|d| !d.is_empty())
        .collect();
    if dirs.is_empty() {
        bail!("--recipe {spec:?}: no report folder");
    }
    let runs = dirs
        .iter()
        .map(|d| {
            let dir = PathBuf::from(d);
            let report = read_report(&dir.join("report.json"))?;
            Ok((dir, report))
        })
        .collect::<Result<Vec<_>>>()?;
    Ok(Recipe {
        label: label.to_string(),
        runs,
    })
}

fn read_report(path: &Path) -> Result<RealReport> {
    let text =
        std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
    serde_json::from_str(&text)
        .with_context(|| format!("{} is not a bench-real report.json", path.display()))
}

/// Every frame named by any run of any recipe, in first-seen order.
pub fn frame_names(recipes: &[Recipe]) -> Vec<String> {
    let mut names: Vec<String> = Vec::new();
    for r in recipes {
        for (_, rep) in &r.runs {
            for f in &rep.frames {
                if !names.contains(&f.frame) {
                    names.push(f.frame.clone());
                }
            }
        }
    }
    names
}

/// `recipe`'s figures on `frame` for `method`, over the seeds whose report has both (`None` when
/// none has).
pub fn frame_stat(recipe: &Recipe, frame: &str, method: &str) -> Option<FrameStat> {
    let (mut view, mut front, mut rel, mut ms_view, mut ms_front) =
        (vec![], vec![], vec![], vec![], vec![]);
    let mut below = 0;
    for (_, rep) in &recipe.runs {
        let Some(f) = rep.frames.iter().find(|f| f.frame == frame) else {
            continue;
        };
        let Some(row) = f.rows.iter().find(|r| r.method == method) else {
            continue;
        };
        view.push(row.view_mae_m.mean);
        if let Some(fr) = &row.front_mae_m {
            front.push(fr.mean);
        }
        if let Some(d) = &f.encoder_depth {
            rel.push(d.abs_rel);
        }
        if let Some(ms) = f.rows.iter().find(|r| r.method == "mean-scan") {
            ms_view.push(ms.view_mae_m.mean);
            if let Some(fr) = &ms.front_mae_m {
                ms_front.push(fr.mean);
            }
            if row.view_mae_m.mean < ms.view_mae_m.mean {
                below += 1;
            }
        }
    }
    Some(FrameStat {
        view: Stat::of(&view)?,
        below_mean_scan: below,
        front: Stat::of(&front),
        abs_rel: Stat::of(&rel),
        mean_scan_view: Stat::of(&ms_view),
        mean_scan_front: Stat::of(&ms_front),
    })
}

/// Difference of two means and its standard error `sqrt(s_a²/n_a + s_b²/n_b)`; no standard error
/// when either side has a single seed (its spread is unknown, not zero).
pub fn difference(a: &Stat, b: &Stat) -> (f64, Option<f64>) {
    let se = (a.n > 1 && b.n > 1)
        .then(|| (a.std.powi(2) / a.n as f64 + b.std.powi(2) / b.n as f64).sqrt());
    (a.mean - b.mean, se)
}

/// `recipe` over all of `frames` at once: per seed, the mean of the view MAE over the frames and
/// the number of frames below its mean scan; then the mean ± std of the first and the mean of the
/// second over the seeds. Seeds that lack a frame are left out; `None` when none has them all.
pub fn overall(recipe: &Recipe, frames: &[String], method: &str) -> Option<(Stat, f64)> {
    let (mut means, mut wins) = (Vec::new(), Vec::new());
    for (_, rep) in &recipe.runs {
        let mut sum = 0.0;
        let mut below = 0usize;
        let mut all = true;
        for name in frames {
            let Some(f) = rep.frames.iter().find(|f| &f.frame == name) else {
                all = false;
                break;
            };
            let row = f.rows.iter().find(|r| r.method == method);
            let ms = f.rows.iter().find(|r| r.method == "mean-scan");
            match (row, ms) {
                (Some(r), Some(m)) => {
                    sum += r.view_mae_m.mean;
                    below += usize::from(r.view_mae_m.mean < m.view_mae_m.mean);
                }
                _ => {
                    all = false;
                    break;
                }
            }
        }
        if all && !frames.is_empty() {
            means.push(sum / frames.len() as f64);
            wins.push(below as f64);
        }
    }
    let st = Stat::of(&means)?;
    Some((st, wins.iter().sum::<f64>() / wins.len() as f64))
}

/// The Δ cell: `st` minus the first recipe's `first` (`-` on the first recipe's own row).
fn delta_cell(st: &Stat, first: Option<&Stat>, is_first: bool) -> String {
    match first {
        Some(f) if !is_first => match difference(st, f) {
            (d, Some(se)) => format!("{d:+.2} ± {se:.2}"),
            (d, None) => format!("{d:+.2} (one seed)"),
        },
        _ => "-".to_string(),
    }
}

fn pm(s: &Stat) -> String {
    if s.n > 1 {
        format!("{:.2} ± {:.2}", s.mean, s.std)
    } else {
        format!("{:.2}", s.mean)
    }
}

/// The Markdown table: one block of rows per frame, one row per recipe.
pub fn markdown(recipes: &[Recipe], method: &str) -> String {
    let mut s = String::new();
    let _ = writeln!(
        s,
        "`{method}` on the real frames, mean ± sample std over each recipe's seeds (`bench-real` \
         reports). View / front = range MAE in the camera's view / the front half (m); `< mean \
         scan` = seeds whose view MAE is below their own mean scan's; Δ view = the difference to \
         the first recipe ± its standard error (none when a recipe has one seed).\n"
    );
    for r in recipes {
        let dirs: Vec<String> = r
            .runs
            .iter()
            .map(|(d, _)| d.display().to_string())
            .collect();
        let _ = writeln!(s, "- {}: {}", r.label, dirs.join(", "));
    }
    let _ = writeln!(
        s,
        "\n| frame | recipe | seeds | view | < mean scan | Δ view | front | depth AbsRel | mean scan view / front |\n|---|---|---|---|---|---|---|---|---|"
    );
    let frames = frame_names(recipes);
    for frame in &frames {
        let first = recipes.first().and_then(|r| frame_stat(r, frame, method));
        for (i, r) in recipes.iter().enumerate() {
            let Some(st) = frame_stat(r, frame, method) else {
                let _ = writeln!(s, "| {frame} | {} | 0 | - | - | - | - | - | - |", r.label);
                continue;
            };
            let delta = delta_cell(&st.view, first.as_ref().map(|f| &f.view), i == 0);
            let opt = |x: &Option<Stat>| x.as_ref().map_or("-".to_string(), pm);
            let ms = match (&st.mean_scan_view, &st.mean_scan_front) {
                (Some(v), Some(f)) => format!("{:.2} / {:.2}", v.mean, f.mean),
                (Some(v), None) => format!("{:.2}", v.mean),
                _ => "-".to_string(),
            };
            let _ = writeln!(
                s,
                "| {frame} | {} | {} | {} | {}/{} | {delta} | {} | {} | {ms} |",
                r.label,
                st.view.n,
                pm(&st.view),
                st.below_mean_scan,
                st.view.n,
                opt(&st.front),
                opt(&st.abs_rel),
            );
        }
    }
    let first = recipes.first().and_then(|r| overall(r, &frames, method));
    for (i, r) in recipes.iter().enumerate() {
        let Some((st, wins)) = overall(r, &frames, method) else {
            continue;
        };
        let delta = delta_cell(&st, first.as_ref().map(|(f, _)| f), i == 0);
        let _ = writeln!(
            s,
            "| mean over the {} frames | {} | {} | {} | {wins:.1}/{} | {delta} | | | |",
            frames.len(),
            r.label,
            st.n,
            pm(&st),
            frames.len(),
        );
    }
    s
}

/// `cargo xtask seed-spread`.
pub fn run(args: SeedSpreadArgs) -> Result<()> {
    let recipes = args
        .recipes
        .iter()
        .map(|r| read_recipe(r))
        .collect::<Result<Vec<_>>>()?;
    let has_method = recipes.iter().flat_map(|r| &r.runs).any(|(_, rep)| {
        rep.frames
            .iter()
            .any(|f| f.rows.iter().any(|row| row.method == args.method))
    });
    if !has_method {
        bail!(
            "no report has a `{}` row (methods: model, mean-network, mean-scan, flat-ground)",
            args.method
        );
    }
    let md = markdown(&recipes, &args.method);
    if let Some(out) = &args.out {
        veila_data::atomic::write_atomic(out, md.as_bytes())
            .with_context(|| format!("writing {}", out.display()))?;
    }
    print!("{md}");
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::bench_real::{DepthScore, RealFrameResult, RealRow, Spread};

    fn row(method: &str, view: f64, front: Option<f64>) -> RealRow {
        let sp = |m| Spread { mean: m, std: 0.0 };
        RealRow {
            method: method.to_string(),
            view_mae_m: sp(view),
            view_coverage: 1.0,
            front_mae_m: front.map(sp),
            front_unseen_mae_m: None,
            view_chamfer_m2: sp(1.0),
        }
    }

    fn report(net_view: f64, mean_scan: f64, abs_rel: f64) -> RealReport {
        RealReport {
            seeds: 1,
            sampler: "ddpm 4 steps".into(),
            missing: vec![],
            frames: vec![RealFrameResult {
                frame: "kitti-000001".into(),
                encoder_depth: Some(DepthScore {
                    abs_rel,
                    mae_m: 1.0,
                    coverage: 1.0,
                }),
                encoder_depth_regions: vec![],
                ground_depth: None,
                real_view_returns: 10,
                rows: vec![
                    row("mean-network", net_view, Some(net_view - 1.0)),
                    row("mean-scan", mean_scan, Some(2.0)),
                ],
                overlay: "real/x.png".into(),
            }],
        }
    }

    fn recipe(label: &str, reports: Vec<RealReport>) -> Recipe {
        Recipe {
            label: label.into(),
            runs: reports
                .into_iter()
                .enumerate()
                .map(|(i, r)| (PathBuf::from(format!("s{i}")), r))
                .collect(),
        }
    }

    #[test]
    fn a_frame_is_aggregated_over_the_seeds() {
        // view MAE 4, 5, 6: mean 5, sample std 1; two of them below the mean scan's 5.5
        let r = recipe(
            "a",
            vec![
                report(4.0, 5.5, 0.2),
                report(5.0, 5.5, 0.3),
                report(6.0, 5.5, 0.4),
            ],
        );
        let st = frame_stat(&r, "kitti-000001", "mean-network").unwrap();
        assert_eq!(st.view.n, 3);
        assert!((st.view.mean - 5.0).abs() < 1e-12);
        assert!((st.view.std - 1.0).abs() < 1e-12);
        assert_eq!(st.below_mean_scan, 2);
        let front = st.front.unwrap();
        assert!((front.mean - 4.0).abs() < 1e-12);
        let rel = st.abs_rel.unwrap();
        assert!((rel.mean - 0.3).abs() < 1e-12 && (rel.std - 0.1).abs() < 1e-12);
        assert!((st.mean_scan_view.unwrap().mean - 5.5).abs() < 1e-12);
        assert!(frame_stat(&r, "kitti-000001", "model").is_none());
        assert!(frame_stat(&r, "kitti-000000", "mean-network").is_none());
    }

    #[test]
    fn the_difference_carries_the_standard_error_of_two_means() {
        // a: 5 ± 1 (n 3), b: 3 ± 2 (n 4): se = sqrt(1/3 + 4/4)
        let a = Stat {
            mean: 5.0,
            std: 1.0,
            n: 3,
        };
        let b = Stat {
            mean: 3.0,
            std: 2.0,
            n: 4,
        };
        let (d, se) = difference(&a, &b);
        assert!((d - 2.0).abs() < 1e-12);
        assert!((se.unwrap() - (1.0f64 / 3.0 + 1.0).sqrt()).abs() < 1e-12);
        // one seed has no known spread: no standard error rather than a falsely small one
        let one = Stat {
            mean: 4.0,
            std: 0.0,
            n: 1,
        };
        assert_eq!(difference(&one, &b), (1.0, None));
    }

    #[test]
    fn the_table_has_a_row_per_recipe_and_the_difference_to_the_first() {
        let a = recipe("plain", vec![report(4.0, 5.5, 0.2), report(6.0, 5.5, 0.2)]);
        let b = recipe("other", vec![report(3.0, 5.0, 0.2), report(3.0, 5.0, 0.2)]);
        let md = markdown(&[a, b], "mean-network");
        assert!(
            md.contains("| kitti-000001 | plain | 2 | 5.00 ± 1.41 | 1/2 | - |"),
            "{md}"
        );
        // other - plain = -2, se = sqrt(2/2 + 0) = 1
        assert!(
            md.contains("| kitti-000001 | other | 2 | 3.00 ± 0.00 | 2/2 | -2.00 ± 1.00 |"),
            "{md}"
        );
    }

    #[test]
    fn the_overall_row_averages_frames_per_seed_then_seeds() {
        // two frames per seed: seed 0 views 4 and 6 (mean 5, one below its mean scan of 5.5),
        // seed 1 views 2 and 4 (mean 3, both below)
        let two = |a: f64, b: f64| {
            let mut r = report(a, 5.5, 0.2);
            let mut f = r.frames[0].clone();
            f.frame = "kitti-000000".into();
            f.rows[0].view_mae_m.mean = b;
            r.frames.push(f);
            r
        };
        let r = recipe("a", vec![two(4.0, 6.0), two(2.0, 4.0)]);
        let frames = frame_names(std::slice::from_ref(&r));
        let (st, wins) = overall(&r, &frames, "mean-network").unwrap();
        assert_eq!(st.n, 2);
        assert!((st.mean - 4.0).abs() < 1e-12);
        assert!((st.std - 2f64.sqrt()).abs() < 1e-12);
        assert!((wins - 1.5).abs() < 1e-12);
        // a seed without one of the frames is left out of the overall row
        let r = recipe("b", vec![two(4.0, 6.0), report(1.0, 5.5, 0.2)]);
        let (st, _) = overall(&r, &frames, "mean-network").unwrap();
        assert_eq!(st.n, 1);
        assert!((st.mean - 5.0).abs() < 1e-12);
        assert!(overall(&r, &frames, "model").is_none());
    }

    #[test]
    fn bad_specs_and_missing_reports_are_named() {
        let err = read_recipe("no-equals-sign").unwrap_err().to_string();
        assert!(err.contains("LABEL=DIR"), "{err}");
        let err = read_recipe("=a,b").unwrap_err().to_string();
        assert!(err.contains("label is empty"), "{err}");
        let dir = std::env::temp_dir().join(format!("veila-seed-spread-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let err = format!(
            "{:#}",
            read_recipe(&format!("x={}", dir.display())).unwrap_err()
        );
        assert!(err.contains("report.json"), "{err}");
        std::fs::write(dir.join("report.json"), "{\"not\": 1}").unwrap();
        let err = format!(
            "{:#}",
            read_recipe(&format!("x={}", dir.display())).unwrap_err()
        );
        assert!(err.contains("not a bench-real report.json"), "{err}");
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn the_committed_bench_real_report_reads() {
        // the shipped bundle's report, as bench-real wrote it: the format this command reads
        let path = crate::simdata::workspace_root().join("docs/bench-real/report.json");
        let rep = read_report(&path).unwrap();
        assert!(rep.frames.iter().any(|f| f.frame == "kitti-000001"));
        let r = Recipe {
            label: "shipped".into(),
            runs: vec![(PathBuf::from("docs/bench-real"), rep)],
        };
        let st = frame_stat(&r, "kitti-000001", "mean-network").unwrap();
        assert_eq!(st.view.n, 1);
        assert!(st.view.mean > 0.0 && st.abs_rel.is_some());
    }

    #[test]
    fn a_written_report_reads_back() {
        let rep = report(4.0, 5.5, 0.25);
        let json = serde_json::to_string(&rep).unwrap();
        let back: RealReport = serde_json::from_str(&json).unwrap();
        assert_eq!(back.frames[0].rows[0].view_mae_m.mean, 4.0);
        assert_eq!(back.frames[0].encoder_depth.unwrap().abs_rel, 0.25);
    }
}
