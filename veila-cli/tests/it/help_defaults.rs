//! Every `--help` text that names a setting of the bundled model agrees with `models/default`: a
//! sampler, a step count or a guidance scale said to be the bundled model's (or printed as a
//! `[default: ..]` of `--sampler`, `--steps`, `--guidance`) is the one `models/default/bundle.json`
//! holds. A help text that says "the bundle's" without a value is always true and is not checked.

use std::path::Path;
use std::process::Command;

/// The sampler settings of `models/default/bundle.json`: (sampler name, steps, guidance).
fn bundled() -> (String, u64, f64) {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../models/default/bundle.json");
    let text = std::fs::read_to_string(&path).expect("models/default/bundle.json");
    let cfg: serde_json::Value = serde_json::from_str(&text).expect("bundle.json is JSON");
    let s = &cfg["sampler"];
    let name = match s["kind"]["kind"].as_str().expect("sampler kind") {
        "ddpm" => "ddpm",
        "ddim" => "ddim",
        "dpm_solver_pp2_m" | "dpm_solver_pp_2m" => "dpm",
        other => panic!("unknown sampler kind {other} in {}", path.display()),
    };
    let steps = s["steps"].as_u64().expect("sampler steps");
    let guidance = s["guidance_scale"].as_f64().unwrap_or(1.0);
    (name.to_string(), steps, guidance)
}

/// One value a help text claims for the bundled model.
#[derive(Debug, Clone, PartialEq)]
enum Claim {
    Sampler(String),
    Steps(u64),
    Guidance(f64),
}

/// The samplers a phrase names (lowercase): `ddpm`, `ddim`, `dpm` (DPM-Solver++).
fn samplers_in(phrase: &str) -> Vec<String> {
    let mut out = Vec::new();
    let words: Vec<&str> = phrase
        .split(|c: char| !(c.is_ascii_alphanumeric() || c == '-' || c == '+'))
        .filter(|w| !w.is_empty())
        .collect();
    for w in words {
        let name = if w == "ddpm" {
            "ddpm"
        } else if w == "ddim" {
            "ddim"
        } else if w == "dpm" || w.starts_with("dpm-solver") {
            "dpm"
        } else {
            continue;
        };
        out.push(name.to_string());
    }
    out
}

/// The number just before `word` in `phrase` ("4 steps" -> 4), for every occurrence.
fn numbers_before(phrase: &str, word: &str) -> Vec<f64> {
    let toks: Vec<&str> = phrase.split_whitespace().collect();
    toks.windows(2)
        .filter(|w| w[1].trim_matches(|c: char| !c.is_alphanumeric()) == word)
        .filter_map(|w| {
            w[0].trim_matches(|c: char| c == '(' || c == ',')
                .parse()
                .ok()
        })
        .collect()
}

/// The number just after `word` in `phrase` ("guidance 1.5" -> 1.5), for every occurrence.
fn numbers_after(phrase: &str, word: &str) -> Vec<f64> {
    let toks: Vec<&str> = phrase.split_whitespace().collect();
    toks.windows(2)
        .filter(|w| w[0].trim_matches(|c: char| !c.is_alphanumeric()) == word)
        .filter_map(|w| w[1].trim_end_matches([')', ',', ';', '.']).parse().ok())
        .collect()
}

/// The help text of the option `flag` (from its line to the next option's).
fn option_block<'h>(help: &'h str, flag: &str) -> Option<&'h str> {
    let lines: Vec<&str> = help.lines().collect();
    let start = lines.iter().position(|l| {
        let t = l.trim_start();
        t.starts_with(flag) && t[flag.len()..].starts_with([' ', '=', '\n', '<']) || t == flag
    })?;
    let end = lines[start + 1..]
        .iter()
        .position(|l| {
            let t = l.trim_start();
            t.starts_with("--") || (t.starts_with('-') && t.len() > 1 && t.as_bytes()[1] != b'-')
        })
        .map_or(lines.len(), |k| start + 1 + k);
    let first = help.find(lines[start])?;
    let last = lines[end - 1];
    let stop = help[first..].find(last).map(|k| first + k + last.len())?;
    Some(&help[first..stop])
}

