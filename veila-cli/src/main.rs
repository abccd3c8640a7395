//! `veila`: the command-line front end of the Veila workspace.
//!
//! Each command family lives in its own module and contributes a clap `Subcommand` enum that is flattened
//! into [`Command`]. Errors are reported through `anyhow` with the file and the problem named; the process
//! exits non-zero and never leaves partial output behind.

use anyhow::Result;
use clap::{CommandFactory, FromArgMatches, Parser, Subcommand};

/// mimalloc keeps freed blocks for reuse (`veila_nn::process`).
#[global_allocator]
static GLOBAL: veila_nn::process::MiMalloc = veila_nn::process::MiMalloc;

#[macro_use]
mod out; // print! and println! that never panic (declared first: every module below uses them)
mod bounds; // the parsers that hold numeric arguments to their stated ranges
mod choices; // the parsers whose choices are a library's list (sensor presets, datasets, metrics)
mod generation; // what generate and edit share (rig and sampler arguments, scan files)
mod model;
mod progress;
mod report; // self-contained HTML reports (veila eval --report)
mod staging; // the output discipline of every command
mod transport; // the all-reduce of data-parallel `veila train` (TCP on the CPU, NCCL on GPUs)
mod workers; // which worker of a split job this is (--shard-index/--shard-count, Slurm, Kubernetes)
// command modules (one per family):
mod bench_cmd; // bench (training and sampling speed)  (veila-nn, veila-diffusion)
mod convert_cmd; // convert (datasets into training shards) (veila-data::convert)
mod data_cmd; // project, unproject, render           (veila-data)
mod demo_cmd; // demo (the README's main job)
mod demo_table; // the tables demo prints
mod edit_cmd; // edit (RePaint scene editing)         (veila-diffusion::pipeline)
mod eval_cmd; // eval, fd                               (veila-metrics)
mod eval_crossmodal; // CM-DC / CM-SC of eval (maps or networks) (veila-metrics::crossmodal)
mod eval_features; // FRD / FPD features for eval          (veila-nn::feature_nets)
mod eval_files; // which files of a folder eval reads (one per scan)
mod eval_regions; // which regions eval scores (camera-cropped scans have no rear)
mod generate_cmd; // generate                           (veila-diffusion::pipeline)
mod segment_cmd; // segment train / predict / eval        (veila-diffusion::app::segment)
mod sim_cmd; // simulate                               (veila-data::sim)
mod train_cmd; // train (bundles from converted shards) (veila-diffusion::trainer)
mod weather_cmd; // weather                                (veila-data::weather)

/// Panoramic LiDAR generation from a monocular RGB image, and the tools around it.
#[derive(Debug, Parser)]
#[command(name = "veila", version, about, long_about = None)]
struct Cli {
    /// Suppress progress bars and progress lines, and log errors only.
    #[arg(short, long, global = true)]
    quiet: bool,
    /// Log more: -v debug, -vv trace (RUST_LOG, when set, decides instead).
    #[arg(short, long, global = true, action = clap::ArgAction::Count)]
    verbose: u8,
    /// Where the networks run: `cpu`, `cuda` (GPU 0, or the launcher's LOCAL_RANK in a
    /// data-parallel `train`) or `cuda:N`; default: the first GPU of a CUDA build, else the CPU.
    #[arg(long, global = true, value_name = "DEVICE", value_parser = model::parse_device)]
    device: Option<model::DeviceArg>,
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Subcommand)]
enum Command {
    #[command(flatten)]
    Data(data_cmd::DataCmd),
    #[command(flatten)]
    Eval(eval_cmd::EvalCmd),
    #[command(flatten)]
    Sim(sim_cmd::SimCmd),
    #[command(flatten)]
    Weather(weather_cmd::WeatherCmd),
    /// The main job on the bundled default model: simulate a test-split scene, generate its 360°
    /// scan from the camera image alone, and write the generated and true scans, side-by-side
    /// views and the metrics to one folder.
    Demo(demo_cmd::DemoArgs),
    /// Generate panoramic LiDAR scans (KITTI .bin, range EXR, previews) from camera images and
    /// their calibration with a model bundle.
    Generate(generate_cmd::GenerateArgs),
    /// Edit a scan by inpainting: regenerate the pixels a mask image or a 3D box selects, consistent
    /// with the rest of the scan and the camera views (RePaint), and keep every other pixel.
    Edit(edit_cmd::EditArgs),
    /// Time the denoiser's training update (f32 and bf16 mixed precision) and its sampling on
    /// this machine's device, for the bundled network and the paper's 64 x 1024 one.
    Bench(bench_cmd::BenchArgs),
    /// Convert a dataset (KITTI, SemanticKITTI, nuScenes) into training shards (safetensors +
    /// manifest.json) for `veila train`; resumable and shardable across workers.
    Convert(convert_cmd::ConvertArgs),
    /// Train a model bundle (encoders and denoiser) on converted shards from a TOML config;
    /// resumable: rerunning the same config continues from the newest checkpoint.
    Train(train_cmd::TrainArgs),
    /// LiDAR semantic segmentation: train a range-view segmenter, label the points of KITTI
    /// scans (SemanticKITTI `.label` files), score predictions against ground truth.
    Segment {
        #[command(subcommand)]
        cmd: segment_cmd::SegmentCmd,
    },
    /// Print a built-in sensor preset as a sensor file (TOML; a starting point for
    /// `--sensor FILE.toml`).
    Sensors {
        /// The preset.
        #[arg(default_value_t = veila_geom::SensorPreset::default(),
              value_parser = choices::sensor_preset_parser())]
        preset: veila_geom::SensorPreset,
    },
    /// Print a shell completion script (e.g. `veila completions bash > ~/.local/share/bash-completion/completions/veila`).
    Completions {
        /// The shell.
        shell: clap_complete::Shell,
    },
}

