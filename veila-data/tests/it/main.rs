//! Integration tests of veila-data (one test binary, a module per area; the feature-gated areas
//! build only with their feature).

#[cfg(feature = "augment")]
mod augment;
mod convert;
#[cfg(feature = "sim")]
mod learning_map;
mod real_data;
#[cfg(feature = "sim")]
mod sim;
mod untrusted;
mod untrusted_paths;
#[cfg(feature = "weather")]
mod weather_identity;
#[cfg(feature = "weather")]
mod weather_numerics;
#[cfg(feature = "weather")]
mod weather_physics;
#[cfg(feature = "weather")]
mod weather_real;
