//! Configs from strangers' files (issue 58): absurd sizes are config errors naming the field, never
//! a hang, a panic or an aborting allocation; the presets stay within every bound.

use std::sync::mpsc;
use std::time::Duration;

use veila_nn::encoders::depth_anything::DepthAnythingV2Config;
use veila_nn::encoders::dinov2::DinoV2Config;
use veila_nn::encoders::kind::EncoderKind;
use veila_nn::encoders::mit::{MitConfig, SegFormerConfig};
use veila_nn::encoders::small_cnn::SmallCnnConfig;
use veila_nn::feature_nets::{PointNetConfig, RangeNetConfig, RangeStage};
use veila_nn::weights::{MAX_PARAMETERS, record_tensor_specs};
use veila_nn::{DenoiserConfig, Error, PfcConfig};

/// The message of a config error (panics on success or on another error).
fn config_err<T: std::fmt::Debug>(r: veila_nn::Result<T>) -> String {
    match r {
        Err(Error::Config(m)) => m,
        other => panic!("expected a config error, got {other:?}"),
    }
}

/// Runs `f` on a thread and fails the test if it takes longer than 10 s.
fn within_seconds<T: Send + 'static>(f: impl FnOnce() -> T + Send + 'static) -> T {
    let (tx, rx) = mpsc::channel();
    std::thread::spawn(move || {
        let _ = tx.send(f());
    });
    rx.recv_timeout(Duration::from_secs(10))
        .expect("did not finish within 10 s")
}

#[test]
fn groups_for_returns_at_once_for_a_huge_bound_and_as_before_otherwise() {
    use veila_nn::ops::groups_for;
    let g = within_seconds(|| {
        (
            groups_for(96, 1_000_000_000_000_000_000),
            groups_for(7, usize::MAX),
        )
    });
    assert_eq!(g, (96, 7));
    // the scan of every bound up to `max_groups`, as it was
    let reference = |c: usize, m: usize| {
        (1..=m.max(1))
            .rev()
            .find(|g| c.is_multiple_of(*g))
            .unwrap_or(1)
    };
    for c in 1..=200 {
        for m in 0..=80 {
            assert_eq!(groups_for(c, m), reference(c, m), "channels {c}, max {m}");
        }
    }
}

#[test]
fn a_u_net_of_65_or_more_levels_is_a_config_error() {
    for levels in [9, 64, 65, 66, 1000] {
        let mut cfg = DenoiserConfig::tiny().unconditional();
        cfg.channel_mults = vec![1; levels];
        cfg.pfc = None;
        let m = config_err(cfg.validate());
        assert!(
            m.contains("channel_mults") && m.contains(&veila_nn::config::MAX_LEVELS.to_string()),
            "{levels} levels: {m}"
        );
    }
}

#[test]
fn absurd_denoiser_sizes_are_config_errors_naming_the_field() {
    type Edit = fn(&mut DenoiserConfig);
    let cases: [(&str, Edit); 13] = [
        ("base_channels", |c| c.base_channels = 1_000_000),
        ("in_channels", |c| c.in_channels = 1 << 40),
        ("num_res_blocks", |c| c.num_res_blocks = 1 << 40),
        ("norm_groups", |c| c.norm_groups = 1_000_000_000_000_000_000),
        ("channel_mults[1]", |c| c.channel_mults[1] = usize::MAX),
        ("time.dim", |c| c.time.dim = 1 << 40),
        ("pfc.num_heads", |c| {
            c.pfc = Some(PfcConfig { num_heads: 1 << 40 })
        }),
        ("gcma.attn_dim", |c| gcma(c).attn_dim = 1 << 40),
        ("gcma.num_heads", |c| gcma(c).num_heads = 1 << 40),
        ("cond_channels[0]", |c| cond(c).cond_channels[0] = 1 << 40),
        ("semantic_channels[2]", |c| {
            cond(c).semantic_channels[2] = 1 << 40
        }),
        ("feature_sizes[1]", |c| {
            cond(c).feature_sizes[1] = [1 << 40, 1 << 40]
        }),
        ("num_views", |c| cond(c).num_views = 1 << 40),
    ];
    for (field, edit) in cases {
        let mut cfg = DenoiserConfig::tiny();
        edit(&mut cfg);
        let m = config_err(cfg.validate());
        assert!(m.contains(field) && m.contains("limit"), "{field}: {m}");
    }
    let mut cfg = DenoiserConfig::tiny();
    cfg.time.max_period = f64::INFINITY;
    assert!(cfg.validate().is_err());
}

