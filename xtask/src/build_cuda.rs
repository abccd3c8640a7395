//! `cargo xtask build-cuda`: builds `veila` with `--features cuda` on a machine without a GPU or a
//! CUDA installation, for carrying to one that has them.
//!
//! 1. **Toolkit from PyPI.** `pip install --no-deps --target DIR` of CUDA 13.0 wheels, every one
//!    pinned (a resolver left alone mixes in NVVM 13.5, whose PTX the 13.0 `ptxas` rejects):
//!    `nvidia-cuda-nvcc`, `-crt`, `nvidia-nvvm`, `nvidia-cuda-cccl` and `-runtime` hold `nvcc` and
//!    the headers; `nvidia-cublas`, `nvidia-curand` and `nvidia-cuda-nvrtc` the libraries the binary
//!    links; `--cudnn` / `--nccl` add theirs. All in one command: a second `--target` install would
//!    replace the shared `nvidia/` folder. A stamp file records the pins, so reruns skip it.
//! 2. **Link folder.** The wheels ship `libX.so.N` without the `libX.so` the linker asks for, and
//!    no `libcuda` (the driver): `DIR/link/` gets the missing names as symbolic links, and
//!    `libcuda.so` as a stub (soname `libcuda.so.1`) defining every `cu*` symbol cudarc's bindings
//!    declare, compiled with the machine's `cc`. On the GPU machine the real driver answers.
//! 3. **Build.** `cargo build --release -p veila-cli --features cuda` (with `--xtask` also
//!    `-p xtask`, for `train-default --device cuda`) with `nvcc` on `PATH`,
//!    `CUDA_COMPUTE_CAP` (default 90: H100 / H200) for candle's kernels, `CUDA_PATH` and
//!    `-L DIR/link`. The binary is `target/release/veila`; `--target-dir` keeps it apart from the
//!    CPU build.
//!
//! `--dry-run` prints the three steps' commands and environment and runs nothing.

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};
use std::process::Command;

use anyhow::{Context, Result, bail};
use clap::Args;

/// The CUDA 13.0 wheels, pinned (the GPU machine's driver 580 runs CUDA 13.0).
pub const TOOLKIT_WHEELS: &[&str] = &[
    "nvidia-cuda-nvcc==13.0.88",
    "nvidia-cuda-crt==13.0.88",
    "nvidia-nvvm==13.0.88",
    "nvidia-cuda-cccl==13.0.85",
    "nvidia-cuda-runtime==13.0.88",
    "nvidia-cuda-nvrtc==13.0.88",
    "nvidia-cublas==13.0.2.14",
    "nvidia-curand==10.4.0.35",
];
/// cuDNN for CUDA 13 (`--cudnn`).
pub const CUDNN_WHEEL: &str = "nvidia-cudnn-cu13==9.13.1.26";
/// NCCL for CUDA 13 (`--nccl`).
pub const NCCL_WHEEL: &str = "nvidia-nccl-cu13==2.27.7";

/// Arguments of `cargo xtask build-cuda`.
#[derive(Debug, Args)]
pub struct BuildCudaArgs {
    /// GPU compute capability the kernels are compiled for (90: H100 / H200; 80: A100; 89: L4 /
    /// RTX 40xx).
    #[arg(long, default_value_t = 90)]
    compute_cap: u32,
    /// Where the PyPI toolkit and the link folder go.
    #[arg(long, default_value = "target/cuda-13.0")]
    toolkit: PathBuf,
    /// Cargo target folder of the CUDA build (apart from the CPU build's).
    #[arg(long, default_value = "target/cuda")]
    target_dir: PathBuf,
    /// Also install cuDNN and build with candle's `cudnn` feature.
    #[arg(long)]
    cudnn: bool,
    /// Also install NCCL (for multi-GPU runs).
    #[arg(long)]
    nccl: bool,
    /// The Python that runs pip.
    #[arg(long, default_value = "python3")]
    python: String,
    /// Print the commands and the environment, run nothing.
    #[arg(long)]
    dry_run: bool,
    /// Also write `TARGET_DIR/veila-cuda.xz`: the binary stripped of debug info and xz-compressed
    /// (213 MB -> 20 MB), to carry to a GPU machine (`xz -d veila-cuda.xz` there). Needs `strip`
    /// and `xz`.
    #[arg(long)]
    pack: bool,
    /// Also build `xtask` with its `cuda` feature (`train-default --device cuda`), in the same
    /// cargo run; `--pack` then also writes `TARGET_DIR/xtask-cuda.xz`.
    #[arg(long)]
    xtask: bool,
}

