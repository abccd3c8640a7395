//! `cargo xtask bench-encoders`: seconds per KITTI-size camera image for every pretrained encoder
//! kind, in f32, in f16 and with weights stored in bf16 / f16, with the half-precision features'
//! error next to the time. (candle 0.11's CPU backend has no bf16 convolution, so bf16 can only
//! be a storage format here; f16 computes natively through gemm's f16 kernels.)
//!
//! The weights are seeded random draws in Hugging Face layout, loaded through
//! [`EncoderKind::load_pretrained`] exactly as a bundle loads the real files (none can be
//! downloaded here): the time does not depend on the values, and the precision loss is measured on
//! the same weights and image in both precisions, as the relative L2 error of each feature map
//! against f32 (the worst of the four maps). The image is fitted to each encoder as a bundle does
//! (nearest multiple of 32 for MiT, of 14 for the ViTs: 384 x 1248 and 378 x 1246 for KITTI's
//! 375 x 1242). Runs that take longer than 5 s are timed once; shorter ones get a warm-up and the
//! median of `--runs`.

use std::time::Instant;

use anyhow::{Context, Result, bail};
use candle_core::{DType, Device, Tensor};
use candle_nn::VarMap;
use clap::Args;
use serde::Serialize;
use veila_nn::encoders::ImageEncoder;
use veila_nn::encoders::depth_anything::DepthAnythingV2Encoder;
use veila_nn::encoders::kind::EncoderKind;
use veila_nn::encoders::mit::MitEncoder;

/// Arguments of `cargo xtask bench-encoders`.
#[derive(Debug, Args)]
pub struct BenchEncodersArgs {
    /// Encoder kinds, comma-separated (default: every pretrained kind).
    #[arg(long, value_delimiter = ',')]
    kinds: Vec<String>,
    /// Precisions, comma-separated (f32 is always run: it is the reference): `f16` computes in
    /// f16 (candle's CPU gemm has f16 kernels), `bf16-weights` stores the weights in bf16 and
    /// computes in f32 (candle's CPU convolution has no bf16 kernel), `f16-weights` likewise.
    #[arg(
        long,
        value_delimiter = ',',
        default_value = "f16,bf16-weights,f16-weights"
    )]
    precisions: Vec<String>,
    /// Camera image size `HxW` (default KITTI's 375x1242).
    #[arg(long, default_value = "375x1242")]
    image_size: String,
    /// Timed runs of encoders that take under 5 s (median reported, after one warm-up).
    #[arg(long, default_value_t = 3)]
    runs: usize,
    /// Seed of the weights and the image.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Print one JSON array on stdout instead of the table.
    #[arg(long)]
    json: bool,
}

#[derive(Debug, Serialize)]
struct Row {
    kind: String,
    parameters: usize,
    input: [usize; 2],
    dtype: String,
    seconds_per_image: f64,
    /// Worst relative L2 error of the four feature maps against f32 (0 for f32).
    rel_l2_vs_f32: f64,
}

/// A precision: the dtype weights are stored in, and the one the forward pass computes in.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Precision {
    name: &'static str,
    storage: DType,
    compute: DType,
}

fn parse_precision(s: &str) -> Result<Precision> {
    let p = |name, storage, compute| Precision {
        name,
        storage,
        compute,
    };
    Ok(match s {
        "f32" => p("f32", DType::F32, DType::F32),
        "f16" => p("f16", DType::F16, DType::F16),
        "bf16-weights" => p("bf16-weights", DType::BF16, DType::F32),
        "f16-weights" => p("f16-weights", DType::F16, DType::F32),
        _ => bail!("unknown precision `{s}` (f32, f16, bf16-weights, f16-weights)"),
    })
}

/// The weights rounded to `storage` and widened back (what an f32 forward pass of weights stored
/// in half precision computes with).
fn rounded_weights(bytes: &[u8], storage: DType) -> Result<Vec<u8>> {
    if storage == DType::F32 {
        return Ok(bytes.to_vec());
    }
    let tensors = candle_core::safetensors::load_buffer(bytes, &Device::Cpu)?;
    let rounded = tensors
        .into_iter()
        .map(|(k, t)| Ok((k, t.to_dtype(storage)?.to_dtype(DType::F32)?)))
        .collect::<Result<std::collections::HashMap<_, _>>>()?;
    Ok(veila_nn::checkpoint::safetensors_bytes(
        &rounded,
        std::path::Path::new("rounded.safetensors"),
    )?)
}

/// Seeded random weights of `kind` as the bytes of a Hugging Face-layout safetensors file, and
/// the parameter count.
fn random_weights(kind: EncoderKind, seed: u64) -> Result<(Vec<u8>, usize)> {
    let vm = VarMap::new();
    let vb = veila_nn::seeded_var_builder(&vm, seed, DType::F32, &Device::Cpu);
    if let Some(cfg) = kind.mit_config() {
        MitEncoder::new(&cfg, vb)?;
    } else if let Some(cfg) = kind.depth_anything_config() {
        DepthAnythingV2Encoder::new(&cfg, vb)?;
    } else if let Some(cfg) = kind.dinov2_config() {
        veila_nn::encoders::dinov2::DinoV2Backbone::new(&cfg, vb)?;
    } else {
        bail!("{kind} is not a pretrained kind");
    }
    let tensors = veila_diffusion::app::varmap_tensors(&vm)?;
    let parameters = tensors.values().map(|t| t.elem_count()).sum();
    let bytes = veila_nn::checkpoint::safetensors_bytes(
        &tensors,
        std::path::Path::new("random.safetensors"),
    )?;
    Ok((bytes, parameters))
}

