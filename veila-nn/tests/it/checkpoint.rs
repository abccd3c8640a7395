//! Checkpoint round trip and the missing / unexpected / mis-shaped report.

use std::collections::HashMap;

use crate::common::*;
use candle_core::{DType, Device, Tensor};
use veila_nn::checkpoint::{
    CONFIG_FILE, WEIGHTS_FILE, expected_tensors, load_denoiser, load_into_varmap, parameter_count,
    save_checkpoint, save_varmap,
};
use veila_nn::{Error, seeded_var_builder};

fn tensors_of(vm: &candle_nn::VarMap) -> HashMap<String, Tensor> {
    vm.data()
        .lock()
        .unwrap()
        .iter()
        .map(|(k, v)| (k.clone(), v.as_tensor().clone()))
        .collect()
}

#[test]
fn round_trip_gives_identical_outputs() {
    let cfg = small_config().unconditional();
    let (vm, net) = varmap_model(&cfg, 21);
    let dir = tempfile::tempdir().unwrap();
    let ck = dir.path().join("ck");
    save_varmap(&ck, &cfg, &vm).unwrap();
    assert!(ck.join(CONFIG_FILE).exists() && ck.join(WEIGHTS_FILE).exists());
    // no temporary files left behind
    assert_eq!(std::fs::read_dir(&ck).unwrap().count(), 2);
    let loaded = load_denoiser(&ck, DType::F32, &Device::Cpu).unwrap();
    assert_eq!(loaded.config(), &cfg);
    let x = rand_tensor(&mut rng(1), &[1, 3, 16, 128]);
    let t = Tensor::new(&[0.25f32], &Device::Cpu).unwrap();
    let a = net.forward(&x, &t, None).unwrap();
    let b = loaded.forward(&x, &t, None).unwrap();
    assert_eq!(max_abs_diff(&a, &b), 0.0);

    // resume into a differently-seeded trainable VarMap
    let mut vm2 = candle_nn::VarMap::new();
    let net2 =
        veila_nn::Denoiser::new(&cfg, seeded_var_builder(&vm2, 99, DType::F32, &Device::Cpu))
            .unwrap();
    assert!(max_abs_diff(&net2.forward(&x, &t, None).unwrap(), &a) > 1e-4);
    load_into_varmap(&ck, &cfg, &mut vm2, &Device::Cpu).unwrap();
    assert_eq!(max_abs_diff(&net2.forward(&x, &t, None).unwrap(), &a), 0.0);
    // the number of tensors and parameters is what the model asks for
    let expected = expected_tensors(&cfg).unwrap();
    assert_eq!(expected.len(), tensors_of(&vm).len());
    let n: usize = tensors_of(&vm).values().map(|t| t.elem_count()).sum();
    assert_eq!(parameter_count(&cfg).unwrap(), n);
}

#[test]
fn mismatched_checkpoint_reports_every_tensor_by_name() {
    let cfg = small_config().unconditional();
    let (vm, _) = varmap_model(&cfg, 22);
    let mut tensors = tensors_of(&vm);
    let dir = tempfile::tempdir().unwrap();
    let ck = dir.path().join("ck");
    save_checkpoint(&ck, &cfg, &tensors).unwrap();

    // tamper with the weights file: one missing, one unexpected, one mis-shaped
    tensors.remove("mid.pfc.proj.bias");
    tensors.insert(
        "extra.weight".into(),
        Tensor::zeros(3, DType::F32, &Device::Cpu).unwrap(),
    );
    tensors.insert(
        "in_conv.bias".into(),
        Tensor::zeros(7, DType::F32, &Device::Cpu).unwrap(),
    );
    candle_core::safetensors::save(&tensors, ck.join(WEIGHTS_FILE)).unwrap();

    match load_denoiser(&ck, DType::F32, &Device::Cpu) {
        Err(Error::CheckpointMismatch { path, report }) => {
            assert_eq!(path, ck.join(WEIGHTS_FILE));
            assert_eq!(report.missing, vec!["mid.pfc.proj.bias".to_string()]);
            assert_eq!(report.unexpected, vec!["extra.weight".to_string()]);
            assert_eq!(
                report.mis_shaped,
                vec![("in_conv.bias".to_string(), vec![16], vec![7])]
            );
            let msg = Error::CheckpointMismatch { path, report }.to_string();
            assert!(
                msg.contains("mid.pfc.proj.bias")
                    && msg.contains("extra.weight")
                    && msg.contains("in_conv.bias")
            );
            assert!(msg.contains("model.safetensors"), "{msg}");
        }
        Err(other) => panic!("wrong error: {other}"),
        Ok(_) => panic!("a tampered checkpoint loaded"),
    }

    // saving refuses tensors that do not fit the config, and writes nothing
    let other = dir.path().join("other");
    assert!(matches!(
        save_checkpoint(&other, &cfg, &tensors),
        Err(Error::CheckpointMismatch { .. })
    ));
    assert!(!other.exists());
}

#[test]
fn corrupt_files_are_errors_naming_the_file() {
    let cfg = small_config().unconditional();
    let (vm, _) = varmap_model(&cfg, 23);
    let dir = tempfile::tempdir().unwrap();
    let ck = dir.path().join("ck");
    save_varmap(&ck, &cfg, &vm).unwrap();
    std::fs::write(ck.join(WEIGHTS_FILE), b"not a safetensors file").unwrap();
    let err = load_denoiser(&ck, DType::F32, &Device::Cpu).unwrap_err();
    assert!(
        matches!(err, Error::SafeTensors { .. }) && err.to_string().contains(WEIGHTS_FILE),
        "{err}"
    );
    std::fs::write(ck.join(CONFIG_FILE), b"{\"sensor\": 3}").unwrap();
    let err = load_denoiser(&ck, DType::F32, &Device::Cpu).unwrap_err();
    assert!(
        matches!(err, Error::Json { .. }) && err.to_string().contains(CONFIG_FILE),
        "{err}"
    );
    let err = load_denoiser(&dir.path().join("missing"), DType::F32, &Device::Cpu).unwrap_err();
    assert!(matches!(err, Error::Io { .. }), "{err}");
}
