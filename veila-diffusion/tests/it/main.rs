//! Integration tests of veila-diffusion (one binary, modules per area).

mod common;
mod device;
mod methods;
mod samplers;
mod training;