/// The wheels of a build.
pub fn wheels(cudnn: bool, nccl: bool) -> Vec<&'static str> {
    let mut w = TOOLKIT_WHEELS.to_vec();
    if cudnn {
        w.push(CUDNN_WHEEL);
    }
    if nccl {
        w.push(NCCL_WHEEL);
    }
    w
}

/// The `cu*` function names declared in cudarc's driver bindings (`extern "C" { fn cuX(...` ).
pub fn driver_symbols(bindings: &str) -> BTreeSet<String> {
    let mut out = BTreeSet::new();
    let mut in_extern = false;
    for line in bindings.lines() {
        let t = line.trim_start();
        if t.starts_with("extern \"C\"") {
            in_extern = true;
            continue;
        }
        if in_extern {
            if let Some(rest) = t.strip_prefix("fn ")
                && let Some(name) = rest.split('(').next()
                && name.starts_with("cu")
                && name.chars().all(|c| c.is_ascii_alphanumeric() || c == '_')
            {
                out.insert(name.to_string());
            }
            if t.starts_with('}') {
                in_extern = false;
            }
        }
    }
    out
}

/// C source of the stub driver: every symbol returns `CUDA_ERROR_STUB_LIBRARY` (34).
pub fn stub_source(symbols: &BTreeSet<String>) -> String {
    let mut s = String::from(
        "/* libcuda stub for linking only (cargo xtask build-cuda); the driver answers at run time */\n",
    );
    for name in symbols {
        s.push_str(&format!("int {name}(void) {{ return 34; }}\n"));
    }
    s
}

/// The environment of the cargo build.
pub fn build_env(toolkit: &Path, compute_cap: u32) -> Vec<(String, String)> {
    let cu = toolkit.join("nvidia/cu13");
    let path = format!(
        "{}:{}",
        cu.join("bin").display(),
        std::env::var("PATH").unwrap_or_default()
    );
    vec![
        ("PATH".into(), path),
        ("CUDA_PATH".into(), cu.display().to_string()),
        ("CUDA_COMPUTE_CAP".into(), compute_cap.to_string()),
        (
            "RUSTFLAGS".into(),
            format!("-L native={}", toolkit.join("link").display()),
        ),
    ]
}

fn cudarc_bindings() -> Result<PathBuf> {
    let home = std::env::var_os("CARGO_HOME")
        .map(PathBuf::from)
        .or_else(|| std::env::var_os("HOME").map(|h| PathBuf::from(h).join(".cargo")))
        .context("neither CARGO_HOME nor HOME is set")?;
    let src = home.join("registry/src");
    for index in std::fs::read_dir(&src).with_context(|| format!("{}", src.display()))? {
        let p = index?.path().join("cudarc-0.19.10/src/driver/sys/mod.rs");
        if p.is_file() {
            return Ok(p);
        }
    }
    bail!(
        "cudarc 0.19.10's sources are not under {}: run `cargo fetch` first",
        src.display()
    )
}

fn run_cmd(cmd: &mut Command, what: &str) -> Result<()> {
    let status = cmd
        .status()
        .with_context(|| format!("{what}: cannot start {cmd:?}"))?;
    if !status.success() {
        bail!("{what} failed ({status}): {cmd:?}");
    }
    Ok(())
}

/// The cargo features of `veila` for these options.
pub fn features(cudnn: bool, nccl: bool) -> String {
    let mut f = vec!["cuda"];
    if cudnn {
        f.push("cudnn");
    }
    if nccl {
        f.push("nccl");
    }
    f.join(",")
}

