//! With the `cuda` feature: compiles `src/fused/cuda/kernels.cu` to PTX (`nvcc --ptx`, for the
//! compute capability in `CUDA_COMPUTE_CAP`, default 90: H100 / H200), which `fused/cuda.rs`
//! embeds. `cargo xtask build-cuda` puts `nvcc` on `PATH` and sets the capability. Without the
//! feature it does nothing.

use std::path::PathBuf;
use std::process::Command;

fn main() {
    const SRC: &str = "src/fused/cuda/kernels.cu";
    println!("cargo::rerun-if-changed={SRC}");
    println!("cargo::rerun-if-env-changed=CUDA_COMPUTE_CAP");
    println!("cargo::rerun-if-env-changed=NVCC");
    if std::env::var_os("CARGO_FEATURE_CUDA").is_none() {
        return;
    }
    let cap = std::env::var("CUDA_COMPUTE_CAP").unwrap_or_else(|_| "90".into());
    let nvcc = std::env::var("NVCC").unwrap_or_else(|_| "nvcc".into());
    let out = PathBuf::from(std::env::var_os("OUT_DIR").expect("cargo sets OUT_DIR"))
        .join("veila_kernels.ptx");
    let status = Command::new(&nvcc)
        .args(["--ptx", &format!("-arch=sm_{cap}"), "-O3", SRC, "-o"])
        .arg(&out)
        .status();
    match status {
        Ok(s) if s.success() => {}
        Ok(s) => panic!("`{nvcc} --ptx {SRC}` failed ({s}): see its messages above"),
        Err(e) => panic!(
            "the `cuda` feature needs nvcc to compile {SRC} ({nvcc}: {e}); \
             `cargo xtask build-cuda` installs one and puts it on PATH"
        ),
    }
}