fn cond(c: &mut DenoiserConfig) -> &mut veila_nn::ConditioningConfig {
    c.conditioning.as_mut().unwrap()
}

fn gcma(c: &mut DenoiserConfig) -> &mut veila_nn::GcmaConfig {
    cond(c).gcma.as_mut().unwrap()
}

#[test]
fn the_presets_and_the_bundled_model_are_within_the_bounds() {
    for cfg in [
        DenoiserConfig::tiny(),
        DenoiserConfig::small(),
        DenoiserConfig::paper(),
        DenoiserConfig::paper().unconditional(),
    ] {
        cfg.validate().unwrap();
    }
    let bundle: serde_json::Value =
        serde_json::from_str(include_str!("../../../models/default/bundle.json")).unwrap();
    let den: DenoiserConfig = serde_json::from_value(bundle["denoiser"].clone()).unwrap();
    den.validate().unwrap();
    for enc in ["semantic_encoder", "depth_encoder"] {
        let c: SmallCnnConfig = serde_json::from_value(bundle[enc]["config"].clone()).unwrap();
        c.validate().unwrap();
    }
    SmallCnnConfig::default().validate().unwrap();
    for kind in EncoderKind::all() {
        if let Some(c) = kind.mit_config() {
            c.validate().unwrap();
        }
        if let Some(c) = kind.segformer_cityscapes_config() {
            c.validate().unwrap();
        }
        if let Some(c) = kind.depth_anything_config() {
            c.validate().unwrap();
        }
        if let Some(c) = kind.dinov2_config() {
            c.validate().unwrap();
        }
    }
    for c in [
        RangeNetConfig::darknet21(),
        RangeNetConfig::darknet53(),
        RangeNetConfig::small(),
    ] {
        c.validate().unwrap();
    }
    for c in [PointNetConfig::sparenet(), PointNetConfig::small()] {
        c.validate().unwrap();
    }
}

#[test]
fn absurd_encoder_sizes_are_config_errors_naming_the_field() {
    let small = |edit: fn(&mut SmallCnnConfig)| {
        let mut c = SmallCnnConfig::default();
        edit(&mut c);
        config_err(c.validate())
    };
    for (field, m) in [
        ("channels[1]", small(|c| c.channels[1] = 1_000_000)),
        ("blocks[3]", small(|c| c.blocks[3] = 1 << 40)),
        ("num_classes", small(|c| c.num_classes = 1 << 40)),
        ("head_channels", small(|c| c.head_channels = 1 << 40)),
        ("norm_groups", small(|c| c.norm_groups = 1 << 60)),
        ("in_channels", small(|c| c.in_channels = 1 << 40)),
    ] {
        assert!(m.contains(field) && m.contains("limit"), "{field}: {m}");
    }
    let mut mit = MitConfig::mit_b0();
    mit.depths[2] = 1 << 40;
    assert!(config_err(mit.validate()).contains("depths[2]"));
    let mut mit = MitConfig::mit_b0();
    mit.strides[0] = 1 << 20;
    assert!(config_err(mit.validate()).contains("strides[0]"));
    let mut seg = SegFormerConfig::b0_cityscapes();
    seg.num_labels = 1 << 40;
    assert!(config_err(seg.validate()).contains("num_labels"));
    let mut dino = DinoV2Config::vit_small_14();
    dino.image_size = 1 << 40;
    assert!(config_err(dino.validate()).contains("image_size"));
    let mut dino = DinoV2Config::vit_small_14();
    dino.num_hidden_layers = 1 << 40;
    assert!(config_err(dino.validate()).contains("num_hidden_layers"));
    let mut da = DepthAnythingV2Config::small();
    da.neck_hidden_sizes[3] = 1 << 40;
    assert!(config_err(da.validate()).contains("neck_hidden_sizes[3]"));
    let mut da = DepthAnythingV2Config::small();
    da.reassemble_factors[0] = 1e9;
    assert!(config_err(da.validate()).contains("reassemble_factors[0]"));
}