/// The `-p` and `--features` arguments of the cargo build: `veila` alone, or with `xtask` (the
/// features then name their package, as cargo asks when several are built).
pub fn package_args(cudnn: bool, nccl: bool, xtask: bool) -> Vec<String> {
    let f = features(cudnn, nccl);
    if !xtask {
        return ["-p", "veila-cli", "--features", &f]
            .map(String::from)
            .to_vec();
    }
    let mut all: Vec<String> = f.split(',').map(|x| format!("veila-cli/{x}")).collect();
    all.push("xtask/cuda".into());
    vec![
        "-p".into(),
        "veila-cli".into(),
        "-p".into(),
        "xtask".into(),
        "--features".into(),
        all.join(","),
    ]
}

/// Runs `build-cuda`.
pub fn run(mut a: BuildCudaArgs) -> Result<()> {
    // build scripts run in their own folders: every path handed to them must be absolute
    a.toolkit = std::path::absolute(&a.toolkit)?;
    if !(30..=130).contains(&a.compute_cap) {
        bail!(
            "--compute-cap {}: expected e.g. 80, 86, 89, 90, 100",
            a.compute_cap
        );
    }
    let wheels = wheels(a.cudnn, a.nccl);
    let stamp = a.toolkit.join("wheels.txt");
    let want_stamp = wheels.join("\n");
    let mut pip = Command::new(&a.python);
    pip.args(["-m", "pip", "install", "--no-deps", "--target"])
        .arg(&a.toolkit)
        .args(&wheels);
    let mut cargo = Command::new(std::env::var("CARGO").unwrap_or_else(|_| "cargo".into()));
    cargo
        .args(["build", "--release", "--locked"])
        .args(package_args(a.cudnn, a.nccl, a.xtask))
        .arg("--target-dir")
        .arg(&a.target_dir);
    let env = build_env(&a.toolkit, a.compute_cap);
    if a.dry_run {
        println!("1. {pip:?}");
        println!(
            "2. link folder {}: lib*.so links, libcuda stub",
            a.toolkit.join("link").display()
        );
        for (k, v) in &env {
            println!("   {k}={v}");
        }
        println!("3. {cargo:?}");
        if a.pack {
            for name in packed_binaries(a.xtask) {
                let [strip, xz] =
                    pack_commands(&a.target_dir.join("release").join(name), &a.target_dir);
                println!("4. {strip:?}\n   {xz:?}");
            }
        }
        return Ok(());
    }
    // 1. toolkit
    if std::fs::read_to_string(&stamp).ok().as_deref() != Some(want_stamp.as_str()) {
        let _ = std::fs::remove_dir_all(&a.toolkit);
        std::fs::create_dir_all(&a.toolkit)?;
        run_cmd(&mut pip, "installing the CUDA wheels")?;
        std::fs::write(&stamp, &want_stamp)?;
    }
    let cu = a.toolkit.join("nvidia/cu13");
    if !cu.join("bin/nvcc").is_file() {
        bail!("{}: no nvcc after the install", cu.join("bin").display());
    }
    // 2. link folder
    let link = a.toolkit.join("link");
    let _ = std::fs::remove_dir_all(&link);
    std::fs::create_dir_all(&link)?;
    // every `lib` folder of the wheels (nvidia/cu13/lib, nvidia/cudnn/lib, nvidia/nccl/lib, ...)
    let mut libdirs = Vec::new();
    let mut stack = vec![(a.toolkit.join("nvidia"), 0)];
    while let Some((dir, depth)) = stack.pop() {
        if dir.file_name().is_some_and(|n| n == "lib") {
            libdirs.push(dir.clone());
        }
        if depth < 3
            && let Ok(rd) = std::fs::read_dir(&dir)
        {
            for e in rd.flatten() {
                if e.path().is_dir() {
                    stack.push((e.path(), depth + 1));
                }
            }
        }
    }
    for dir in &libdirs {
        for e in std::fs::read_dir(dir)? {
            let p = e?.path();
            let name = p
                .file_name()
                .map(|n| n.to_string_lossy().into_owned())
                .unwrap_or_default();
            // libcublas.so.13 -> link/libcublas.so
            if let Some(i) = name.find(".so.") {
                let plain = link.join(&name[..i + 3]);
                if !plain.exists() {
                    std::os::unix::fs::symlink(&p, &plain)?;
                }
            }
        }
    }
    let symbols = driver_symbols(&std::fs::read_to_string(cudarc_bindings()?)?);
    if symbols.len() < 100 {
        bail!(
            "found only {} driver symbols in cudarc's bindings",
            symbols.len()
        );
    }
    let c = link.join("cuda_stub.c");
    std::fs::write(&c, stub_source(&symbols))?;
    run_cmd(
        Command::new("cc")
            .args(["-shared", "-fPIC", "-Wl,-soname,libcuda.so.1", "-o"])
            .arg(link.join("libcuda.so"))
            .arg(&c),
        "compiling the libcuda stub",
    )?;
    // 3. build
    for (k, v) in &env {
        cargo.env(k, v);
    }
    let t = std::time::Instant::now();
    run_cmd(&mut cargo, "the CUDA build")?;
    let built: Vec<String> = packed_binaries(a.xtask)
        .iter()
        .map(|n| a.target_dir.join("release").join(n).display().to_string())
        .collect();
    println!(
        "built {} in {:.0} s (compute capability {}); on the GPU machine put the CUDA 13 libraries \
         (cublas, curand, nvrtc{}) on LD_LIBRARY_PATH",
        built.join(" and "),
        t.elapsed().as_secs_f64(),
        a.compute_cap,
        if a.cudnn { ", cudnn" } else { "" }
    );
    if a.pack {
        let mib = |p: &Path| std::fs::metadata(p).map(|m| m.len() as f64 / 1048576.0);
        for name in packed_binaries(a.xtask) {
            let packed = pack(&a.target_dir.join("release").join(name), &a.target_dir)?;
            println!(
                "packed {} ({:.0} MiB; `xz -d` it on the GPU machine)",
                packed.display(),
                mib(&packed)?
            );
        }
    }
    Ok(())
}

