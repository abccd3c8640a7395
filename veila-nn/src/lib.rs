//! The Veila denoiser on candle (being filled in): U-Net with CACM, GCMA and PFC, image encoders,
//! checkpoint IO.

pub mod encoders;
