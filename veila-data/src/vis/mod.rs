//! Visualisation (feature `vis`): pictures of scans and numbers, never read back by anything.
//!
//! - [`render`]: previews of range, intensity and label images, a bird's-eye view, and LiDAR points
//!   drawn on the camera image coloured by depth.
//! - [`plot`]: line / scatter plots with log axes, error bars and legends, and grouped bar charts,
//!   drawn with `plotters` onto PNG in an embedded font (no system fonts).
//! - [`density`]: the building blocks of the HTML reports: BEV point-density grids and their
//!   signed-difference image, a diverging colour map, and normalised histograms.
//! - [`html`]: self-contained HTML report pages (inline CSS, images as `data:` URLs, escaped text).

pub mod density;
pub mod html;
pub mod plot;
pub mod render;
