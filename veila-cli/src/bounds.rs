//! The value parsers that hold every numeric argument to the range its help states: a value
//! outside it is refused by the parser, before anything runs, with the range in the message.
//! (Seeds take any 64-bit value: the `u64` parser holds them to it.)
//!
//! Every numeric option's help says its range as "`LO` to `HI`"; a test in `main.rs` reads it
//! there and checks that the parser takes both ends and refuses the values just outside.

/// A whole number from `lo` to `hi` (both included).
pub(crate) fn int<T>(
    lo: u64,
    hi: u64,
) -> impl Fn(&str) -> Result<T, String> + Clone + Send + Sync + 'static
where
    T: TryFrom<u64> + Clone + Send + Sync + 'static,
{
    move |s: &str| {
        let range = || format!("must be a whole number between {lo} and {hi}");
        let v: u64 = s.trim().parse().map_err(|_| range())?;
        if !(lo..=hi).contains(&v) {
            return Err(range());
        }
        T::try_from(v).map_err(|_| range())
    }
}

/// A finite number from `lo` to `hi` (both included).
pub(crate) fn float(
    lo: f64,
    hi: f64,
) -> impl Fn(&str) -> Result<f64, String> + Clone + Send + Sync + 'static {
    move |s: &str| {
        let range = || format!("must be a number between {lo} and {hi}");
        let v: f64 = s.trim().parse().map_err(|_| range())?;
        if !(v.is_finite() && (lo..=hi).contains(&v)) {
            return Err(range());
        }
        Ok(v)
    }
}

/// [`float`] as an `f32` (the range is checked on the `f32` value).
pub(crate) fn float32(
    lo: f32,
    hi: f32,
) -> impl Fn(&str) -> Result<f32, String> + Clone + Send + Sync + 'static {
    move |s: &str| {
        let range = || format!("must be a number between {lo} and {hi}");
        let v: f32 = s.trim().parse().map_err(|_| range())?;
        if !(v.is_finite() && (lo..=hi).contains(&v)) {
            return Err(range());
        }
        Ok(v)
    }
}

/// Sampler steps of `generate`, `edit` and `demo`: 1 to the library's
/// [`veila_diffusion::MAX_STEPS`], the bound of a bundle's `sampler.steps` too.
pub(crate) fn steps() -> impl Fn(&str) -> Result<usize, String> + Clone + Send + Sync + 'static {
    int(1, veila_diffusion::MAX_STEPS as u64)
}

/// A classifier-free guidance scale: 0 to the library's [`veila_diffusion::MAX_GUIDANCE`], the
/// bound of a bundle's `sampler.guidance_scale` too.
pub(crate) fn guidance() -> impl Fn(&str) -> Result<f64, String> + Clone + Send + Sync + 'static {
    float(0.0, veila_diffusion::MAX_GUIDANCE)
}

/// A sampler's start level ([`veila_diffusion::SamplerConfig::start_t`]): 0.001 (below the
/// samplers' last level, the mean network's scan itself) to 1 (pure noise).
pub(crate) fn start_level() -> impl Fn(&str) -> Result<f64, String> + Clone + Send + Sync + 'static
{
    float(0.001, 1.0)
}

/// A residual weight: the library's [`veila_diffusion::app::RESIDUAL_WEIGHT`], 0 to 1.
pub(crate) fn unit() -> impl Fn(&str) -> Result<f64, String> + Clone + Send + Sync + 'static {
    let (lo, hi) = veila_diffusion::app::RESIDUAL_WEIGHT;
    float(lo, hi)
}
