//! Integration tests of veila-diffusion (one binary, modules per area).

mod common;
mod samplers;
mod training;