#[test]
fn absurd_feature_net_sizes_are_config_errors_naming_the_field() {
    let mut r = RangeNetConfig::small();
    r.stem_channels = 1 << 40;
    assert!(config_err(r.validate()).contains("stem_channels"));
    let mut r = RangeNetConfig::small();
    r.stages[2].blocks = 1 << 40;
    assert!(config_err(r.validate()).contains("stages[2].blocks"));
    let mut r = RangeNetConfig::small();
    r.stages = vec![
        RangeStage {
            channels: 8,
            blocks: 1
        };
        1000
    ];
    assert!(config_err(r.validate()).contains("stages (count)"));
    let mut p = PointNetConfig::small();
    p.mlp[1] = 1 << 40;
    assert!(config_err(p.validate()).contains("mlp[1]"));
    let mut p = PointNetConfig::small();
    p.num_points = Some(1 << 40);
    assert!(config_err(p.validate()).contains("num_points"));
}

#[test]
fn recording_refuses_more_than_max_parameters_before_allocating() {
    // one tensor whose byte size overflows (`capacity overflow` when allocated), one of 2^40
    // elements (a 4 TiB allocation), and a running total just past the limit
    for shapes in [
        vec![vec![1usize << 31, 1 << 31, 4]],
        vec![vec![1 << 62, 1 << 62]],
        vec![vec![1 << 20, 1 << 20]],
        vec![vec![1 << 29], vec![1 << 29], vec![1]],
    ] {
        let last = format!("t{}", shapes.len() - 1);
        let m = config_err(record_tensor_specs(move |vb| {
            for (i, s) in shapes.iter().enumerate() {
                vb.get(s.as_slice(), &format!("t{i}"))?;
            }
            Ok(())
        }));
        assert!(
            m.contains(&MAX_PARAMETERS.to_string()) && m.contains(&format!("`{last}`")),
            "{m}"
        );
    }
    // exactly the limit passes, and what the builder gets is a broadcast zero (no storage of
    // the tensor's size)
    let specs = record_tensor_specs(|vb| {
        let t = vb.get((1usize << 15, 1usize << 15), "w")?;
        assert_eq!(t.stride(), &[0, 0]);
        assert_eq!(t.dims(), &[1 << 15, 1 << 15]);
        Ok(())
    })
    .unwrap();
    assert_eq!(specs.len(), 1);
}

#[test]
fn a_valid_config_whose_model_is_too_large_fails_the_recording() {
    // every field within its bound, but 16384-channel 3x3 convolutions: billions of weights
    let mut cfg = DenoiserConfig::tiny().unconditional();
    cfg.base_channels = 4096;
    cfg.channel_mults = vec![1, 2, 4, 4];
    cfg.pfc = None;
    cfg.validate().unwrap();
    let m = config_err(veila_nn::checkpoint::expected_tensors(&cfg));
    assert!(m.contains(&MAX_PARAMETERS.to_string()), "{m}");
}

// ------------------------------------------------------------------------------------------------
// issue 58, case 9: weights must be stored as the model declares them, and be finite

