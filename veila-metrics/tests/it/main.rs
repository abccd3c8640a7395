//! Integration tests of veila-metrics (one test binary, a module per area).

mod bvh;
mod crossmodal;
mod golden;
mod hard_cases;
mod hostile_bounds;
mod peer_protocols;
mod segmentation;
mod texture;