/// One example per command, shown at the end of its `--help`.
const EXAMPLES: &[(&str, &str)] = &[
    ("demo", "veila demo --out out/demo --weather fog-moderate"),
    (
        "generate",
        "veila generate --image 000008.png --calib calib/000008.txt --samples 2 --out out/gen",
    ),
    (
        "edit",
        "veila edit --image 000008.png --calib calib/000008.txt --scan out/gen/scan_000.bin \\\n    --remove-box \"5,-2,-2,15,2,1\" --out out/edit",
    ),
    (
        "convert",
        "veila convert --dataset semantickitti --root data/semantic-kitti --split train --out shards/train",
    ),
    (
        "train",
        "veila train --config examples/train.toml --stop-after 500",
    ),
    (
        "bench",
        "veila bench --device cuda --models bundled,paper --precision f32,bf16 --json bench.json",
    ),
    (
        "eval",
        "veila eval --generated out/gen --reference data/velodyne --metrics jsd,mmd --json eval.json",
    ),
    ("fd", "veila fd generated.npy reference.npy --json fd.json"),
    ("sensors", "veila sensors > my-sensor.toml"),
    (
        "segment",
        "veila segment predict --scans data/sequences/08/velodyne --out out/labels",
    ),
    (
        "project",
        "veila project 000008.bin --sensor hdl64e --out 000008.exr --png 000008_range.png",
    ),
    ("unproject", "veila unproject 000008.exr --out 000008.ply"),
    (
        "render",
        "veila render 000008.bin --bev bev.png --range range.png --image 000008.png --calib calib/000008.txt --overlay overlay.png",
    ),
    (
        "simulate",
        "veila simulate --scene scenes/straight_road.toml --out out/sim --frames 4 --seed 1",
    ),
    (
        "weather",
        "veila weather 000008.bin --image 000008.png --calib calib/000008.txt --preset fog-moderate --out out/fog",
    ),
    ("completions", "veila completions zsh > ~/.zfunc/_veila"),
];

/// The clap command with every subcommand's example appended to its help.
fn cli_command() -> clap::Command {
    let mut cmd = Cli::command();
    for (name, example) in EXAMPLES {
        cmd = cmd.mut_subcommand(*name, |c| c.after_help(format!("Example:\n  {example}")));
    }
    cmd
}

fn main() {
    restore_default_sigpipe();
    // SAFETY: first thing in `main`, before any other thread exists.
    #[allow(unsafe_code)]
    unsafe {
        veila_nn::process::tune_process();
    }
    staging::install_signal_cleanup();
    let matches = cli_command().get_matches();
    if let Some(name) = matches.subcommand_name() {
        staging::set_command(name);
    }
    let cli = match Cli::from_arg_matches(&matches) {
        Ok(cli) => cli,
        Err(e) => e.exit(),
    };
    progress::set_quiet(cli.quiet);
    progress::init_logging(cli.verbose, cli.quiet);
    model::set_device(cli.device);
    // a failed write to standard output is an error too (after the command: its files stand)
    if let Err(err) = run(cli.command).and_then(|()| out::finish()) {
        let err = staging::explain(err);
        eprintln!("error: {err:#}");
        std::process::exit(1);
    }
}

