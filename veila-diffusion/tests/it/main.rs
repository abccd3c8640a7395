//! Integration tests of veila-diffusion (one binary, modules per area).
mod bundle_pipeline;
mod common;
mod dataset_gen;
mod device;
mod encoder_augment;
mod methods;
mod prior;
mod samplers;
mod scan_pipeline;
mod segment;
mod training;