/// Every value a help text states for the bundled model: in the phrases that name it ("... for
/// the bundled model", split at sentence ends and `;`), and in every default of `--sampler`, `--steps`
/// and `--guidance` ("default ddim", "[default: 16]"; "default: the bundle's" names no value).
fn claims(help: &str) -> Vec<Claim> {
    // paragraphs: an option's or a possible value's line (`-x`, `--x`, `- name:`) or a blank line
    // starts a new one, so a phrase never runs from one option into the next
    let mut paragraphs: Vec<String> = vec![String::new()];
    for line in help.lines() {
        let l = line.trim_start();
        if l.is_empty() || l.starts_with('-') {
            paragraphs.push(String::new());
        }
        let last = paragraphs.last_mut().expect("one paragraph");
        last.push(' ');
        last.push_str(&l.to_lowercase());
    }
    let mut out = Vec::new();
    for paragraph in &paragraphs {
        // sentences end at ". " or ";" (a bare "." may be a decimal point)
        let flat = paragraph.split_whitespace().collect::<Vec<_>>().join(" ") + " ";
        let flat = flat.replace(". ", "\u{1}");
        for phrase in flat.split(['\u{1}', ';']) {
            if !phrase.contains("bundled") {
                continue;
            }
            out.extend(samplers_in(phrase).into_iter().map(Claim::Sampler));
            out.extend(
                numbers_before(phrase, "steps")
                    .into_iter()
                    .map(|v| Claim::Steps(v as u64)),
            );
            out.extend(
                numbers_after(phrase, "guidance")
                    .into_iter()
                    .map(Claim::Guidance),
            );
        }
    }
    for flag in ["--sampler", "--steps", "--guidance"] {
        let Some(block) = option_block(help, flag) else {
            continue;
        };
        let block = block
            .split_whitespace()
            .collect::<Vec<_>>()
            .join(" ")
            .to_lowercase();
        // every "default X" of the option: what follows up to `)`, `]`, `;` or `.`
        for (k, _) in block.match_indices("default") {
            let rest = block[k + "default".len()..].trim_start_matches([':', ' ']);
            let value = rest.split(". ").next().unwrap_or("");
            let value = value.split([')', ']', ';']).next().unwrap_or("").trim();
            match flag {
                "--sampler" => out.extend(samplers_in(value).into_iter().map(Claim::Sampler)),
                "--steps" => out.extend(
                    value
                        .split_whitespace()
                        .next()
                        .and_then(|v| v.parse().ok())
                        .map(Claim::Steps),
                ),
                _ => out.extend(
                    value
                        .split_whitespace()
                        .next()
                        .and_then(|v| v.parse().ok())
                        .map(Claim::Guidance),
                ),
            }
        }
    }
    out
}

/// The claims of `help` that disagree with the bundle's settings.
fn wrong(help: &str, (sampler, steps, guidance): &(String, u64, f64)) -> Vec<Claim> {
    claims(help)
        .into_iter()
        .filter(|c| match c {
            Claim::Sampler(s) => s != sampler,
            Claim::Steps(n) => n != steps,
            Claim::Guidance(g) => (g - guidance).abs() > 1e-9,
        })
        .collect()
}

fn help_of(cmd: &str) -> String {
    let o = Command::new(env!("CARGO_BIN_EXE_veila"))
        .args([cmd, "--help"])
        .output()
        .expect("veila runs");
    assert!(o.status.success(), "veila {cmd} --help failed");
    String::from_utf8(o.stdout).expect("help is UTF-8")
}

#[test]
fn the_checker_finds_a_wrong_default_and_passes_a_true_one() {
    let bundle = ("ddpm".to_string(), 4, 1.5);
    let bad = "      --sampler <SAMPLER>\n          Sampler (default: the bundle's, DPM-Solver++(2M) for the\n          bundled model).\n      --steps <N>\n          Steps [default: 16]\n      --guidance <S>\n          The bundled model samples 8 steps at guidance 2.\n";
    assert_eq!(
        wrong(bad, &bundle),
        vec![
            Claim::Sampler("dpm".into()),
            Claim::Steps(8),
            Claim::Guidance(2.0),
            Claim::Sampler("dpm".into()),
            Claim::Steps(16),
        ]
    );
    let edit = "      --sampler <SAMPLER>\n          Sampler: ddpm or ddim (inpainting cannot use the multistep dpm\n          solver; default ddim)\n\n          Possible values:\n          - ddpm: Ancestral DDPM\n      --steps <N>\n";
    assert_eq!(wrong(edit, &bundle), vec![Claim::Sampler("ddim".into())]);
    let good = "      --sampler <SAMPLER>\n          Sampler (default: the bundle's: DDPM, 4 steps, guidance 1.5\n          for the bundled model).\n      --steps <N>\n          Sampler steps (default: the bundle's).\n";
    assert_eq!(
        claims(good),
        vec![
            Claim::Sampler("ddpm".into()),
            Claim::Steps(4),
            Claim::Guidance(1.5),
            Claim::Sampler("ddpm".into()),
        ]
    );
    assert!(wrong(good, &bundle).is_empty());
}

/// `generate`'s `--sampler` help named DPM-Solver++(2M) as the bundled model's sampler, and
/// `edit`'s a DDIM default, while `models/default` samples with 4 DDPM steps (which `edit` keeps);
/// the fixes are in `generate_cmd.rs` and `edit_cmd.rs`.
#[test]
fn help_defaults_agree_with_the_bundled_model() {
    let bundle = bundled();
    for cmd in ["demo", "generate", "edit", "bench"] {
        let help = help_of(cmd);
        let bad = wrong(&help, &bundle);
        assert!(
            bad.is_empty(),
            "`veila {cmd} --help` states {bad:?} for the bundled model, but models/default/bundle.json has sampler {} with {} steps and guidance {}:\n{help}",
            bundle.0,
            bundle.1,
            bundle.2
        );
    }
}
