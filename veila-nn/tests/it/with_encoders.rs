//! End to end with the project's own image encoders: two small CNNs (E_s, E_d) feed CACM and GCMA.

use crate::common::*;
use candle_core::{DType, Device, Tensor};
use candle_nn::{VarBuilder, VarMap};
use veila_nn::encoders::small_cnn::{SmallCnn, SmallCnnConfig};
use veila_nn::encoders::{Frozen, ImageEncoder};
use veila_nn::{ConditionInput, GcmaGeometry};

#[test]
fn small_cnn_encoders_condition_the_denoiser() {
    let dev = Device::Cpu;
    let enc_cfg = SmallCnnConfig::default();
    let e_s = Frozen::new(
        SmallCnn::new(
            &enc_cfg,
            VarBuilder::from_varmap(&VarMap::new(), DType::F32, &dev),
        )
        .unwrap(),
    );
    let e_d = Frozen::new(
        SmallCnn::new(
            &enc_cfg,
            VarBuilder::from_varmap(&VarMap::new(), DType::F32, &dev),
        )
        .unwrap(),
    );
    let mut cfg = small_config();
    let (h, w) = (IMG_H as usize, IMG_W as usize);
    cfg.conditioning
        .as_mut()
        .unwrap()
        .set_encoders(Some(&e_s), Some(&e_d), h, w)
        .unwrap();
    cfg.validate().unwrap();
    assert_eq!(
        cfg.conditioning.as_ref().unwrap().semantic_channels,
        e_s.channels().to_vec()
    );
    let (_, net) = varmap_model(&cfg, 3);
    let geom = GcmaGeometry::new(&cfg, &[kitti_camera()], &epipolar(4), &dev).unwrap();
    let image = rand_tensor(&mut rng(4), &[2, 3, h, w]);
    let input = ConditionInput {
        semantic: Some(e_s.forward(&image).unwrap()),
        depth: Some(e_d.forward(&image).unwrap()),
        keep: None,
    };
    let prepared = net.prepare_condition(&input, Some(&geom)).unwrap();
    let x = rand_tensor(&mut rng(5), &[2, 3, 16, 128]);
    let t = Tensor::new(&[0.3f32, 0.8], &dev).unwrap();
    let y = net.forward(&x, &t, Some(&prepared)).unwrap();
    assert_eq!(y.dims(), &[2, 3, 16, 128]);
    assert!(all_finite(&y));
}