fn flat(ts: &[Tensor]) -> Result<Vec<Vec<f32>>> {
    ts.iter()
        .map(|t| Ok(t.to_dtype(DType::F32)?.flatten_all()?.to_vec1::<f32>()?))
        .collect()
}

fn rel_l2(a: &[f32], b: &[f32]) -> f64 {
    let (mut num, mut den) = (0f64, 0f64);
    for (x, y) in a.iter().zip(b) {
        num += ((x - y) as f64).powi(2);
        den += (*y as f64).powi(2);
    }
    (num / den.max(1e-30)).sqrt()
}

/// Runs `bench-encoders`.
pub fn run(args: BenchEncodersArgs) -> Result<()> {
    let (h, w) = args
        .image_size
        .split_once('x')
        .and_then(|(a, b)| Some((a.parse::<usize>().ok()?, b.parse::<usize>().ok()?)))
        .filter(|&(a, b)| a >= 28 && b >= 28 && a * b <= 4096 * 4096)
        .context("--image-size: expected HxW, each side at least 28, at most 16 Mpx")?;
    let kinds: Vec<EncoderKind> = if args.kinds.is_empty() {
        EncoderKind::all()
            .into_iter()
            .filter(|k| k.is_pretrained())
            .collect()
    } else {
        args.kinds
            .iter()
            .map(|k| k.parse().map_err(|e: String| anyhow::anyhow!(e)))
            .collect::<Result<_>>()?
    };
    let mut precisions = vec![parse_precision("f32")?];
    for d in &args.precisions {
        let d = parse_precision(d)?;
        if !precisions.contains(&d) {
            precisions.push(d);
        }
    }
    // a deterministic street-like image: smooth gradients and texture
    let rgb: Vec<u8> = (0..h * w * 3)
        .map(|i| {
            let (p, c) = (i / 3, i % 3);
            let (y, x) = (p / w, p % w);
            let v = 128.0
                + 60.0 * ((x as f64 / 37.0 + c as f64).sin() * (y as f64 / 23.0).cos())
                + 40.0 * (y as f64 / h as f64)
                + ((p as u64 * 2654435761 + args.seed) % 31) as f64;
            v.clamp(0.0, 255.0) as u8
        })
        .collect();
    let dev = Device::Cpu;
    let mut rows = Vec::new();
    if !args.json {
        eprintln!(
            "{:<26} {:>8} {:>11} {:>12} {:>10} {:>12}",
            "kind", "params", "input", "dtype", "s/image", "rel L2 vs f32"
        );
    }
    for kind in kinds {
        if !kind.is_pretrained() {
            bail!("{kind} is not a pretrained kind");
        }
        let (bytes, parameters) = random_weights(kind, args.seed)?;
        let path = std::path::Path::new("random.safetensors");
        let input = kind.input_size(h, w)?;
        let mut reference: Option<Vec<Vec<f32>>> = None;
        for &prec in &precisions {
            let dtype = prec.compute;
            let weights = if prec.compute == prec.storage {
                bytes.clone()
            } else {
                rounded_weights(&bytes, prec.storage)?
            };
            let enc = kind.load_pretrained(&weights, path, dtype, &dev)?;
            let p = kind.processor();
            let (bytes_in, ih, iw) = p.resize_rgb8(&rgb, h, w)?;
            let x = veila_nn::encoders::rgb8_to_tensor(&bytes_in, ih, iw, &p.normalization, &dev)?
                .to_dtype(dtype)?;
            let time = || -> Result<(f64, Vec<Tensor>)> {
                let t = Instant::now();
                let out = enc.forward(&x)?;
                Ok((t.elapsed().as_secs_f64(), out))
            };
            let (first, out) = time()?;
            let seconds = if first > 5.0 {
                first
            } else {
                let mut v: Vec<f64> = (0..args.runs.max(1))
                    .map(|_| time().map(|r| r.0))
                    .collect::<Result<_>>()?;
                v.sort_by(|a, b| a.total_cmp(b));
                v[v.len() / 2]
            };
            let feats = flat(&out)?;
            let err = match &reference {
                None => {
                    reference = Some(feats);
                    0.0
                }
                Some(r) => r
                    .iter()
                    .zip(&feats)
                    .map(|(a, b)| rel_l2(b, a))
                    .fold(0.0, f64::max),
            };
            let row = Row {
                kind: kind.to_string(),
                parameters,
                input: [input.0, input.1],
                dtype: prec.name.to_string(),
                seconds_per_image: seconds,
                rel_l2_vs_f32: err,
            };
            if !args.json {
                eprintln!(
                    "{:<26} {:>7.1}M {:>11} {:>12} {:>10.2} {:>12.2e}",
                    row.kind,
                    row.parameters as f64 / 1e6,
                    format!("{}x{}", row.input[0], row.input[1]),
                    row.dtype,
                    row.seconds_per_image,
                    row.rel_l2_vs_f32
                );
            }
            rows.push(row);
        }
    }
    if args.json {
        println!("{}", serde_json::to_string_pretty(&rows)?);
    }
    Ok(())
}
