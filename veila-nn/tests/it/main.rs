//! Integration tests of veila-nn (one test binary, a module per area).

mod bundled_model;
mod cacm;
mod checkpoint;
mod common;
mod cuda_emu;
mod denoiser;
mod encoder_kinds;
mod encoder_parity;
mod encoders;
mod feature_nets;
mod fused;
mod gather;
mod gcma;
mod mixed_precision;
mod ops;
mod preprocess;
mod recompute;
mod segmenter;
mod untrusted;
mod with_encoders;
