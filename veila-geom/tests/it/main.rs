//! Integration tests of veila-geom (one test binary, a module per area).

mod camera_epipolar;
mod common;
mod hard_cases;
mod projection_reference;
mod roundtrip;
