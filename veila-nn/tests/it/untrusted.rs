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