/// The binaries a build writes (`veila`, and `xtask` with `--xtask`).
pub fn packed_binaries(xtask: bool) -> &'static [&'static str] {
    if xtask {
        &["veila", "xtask"]
    } else {
        &["veila"]
    }
}

/// The commands that make `dir/NAME-cuda.xz` from `binary` (`dir/release/NAME`): a stripped copy,
/// then xz.
pub fn pack_commands(binary: &Path, dir: &Path) -> [Command; 2] {
    let copy = stripped_copy(binary, dir);
    let mut strip = Command::new("strip");
    strip.arg("-o").arg(&copy).arg(binary);
    let mut xz = Command::new("xz");
    xz.args(["-6", "-T0", "-f"]).arg(&copy);
    [strip, xz]
}

/// Strips and compresses `binary` into `dir/NAME-cuda.xz` (the stripped copy is replaced by it).
fn pack(binary: &Path, dir: &Path) -> Result<PathBuf> {
    let [mut strip, mut xz] = pack_commands(binary, dir);
    run_cmd(&mut strip, "stripping the binary (binutils' `strip`)")?;
    run_cmd(&mut xz, "compressing the binary (`xz`)")?;
    Ok(stripped_copy(binary, dir).with_extension("xz"))
}

/// `dir/NAME-cuda` for `binary` `.../NAME`: the stripped copy that xz then replaces by `.xz`.
fn stripped_copy(binary: &Path, dir: &Path) -> PathBuf {
    let name = binary
        .file_name()
        .unwrap_or("veila".as_ref())
        .to_string_lossy();
    dir.join(format!("{name}-cuda"))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn packing_strips_a_copy_then_compresses_it_in_place() {
        let [strip, xz] = pack_commands(Path::new("/t/cuda/release/veila"), Path::new("/t/cuda"));
        let args = |c: &Command| -> Vec<String> {
            c.get_args()
                .map(|a| a.to_string_lossy().into_owned())
                .collect()
        };
        assert_eq!(strip.get_program(), "strip");
        assert_eq!(
            args(&strip),
            ["-o", "/t/cuda/veila-cuda", "/t/cuda/release/veila"]
        );
        assert_eq!(xz.get_program(), "xz");
        assert_eq!(args(&xz), ["-6", "-T0", "-f", "/t/cuda/veila-cuda"]);
    }

    #[test]
    fn xtask_is_built_beside_veila_with_package_qualified_features() {
        assert_eq!(
            package_args(false, false, false),
            ["-p", "veila-cli", "--features", "cuda"]
        );
        assert_eq!(
            package_args(true, true, true),
            [
                "-p",
                "veila-cli",
                "-p",
                "xtask",
                "--features",
                "veila-cli/cuda,veila-cli/cudnn,veila-cli/nccl,xtask/cuda"
            ]
        );
        assert_eq!(packed_binaries(true), ["veila", "xtask"]);
        let [strip, _] = pack_commands(Path::new("/t/cuda/release/xtask"), Path::new("/t/cuda"));
        let last = strip
            .get_args()
            .nth(1)
            .unwrap()
            .to_string_lossy()
            .into_owned();
        assert_eq!(last, "/t/cuda/xtask-cuda");
    }

    #[test]
    fn the_options_choose_the_features_and_wheels() {
        assert_eq!(features(false, false), "cuda");
        assert_eq!(features(true, false), "cuda,cudnn");
        assert_eq!(features(false, true), "cuda,nccl");
        assert_eq!(features(true, true), "cuda,cudnn,nccl");
        assert!(wheels(false, true).contains(&NCCL_WHEEL));
        assert!(!wheels(false, false).contains(&NCCL_WHEEL));
    }

    #[test]
    fn every_wheel_is_pinned_to_cuda_13_0() {
        for w in wheels(true, true) {
            let (name, version) = w
                .split_once("==")
                .unwrap_or_else(|| panic!("{w} is not pinned"));
            assert!(name.starts_with("nvidia-"), "{w}");
            assert!(!version.contains('*'), "{w}");
            if name.starts_with("nvidia-cuda-") || name == "nvidia-nvvm" {
                assert!(version.starts_with("13.0."), "{w}");
            }
        }
        assert_eq!(wheels(false, false).len(), TOOLKIT_WHEELS.len());
    }

    #[test]
    fn driver_symbols_come_from_extern_blocks_only() {
        let src = r#"
pub unsafe fn cuInit(Flags: u32) -> CUresult {
    #[cfg(not(feature = "dynamic-loading"))]
    {
        extern "C" {
            fn cuInit(Flags: ::core::ffi::c_uint) -> CUresult;
        }
        cuInit(Flags)
    }
}
extern "C" {
    fn cuMemAlloc_v2(p: *mut u64, n: usize) -> CUresult;
    fn helper(x: u32);
}
fn cuNotExtern() {}
"#;
        let s = driver_symbols(src);
        assert_eq!(
            s.into_iter().collect::<Vec<_>>(),
            vec!["cuInit".to_string(), "cuMemAlloc_v2".to_string()]
        );
        let c = stub_source(&["cuInit".to_string()].into_iter().collect());
        assert!(c.contains("int cuInit(void) { return 34; }"));
    }

    #[test]
    fn the_build_environment_names_nvcc_the_capability_and_the_link_folder() {
        let env = build_env(Path::new("/t/cuda"), 80);
        let get = |k: &str| {
            env.iter()
                .find(|(a, _)| a == k)
                .map(|(_, v)| v.clone())
                .unwrap()
        };
        assert!(get("PATH").starts_with("/t/cuda/nvidia/cu13/bin:"));
        assert_eq!(get("CUDA_COMPUTE_CAP"), "80");
        assert_eq!(get("CUDA_PATH"), "/t/cuda/nvidia/cu13");
        assert_eq!(get("RUSTFLAGS"), "-L native=/t/cuda/link");
    }
}
