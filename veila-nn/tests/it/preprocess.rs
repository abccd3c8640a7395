//! Preprocessing against its references: Pillow's resampling byte for byte, and the pixel values of
//! transformers' `SegformerImageProcessorPil` and `DPTImageProcessorPil` (Depth-Anything-V2
//! settings). `tests/data/preprocess/make_preprocess.py` made the reference file (run by hand).

use std::collections::HashMap;
use std::path::Path;

use candle_core::{DType, Device, Tensor};
use veila_nn::encoders::preprocess::{ImageProcessor, Resample, ResizeRule, resize_rgb8};

fn reference() -> HashMap<String, Tensor> {
    let path =
        Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/preprocess/preprocess.safetensors");
    candle_core::safetensors::load(&path, &Device::Cpu)
        .unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

fn bytes(t: &Tensor) -> (Vec<u8>, usize, usize) {
    let (h, w, c) = t.dims3().unwrap();
    assert_eq!(c, 3);
    (t.flatten_all().unwrap().to_vec1::<u8>().unwrap(), h, w)
}

/// Pillow runs the two passes (each rounded to u8) in an order that depends on the sizes; with
/// either fixed order 6 to 10 of these 30 cases differ in hundreds of bytes, so this covers the rule.
#[test]
fn resize_matches_pillow_byte_for_byte() {
    let r = reference();
    let (image, h, w) = bytes(&r["image"]);
    let mut checked = 0;
    for (name, filter) in [
        ("bilinear", Resample::Bilinear),
        ("bicubic", Resample::Bicubic),
    ] {
        let mut keys: Vec<&String> = r
            .keys()
            .filter(|k| k.starts_with(&format!("pil_{name}_")))
            .collect();
        keys.sort();
        assert!(keys.len() >= 6, "too few {name} references");
        for key in keys {
            let (want, oh, ow) = bytes(&r[key]);
            let got = resize_rgb8(&image, (h, w), (oh, ow), filter).unwrap();
            let diff = got.iter().zip(&want).filter(|(a, b)| a != b).count();
            assert_eq!(
                diff,
                0,
                "{key}: {diff} of {} bytes differ from Pillow",
                want.len()
            );
            checked += 1;
        }
    }
    assert_eq!(checked, 30);
}

#[test]
fn a_changed_filter_is_detected() {
    // the references tell the two filters apart, so the test above can fail
    let r = reference();
    let (image, h, w) = bytes(&r["image"]);
    let (want, oh, ow) = bytes(&r["pil_bicubic_20x30"]);
    let got = resize_rgb8(&image, (h, w), (oh, ow), Resample::Bilinear).unwrap();
    assert!(got.iter().zip(&want).filter(|(a, b)| a != b).count() > 100);
}

fn max_abs_diff(got: &Tensor, want: &Tensor) -> f32 {
    assert_eq!(got.dims(), want.dims());
    let d = (got.to_dtype(DType::F32).unwrap() - want)
        .unwrap()
        .abs()
        .unwrap();
    d.flatten_all()
        .unwrap()
        .max(0)
        .unwrap()
        .to_scalar::<f32>()
        .unwrap()
}

#[test]
fn segformer_processor_matches_transformers() {
    let r = reference();
    let (image, h, w) = bytes(&r["image"]);
    let p = ImageProcessor::segformer(32, 48);
    let got = p
        .preprocess(&image, h, w, &Device::Cpu)
        .unwrap()
        .squeeze(0)
        .unwrap();
    let err = max_abs_diff(&got, &r["segformer"]);
    assert!(err < 1e-5, "max |diff| {err}");
}

#[test]
fn depth_anything_processor_matches_transformers() {
    let r = reference();
    let (image, h, w) = bytes(&r["image"]);
    // the -hf settings with the script's 56x56 target
    let p = ImageProcessor {
        resize: ResizeRule::KeepAspectMultiple {
            height: 56,
            width: 56,
            multiple: 14,
        },
        ..ImageProcessor::depth_anything_v2()
    };
    assert_eq!(p.output_size(h, w).unwrap(), (42, 56));
    let got = p
        .preprocess(&image, h, w, &Device::Cpu)
        .unwrap()
        .squeeze(0)
        .unwrap();
    let err = max_abs_diff(&got, &r["depth_anything"]);
    assert!(err < 1e-5, "max |diff| {err}");
}

#[test]
fn bad_sizes_are_errors_not_panics() {
    let img = vec![0u8; 4 * 5 * 3];
    assert!(resize_rgb8(&img, (4, 5), (0, 3), Resample::Bicubic).is_err());
    assert!(resize_rgb8(&img, (5, 5), (3, 3), Resample::Bicubic).is_err());
    assert!(resize_rgb8(&img, (4, 5), (1 << 20, 1 << 20), Resample::Bicubic).is_err());
    // a tiny image far below Depth-Anything's target still gets a size; a huge target is refused
    let huge = ImageProcessor {
        resize: ResizeRule::Exact {
            height: 1 << 16,
            width: 1 << 16,
        },
        ..ImageProcessor::segformer(1, 1)
    };
    assert!(huge.preprocess(&img, 4, 5, &Device::Cpu).is_err());
    let tiny = ImageProcessor {
        resize: ResizeRule::KeepAspectMultiple {
            height: 14,
            width: 14,
            multiple: 14,
        },
        ..ImageProcessor::depth_anything_v2()
    };
    let e = tiny.output_size(2, 400).unwrap_err().to_string();
    assert!(e.contains("too small"), "{e}");
}

#[test]
fn nearest_multiple_keeps_fitting_sizes() {
    let p = ImageProcessor {
        resize: ResizeRule::NearestMultiple { multiple: 14 },
        ..ImageProcessor::depth_anything_v2()
    };
    assert_eq!(p.output_size(98, 322).unwrap(), (98, 322));
    assert_eq!(p.output_size(96, 320).unwrap(), (98, 322));
    let img: Vec<u8> = (0..98 * 322 * 3).map(|i| (i % 251) as u8).collect();
    let (out, h, w) = p.resize_rgb8(&img, 98, 322).unwrap();
    assert_eq!((h, w), (98, 322));
    assert_eq!(out, img);
}
