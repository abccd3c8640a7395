//! `--device` of the xtask commands that run networks (`train-default`, `bench-model`): the CPU or
//! one GPU of a `cuda` build. `veila`'s own `--device` differs on purpose: its `cuda` means the
//! launcher's `LOCAL_RANK` in a data-parallel run, and without the flag it takes a GPU when one is
//! there; these commands run one process and default to the CPU.

use anyhow::{Context, Result};
use candle_core::Device;

/// `--device`: the CPU or one GPU by ordinal.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum DeviceArg {
    /// The CPU.
    Cpu,
    /// GPU `n`.
    Cuda(usize),
}

impl DeviceArg {
    /// The candle device (an error when this build has no CUDA or there is no such GPU).
    pub fn open(self) -> Result<Device> {
        match self {
            DeviceArg::Cpu => Ok(Device::Cpu),
            DeviceArg::Cuda(n) => Device::new_cuda(n).with_context(|| {
                format!(
                    "--device cuda:{n}: cannot open the GPU{}",
                    if cfg!(feature = "cuda") {
                        ""
                    } else {
                        " (this xtask is built without the `cuda` feature: `cargo xtask build-cuda --xtask`)"
                    }
                )
            }),
        }
    }

    /// The name the provenance records.
    pub fn name(self) -> String {
        match self {
            DeviceArg::Cpu => "cpu".into(),
            DeviceArg::Cuda(n) => format!("cuda:{n}"),
        }
    }
}

/// Parses `cpu`, `cuda` or `cuda:N`.
pub fn parse_device(s: &str) -> std::result::Result<DeviceArg, String> {
    match s {
        "cpu" => Ok(DeviceArg::Cpu),
        "cuda" => Ok(DeviceArg::Cuda(0)),
        _ => s
            .strip_prefix("cuda:")
            .and_then(|n| n.parse().ok())
            .map(DeviceArg::Cuda)
            .ok_or_else(|| format!("expected cpu, cuda or cuda:N, got {s:?}")),
    }
}