/// Rust ignores SIGPIPE, so `println!` panics when stdout is a closed pipe (`veila eval ... | head`).
/// Restore the default disposition, as command-line tools are expected to behave: the process ends
/// quietly when its reader goes away. Output files are unaffected (they are written atomically).
#[cfg(unix)]
fn restore_default_sigpipe() {
    // SAFETY: first statement of `main`, before any other thread exists; `SIG_DFL` is a valid
    // disposition for SIGPIPE.
    #[allow(unsafe_code)]
    unsafe {
        libc::signal(libc::SIGPIPE, libc::SIG_DFL);
    }
}

#[cfg(not(unix))]
fn restore_default_sigpipe() {}

fn run(command: Command) -> Result<()> {
    match command {
        Command::Data(c) => data_cmd::run(c),
        Command::Eval(c) => eval_cmd::run(c),
        Command::Sim(c) => sim_cmd::run(c),
        Command::Weather(c) => weather_cmd::run(c),
        Command::Demo(a) => demo_cmd::run(a),
        Command::Generate(a) => generate_cmd::run(a),
        Command::Edit(a) => edit_cmd::run(a),
        Command::Convert(a) => convert_cmd::run(a),
        Command::Train(a) => train_cmd::run(a),
        Command::Bench(a) => bench_cmd::run(a),
        Command::Segment { cmd } => segment_cmd::run(cmd),
        Command::Completions { shell } => {
            // into memory first: clap_complete panics on a failed write
            let mut script = Vec::new();
            clap_complete::generate(shell, &mut cli_command(), "veila", &mut script);
            out::write_bytes(&script);
            Ok(())
        }
        Command::Sensors { preset } => {
            print!("{}", veila_data::spec::sensor_preset_toml(preset)?);
            Ok(())
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_command_has_one_example_that_parses() {
        let cmd = cli_command();
        let names: Vec<&str> = cmd.get_subcommands().map(|c| c.get_name()).collect();
        for name in &names {
            let n = EXAMPLES.iter().filter(|(c, _)| c == name).count();
            assert_eq!(n, 1, "command `{name}` needs exactly one entry in EXAMPLES");
        }
        for (name, example) in EXAMPLES {
            assert!(
                names.contains(name),
                "EXAMPLES names an unknown command `{name}`"
            );
            // the example parses (shell quoting, line continuations and redirections removed)
            let words: Vec<String> = example
                .split(" > ")
                .next()
                .unwrap_or(example)
                .replace("\\\n", " ")
                .split_whitespace()
                .map(|w| w.trim_matches('"').to_string())
                .collect();
            if let Err(e) = cli_command().try_get_matches_from(&words) {
                panic!("the example of `{name}` does not parse: {e}");
            }
        }
    }

    /// The commands (paths) whose `--long` option offers exactly `library`, in its order; an
    /// option that offers anything else fails the test.
    fn doors_offering(long: &str, library: &[String]) -> Vec<String> {
        let mut args = Vec::new();
        every_argument(&cli_command(), "veila", &mut args);
        let mut doors = Vec::new();
        for (path, arg) in args.iter().filter(|(_, a)| a.get_long() == Some(long)) {
            assert_eq!(offered(arg), library, "`{path} --{long}`");
            doors.push(path.clone());
        }
        doors.sort();
        doors
    }

    /// Every `--sampler` of every command offers exactly the library's samplers
    /// ([`veila_diffusion::SamplerName::ALL`]), in its order: a door cannot forget one.
    #[test]
    fn every_sampler_option_offers_the_librarys_samplers() {
        let library: Vec<String> = veila_diffusion::SamplerName::ALL
            .iter()
            .map(|n| n.to_string())
            .collect();
        let doors = doors_offering("sampler", &library);
        assert_eq!(
            doors,
            ["veila demo", "veila edit", "veila generate"],
            "the commands with --sampler"
        );
    }

    /// Every `--spacing` of every command offers exactly the library's spacings
    /// ([`veila_diffusion::Spacing::ALL`]), in its order.
    #[test]
    fn every_spacing_option_offers_the_librarys_spacings() {
        let library: Vec<String> = veila_diffusion::Spacing::ALL
            .iter()
            .map(|s| s.to_string())
            .collect();
        let doors = doors_offering("spacing", &library);
        assert_eq!(
            doors,
            ["veila demo", "veila edit", "veila generate"],
            "the commands with --spacing"
        );
    }

    /// Every argument of every command and subcommand, with the command's path.
    fn every_argument(cmd: &clap::Command, path: &str, out: &mut Vec<(String, clap::Arg)>) {
        for arg in cmd.get_arguments() {
            out.push((path.to_string(), arg.clone()));
        }
        for sub in cmd.get_subcommands() {
            every_argument(sub, &format!("{path} {}", sub.get_name()), out);
        }
    }

    /// The names an argument offers (its possible values).
    fn offered(arg: &clap::Arg) -> Vec<String> {
        arg.get_possible_values()
            .iter()
            .map(|v| v.get_name().to_string())
            .collect()
    }

    /// Every option that takes a sensor preset offers exactly the library's presets
    /// ([`veila_geom::SensorPreset::ALL`]), in its order: `veila sensors PRESET` as its choices,
    /// and every `--sensor PRESET|FILE` in its help.
    #[test]
    fn every_sensor_option_offers_the_librarys_presets() {
        use veila_geom::SensorPreset;
        let library: Vec<String> = SensorPreset::ALL.iter().map(|p| p.to_string()).collect();
        let mut args = Vec::new();
        every_argument(&cli_command(), "veila", &mut args);
        let (mut choices, mut files) = (0, 0);
        for (path, arg) in &args {
            if path == "veila sensors" && arg.get_id() == "preset" {
                assert_eq!(offered(arg), library, "`{path} PRESET`");
                choices += 1;
            }
            if arg.get_long() == Some("sensor") {
                // a preset or a file: no choices, the presets named in the help
                assert!(offered(arg).is_empty(), "`{path} --sensor` takes files too");
                let help = arg.get_help().map(|h| h.to_string()).unwrap_or_default();
                assert!(
                    help.contains(&library.join(", ")),
                    "`{path} --sensor` names the presets {} in its help: {help}",
                    library.join(", ")
                );
                files += 1;
            }
        }
        assert_eq!(choices, 1, "veila sensors PRESET");
        assert!(
            files >= 3,
            "convert, project and render take --sensor; found {files}"
        );
    }

    /// Every `--dataset` offers exactly the library's datasets
    /// ([`veila_data::dataset::DatasetName::ALL`]), in its order.
    #[test]
    fn every_dataset_option_offers_the_librarys_datasets() {
        let library: Vec<String> = veila_data::dataset::DatasetName::ALL
            .iter()
            .map(|d| d.to_string())
            .collect();
        let doors = doors_offering("dataset", &library);
        assert_eq!(doors, ["veila convert"], "the commands with --dataset");
    }

    /// Every `--metrics` offers exactly the library's metrics
    /// ([`veila_metrics::MetricName::ALL`]), in its order.
    #[test]
    fn every_metric_option_offers_the_librarys_metrics() {
        let library: Vec<String> = veila_metrics::MetricName::ALL
            .iter()
            .map(|m| m.to_string())
            .collect();
        let doors = doors_offering("metrics", &library);
        assert_eq!(doors, ["veila eval"], "the commands with --metrics");
    }

    /// The first "LO to HI" of a help text, as written.
    fn stated_range(help: &str) -> Option<(String, String)> {
        let words: Vec<&str> = help.split_whitespace().collect();
        let num = |w: &str| -> Option<String> {
            let w = w
                .trim_start_matches('(')
                .trim_end_matches([',', ';', ')', ':'])
                .trim_end_matches('.');
            w.parse::<f64>().is_ok().then(|| w.to_string())
        };
        words
            .windows(3)
            .find_map(|w| (w[1] == "to").then(|| Some((num(w[0])?, num(w[2])?)))?)
    }

    /// Options whose range is checked when the command runs, not by the parser (none today).
    const CHECKED_AT_RUN_TIME: &[&str] = &[];

    #[test]
    fn every_numeric_option_states_its_range_and_the_parser_holds_it() {
        use std::any::TypeId;
        let ints = [
            TypeId::of::<u64>(),
            TypeId::of::<usize>(),
            TypeId::of::<u32>(),
        ];
        let floats = [TypeId::of::<f64>(), TypeId::of::<f32>()];
        let cmd = cli_command();
        let mut checked = 0;
        for sub in cmd.get_subcommands() {
            // a parser of this subcommand alone, with nothing required
            let mut lone = sub
                .clone()
                .no_binary_name(true)
                .mut_args(|a| a.required(false));
            for g in sub.get_groups() {
                lone = lone.mut_group(g.get_id().clone(), |g| g.required(false));
            }
            let refused = |long: &str, v: &str| {
                lone.clone()
                    .try_get_matches_from([format!("--{long}={v}")])
                    .err()
                    .is_some_and(|e| {
                        matches!(
                            e.kind(),
                            clap::error::ErrorKind::ValueValidation
                                | clap::error::ErrorKind::InvalidValue
                        )
                    })
            };
            for arg in sub.get_arguments() {
                let t = arg.get_value_parser().type_id();
                let is_int = ints.iter().any(|id| t == *id);
                let is_float = floats.iter().any(|id| t == *id);
                let Some(long) = arg.get_long() else { continue };
                if arg.is_hide_set() || !(is_int || is_float) || CHECKED_AT_RUN_TIME.contains(&long)
                {
                    continue;
                }
                let name = format!("veila {} --{long}", sub.get_name());
                let help = arg.get_help().map(|h| h.to_string()).unwrap_or_default();
                let (lo, hi) = stated_range(&help).unwrap_or_else(|| {
                    panic!("{name}: its help states no range (LO to HI): {help}")
                });
                for v in [&lo, &hi] {
                    assert!(
                        !refused(long, v),
                        "{name}: refuses {v}, in its stated range"
                    );
                }
                let outside: Vec<String> = if is_int {
                    let (lo, hi): (u128, u128) = (lo.parse().unwrap(), hi.parse().unwrap());
                    let mut v = vec![(hi + 1).to_string()];
                    if lo >= 1 {
                        v.push((lo - 1).to_string());
                    }
                    v
                } else {
                    let (lo, hi): (f64, f64) = (lo.parse().unwrap(), hi.parse().unwrap());
                    let d = ((hi - lo) * 1e-3).max(1e-6);
                    vec![
                        (lo - d).to_string(),
                        (hi + d).to_string(),
                        "NaN".into(),
                        "inf".into(),
                    ]
                };
                for v in outside {
                    assert!(
                        refused(long, &v),
                        "{name}: takes {v}, outside its stated range {lo} to {hi}"
                    );
                }
                checked += 1;
            }
        }
        // the detection works: the commands have some thirty numeric options
        assert!(checked >= 30, "only {checked} numeric options found");
    }

    #[test]
    fn completions_name_every_command() {
        for shell in [clap_complete::Shell::Bash, clap_complete::Shell::Zsh] {
            let mut out = Vec::new();
            clap_complete::generate(shell, &mut cli_command(), "veila", &mut out);
            let text = String::from_utf8(out).unwrap();
            for (name, _) in EXAMPLES {
                assert!(text.contains(name), "{shell}: no `{name}`");
            }
            assert!(text.contains("--model"), "{shell}: no flags");
        }
    }

    /// `--model DIR` names a bundle wherever one is loaded; `--checkpoint`, its old name, still
    /// works (scripts written before the rename), without showing in the help.
    #[test]
    fn every_bundle_flag_is_model_with_checkpoint_as_its_alias() {
        let mut with_model = Vec::new();
        for sub in cli_command().get_subcommands() {
            for arg in sub.get_arguments() {
                let aliases = arg.get_all_aliases().unwrap_or_default();
                match arg.get_long() {
                    Some("model") => {
                        assert!(
                            aliases.contains(&"checkpoint"),
                            "`veila {} --model` lacks the --checkpoint alias",
                            sub.get_name()
                        );
                        with_model.push(sub.get_name().to_string());
                    }
                    Some("checkpoint") => {
                        panic!(
                            "`veila {} --checkpoint` is a flag of its own",
                            sub.get_name()
                        )
                    }
                    _ => {}
                }
            }
        }
        with_model.sort();
        assert_eq!(with_model, ["bench", "demo", "edit", "generate"]);
        let matches = cli_command()
            .try_get_matches_from(["veila", "demo", "--checkpoint", "some/bundle"])
            .unwrap();
        let (_, demo) = matches.subcommand().unwrap();
        assert_eq!(
            demo.get_one::<std::path::PathBuf>("model"),
            Some(&std::path::PathBuf::from("some/bundle"))
        );
    }

    #[test]
    fn help_shows_the_example() {
        let mut cmd = cli_command();
        let sub = cmd.find_subcommand_mut("generate").unwrap();
        let help = sub.render_long_help().to_string();
        assert!(
            help.contains("Example:\n  veila generate --image"),
            "{help}"
        );
    }
}
