//! Integration tests of veila-diffusion (one binary, modules per area).

mod common;
mod device;
mod samplers;
mod training;