/// The tensors of a tiny unconditional denoiser, name -> shape.
fn tiny_denoiser() -> (
    DenoiserConfig,
    std::collections::BTreeMap<String, Vec<usize>>,
) {
    let cfg = DenoiserConfig::tiny().unconditional();
    let expected = veila_nn::checkpoint::expected_tensors(&cfg).unwrap();
    (cfg, expected)
}

/// Safetensors bytes of `expected`, every tensor F32 filled with 0.01, except `target`, which is
/// stored as `dtype` with the raw bytes `fill(element count)`.
fn weights_with(
    expected: &std::collections::BTreeMap<String, Vec<usize>>,
    target: &str,
    dtype: safetensors::Dtype,
    fill: &dyn Fn(usize) -> Vec<u8>,
) -> Vec<u8> {
    let data: Vec<(String, safetensors::Dtype, Vec<usize>, Vec<u8>)> = expected
        .iter()
        .map(|(name, shape)| {
            let n: usize = shape.iter().product();
            if name == target {
                (name.clone(), dtype, shape.clone(), fill(n))
            } else {
                let bytes = (0..n).flat_map(|_| 0.01f32.to_le_bytes()).collect();
                (name.clone(), safetensors::Dtype::F32, shape.clone(), bytes)
            }
        })
        .collect();
    let views: Vec<(String, safetensors::tensor::TensorView<'_>)> = data
        .iter()
        .map(|(n, d, s, b)| {
            (
                n.clone(),
                safetensors::tensor::TensorView::new(*d, s.clone(), b).unwrap(),
            )
        })
        .collect();
    safetensors::serialize(views, None).unwrap()
}

fn f32s(v: f32) -> impl Fn(usize) -> Vec<u8> {
    move |n| (0..n).flat_map(|_| v.to_le_bytes()).collect()
}

/// The denoiser's read ([`veila_nn::checkpoint::read_checked_bytes`], what bundles load with).
fn read_denoiser(
    bytes: &[u8],
    expected: &std::collections::BTreeMap<String, Vec<usize>>,
) -> veila_nn::Result<usize> {
    let path = std::path::Path::new("/bundles/x/denoiser.safetensors");
    veila_nn::checkpoint::read_checked_bytes(bytes, path, expected, &candle_core::Device::Cpu)
        .map(|t| t.len())
}

fn bad_weights(r: veila_nn::Result<usize>, tensor: &str, words: &[&str]) {
    match r {
        Err(e @ Error::BadWeights { .. }) => {
            let m = e.to_string();
            assert!(
                m.contains(&format!("tensor `{tensor}`")) && m.contains("denoiser.safetensors"),
                "{m}"
            );
            for w in words {
                assert!(m.contains(w), "`{w}` not in: {m}");
            }
        }
        other => panic!("expected bad weights, got {other:?}"),
    }
}

#[test]
fn denoiser_weights_of_another_dtype_are_refused_naming_the_tensor() {
    use safetensors::Dtype;
    let (_, expected) = tiny_denoiser();
    let target = expected.keys().nth(3).unwrap().clone();
    let ok = weights_with(&expected, &target, Dtype::F32, &f32s(0.5));
    assert_eq!(read_denoiser(&ok, &expected).unwrap(), expected.len());
    // U8 and I64 tensors were converted to f32 without a word
    let u8s = weights_with(&expected, &target, Dtype::U8, &|n| vec![200; n]);
    bad_weights(
        read_denoiser(&u8s, &expected),
        &target,
        &["stored as U8", "F32"],
    );
    let i64s = weights_with(&expected, &target, Dtype::I64, &|n| {
        (0..n).flat_map(|_| 7i64.to_le_bytes()).collect()
    });
    bad_weights(read_denoiser(&i64s, &expected), &target, &["stored as I64"]);
    // a bundle's denoiser is f32 as the workspace writes it: half precision is another dtype too
    let f16s = weights_with(&expected, &target, Dtype::F16, &|n| {
        (0..n).flat_map(|_| 0x3c00u16.to_le_bytes()).collect()
    });
    bad_weights(read_denoiser(&f16s, &expected), &target, &["stored as F16"]);
}

#[test]
fn non_finite_or_huge_weights_are_refused_naming_the_tensor() {
    use safetensors::Dtype;
    let (_, expected) = tiny_denoiser();
    let target = expected.keys().last().unwrap().clone();
    for (v, words) in [
        (f32::NAN, &["value 0 is NaN", "must be finite"][..]),
        (f32::INFINITY, &["value 0 is inf"][..]),
        (f32::NEG_INFINITY, &["value 0 is -inf"][..]),
        (3e38, &["value 0 is 3e38", "limit of 1e8"][..]),
    ] {
        let bytes = weights_with(&expected, &target, Dtype::F32, &f32s(v));
        bad_weights(read_denoiser(&bytes, &expected), &target, words);
    }
    // one bad value among good ones is found, by its index
    let one_nan = weights_with(&expected, &target, Dtype::F32, &|n| {
        (0..n)
            .flat_map(|i| if i == n - 1 { f32::NAN } else { 0.1 }.to_le_bytes())
            .collect()
    });
    let n: usize = expected[&target].iter().product();
    bad_weights(
        read_denoiser(&one_nan, &expected),
        &target,
        &[&format!("value {} is NaN", n - 1)],
    );
    // the limit itself is allowed
    let at_limit = weights_with(
        &expected,
        &target,
        Dtype::F32,
        &f32s(veila_nn::weights::MAX_ABS_WEIGHT),
    );
    read_denoiser(&at_limit, &expected).unwrap();
}

#[test]
fn encoder_files_take_any_float_precision_and_refuse_integers() {
    use safetensors::Dtype;
    let cfg = SmallCnnConfig::default();
    let build = |vb| veila_nn::encoders::small_cnn::SmallCnn::new(&cfg, vb);
    let expected = veila_nn::weights::record_tensors(|vb| build(vb).map(|_| ())).unwrap();
    let target = expected.keys().next().unwrap().clone();
    let path = std::path::Path::new("enc/semantic_encoder.safetensors");
    let load = |bytes: &[u8]| {
        veila_nn::encoders::load_checked_bytes(
            bytes,
            path,
            candle_core::DType::F32,
            &candle_core::Device::Cpu,
            |_| true,
            build,
        )
        .map(drop)
    };
    // a published checkpoint in half precision loads (converted to the model's f32)
    let bf16 = weights_with(&expected, &target, Dtype::BF16, &|n| {
        (0..n).flat_map(|_| 0x3f80u16.to_le_bytes()).collect()
    });
    load(&bf16).unwrap();
    let f16 = weights_with(&expected, &target, Dtype::F16, &|n| {
        (0..n).flat_map(|_| 0x3c00u16.to_le_bytes()).collect()
    });
    load(&f16).unwrap();
    // integers and a non-finite half are refused, naming the tensor and the file
    let half = |bits: u16| {
        move |n: usize| -> Vec<u8> { (0..n).flat_map(|_| bits.to_le_bytes()).collect() }
    };
    type Fill = Box<dyn Fn(usize) -> Vec<u8>>;
    let cases: [(Dtype, Fill, &str); 4] = [
        (Dtype::I32, Box::new(|n| vec![1; 4 * n]), "stored as I32"),
        (Dtype::BOOL, Box::new(|n| vec![1; n]), "stored as BOOL"),
        (Dtype::F16, Box::new(half(0x7e00)), "is NaN"),
        (Dtype::BF16, Box::new(half(0xff80)), "is -inf"),
    ];
    for (dtype, fill, word) in cases {
        let bytes = weights_with(&expected, &target, dtype, &fill);
        let m = load(&bytes).unwrap_err().to_string();
        assert!(
            m.contains(&format!("tensor `{target}`"))
                && m.contains("semantic_encoder.safetensors")
                && m.contains(word),
            "{m}"
        );
    }
}

#[test]
fn the_time_input_scale_is_bounded() {
    let mut cfg = DenoiserConfig::tiny();
    for bad in [
        1e300,
        f64::INFINITY,
        0.0,
        -1000.0,
        veila_nn::config::MAX_TIME_INPUT_SCALE * 1.01,
    ] {
        cfg.time.input_scale = bad;
        let m = config_err(cfg.validate());
        assert!(m.contains("time.input_scale"), "{bad}: {m}");
    }
    cfg.time.input_scale = veila_nn::config::MAX_TIME_INPUT_SCALE;
    cfg.validate().unwrap();
}

// ------------------------------------------------------------------------------------------------
// issue 58, case 8: weights files are regular files under a cap, checked before they are read

/// A FIFO at `p` (`mkfifo`), or `false` where the tool is missing.
fn make_fifo(p: &std::path::Path) -> bool {
    match std::process::Command::new("mkfifo").arg(p).status() {
        Ok(s) if s.success() => true,
        other => {
            eprintln!("skipped the FIFO case: mkfifo is unavailable ({other:?})");
            false
        }
    }
}

/// The message of a refusal (panics on success or on another error).
fn refused<T: std::fmt::Debug>(r: veila_nn::Result<T>) -> String {
    match r {
        Err(e @ Error::Refused { .. }) => e.to_string(),
        other => panic!("expected a refusal, got {other:?}"),
    }
}

#[test]
fn weights_files_are_refused_unread_unless_regular_and_under_the_cap() {
    use veila_nn::weights::{MAX_WEIGHTS_FILE_BYTES, read_weights_file};
    let dir = tempfile::tempdir().unwrap();
    // a regular file reads back whole
    let ok = dir.path().join("ok.safetensors");
    std::fs::write(&ok, b"0123456789").unwrap();
    assert_eq!(read_weights_file(&ok).unwrap(), b"0123456789");
    // a sparse file one byte over the cap: refused from its length (reading it would take
    // 4 GiB and seconds)
    let big = dir.path().join("big.safetensors");
    std::fs::File::create(&big)
        .unwrap()
        .set_len(MAX_WEIGHTS_FILE_BYTES + 1)
        .unwrap();
    let m = within_seconds({
        let big = big.clone();
        move || refused(read_weights_file(&big))
    });
    assert!(
        m.contains("big.safetensors") && m.contains("more than the cap"),
        "{m}"
    );
    // a link to /dev/zero reads forever, a FIFO blocks, a directory is none
    #[cfg(unix)]
    {
        let zero = dir.path().join("zero.safetensors");
        std::os::unix::fs::symlink("/dev/zero", &zero).unwrap();
        let m = within_seconds(move || refused(read_weights_file(&zero)));
        assert!(
            m.contains("zero.safetensors") && m.contains("regular file"),
            "{m}"
        );
        let fifo = dir.path().join("fifo.safetensors");
        if make_fifo(&fifo) {
            let m = within_seconds(move || refused(read_weights_file(&fifo)));
            assert!(m.contains("fifo.safetensors") && m.contains("FIFO"), "{m}");
        }
    }
    let m = refused(read_weights_file(dir.path()));
    assert!(m.contains("directory"), "{m}");
    // and every loader reads through it: a checkpoint whose weights or config are links to
    // /dev/zero, an encoder file over the cap
    #[cfg(unix)]
    {
        let ckpt = dir.path().join("ckpt");
        std::fs::create_dir(&ckpt).unwrap();
        std::os::unix::fs::symlink("/dev/zero", ckpt.join("config.json")).unwrap();
        let c = ckpt.clone();
        let m = within_seconds(move || {
            refused(veila_nn::checkpoint::read_checkpoint(
                &c,
                candle_core::DType::F32,
                &candle_core::Device::Cpu,
            ))
        });
        assert!(m.contains("config.json"), "{m}");
        let (cfg, _) = tiny_denoiser();
        std::fs::remove_file(ckpt.join("config.json")).unwrap();
        std::fs::write(ckpt.join("config.json"), serde_json::to_vec(&cfg).unwrap()).unwrap();
        std::os::unix::fs::symlink("/dev/zero", ckpt.join("model.safetensors")).unwrap();
        let m = within_seconds(move || {
            refused(veila_nn::checkpoint::read_checkpoint(
                &ckpt,
                candle_core::DType::F32,
                &candle_core::Device::Cpu,
            ))
        });
        assert!(m.contains("model.safetensors"), "{m}");
    }
    let cfg = SmallCnnConfig::default();
    let m = within_seconds(move || {
        refused(veila_nn::encoders::load_checked(
            &big,
            candle_core::DType::F32,
            &candle_core::Device::Cpu,
            |_| true,
            |vb| veila_nn::encoders::small_cnn::SmallCnn::new(&cfg, vb),
        ))
    });
    assert!(m.contains("big.safetensors"), "{m}");
}

#[test]
fn float_checkpoints_load_in_the_dtype_asked_with_the_bundles_checks() {
    use safetensors::Dtype;
    let (_, expected) = tiny_denoiser();
    let target = expected.keys().next().unwrap().clone();
    let path = std::path::Path::new("/runs/x/step-0000000010/model.safetensors");
    let read = |bytes: &[u8], dtype: candle_core::DType| {
        veila_nn::weights::read_checked_float_bytes(
            bytes,
            path,
            &expected,
            dtype,
            &candle_core::Device::Cpu,
        )
    };
    // f64 weights stay f64 when asked (a resumed f64 run is exact), f16 ones convert
    let f64s = weights_with(&expected, &target, Dtype::F64, &|n| {
        (0..n).flat_map(|_| 0.1f64.to_le_bytes()).collect()
    });
    let t = read(&f64s, candle_core::DType::F64).unwrap();
    assert_eq!(t[&target].dtype(), candle_core::DType::F64);
    let v = t[&target].flatten_all().unwrap().to_vec1::<f64>().unwrap();
    assert!(v.iter().all(|x| *x == 0.1), "{:?}", &v[..4]);
    let f16 = weights_with(&expected, &target, Dtype::F16, &|n| {
        (0..n).flat_map(|_| 0x3c00u16.to_le_bytes()).collect()
    });
    let t = read(&f16, candle_core::DType::F32).unwrap();
    assert_eq!(t[&target].dtype(), candle_core::DType::F32);
    // refused as a bundle's weights are: integers, NaN, too large, a missing tensor
    let cases: [(Vec<u8>, &str); 3] = [
        (
            weights_with(&expected, &target, Dtype::I64, &|n| vec![0; 8 * n]),
            "stored as I64",
        ),
        (
            weights_with(&expected, &target, Dtype::F32, &f32s(f32::NAN)),
            "must be finite",
        ),
        (
            weights_with(&expected, &target, Dtype::F32, &f32s(3e38)),
            "beyond the limit",
        ),
    ];
    for (bytes, word) in cases {
        let m = read(&bytes, candle_core::DType::F32)
            .unwrap_err()
            .to_string();
        assert!(
            m.contains(word) && m.contains(&target) && m.contains("model.safetensors"),
            "{m}"
        );
    }
    let mut fewer = expected.clone();
    fewer.insert("extra.weight".into(), vec![2]);
    let good = weights_with(&expected, &target, Dtype::F32, &f32s(0.5));
    let e = veila_nn::weights::read_checked_float_bytes(
        &good,
        path,
        &fewer,
        candle_core::DType::F32,
        &candle_core::Device::Cpu,
    )
    .unwrap_err();
    assert!(matches!(e, Error::CheckpointMismatch { .. }), "{e}");
}
