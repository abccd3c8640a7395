//! The choices of options that name an entry of a library's list, built from that list: a sensor
//! preset ([`SensorPreset::ALL`]), a dataset ([`DatasetName::ALL`]), a metric
//! ([`MetricName::ALL`]). (`--sampler`'s parser is in
//! `generation.rs`.) Tests in `main.rs` check that every door offers exactly the library's list.

use clap::builder::{PossibleValue, PossibleValuesParser, TypedValueParser};
use veila_data::dataset::DatasetName;
use veila_geom::SensorPreset;
use veila_metrics::MetricName;

/// A metric's parser: the choices (with their help) are [`MetricName::ALL`].
pub(crate) fn metric_parser() -> impl TypedValueParser<Value = MetricName> {
    PossibleValuesParser::new(
        MetricName::ALL.map(|m| PossibleValue::new(m.as_str()).help(m.help())),
    )
    .try_map(|name| name.parse::<MetricName>())
}

/// A dataset's parser: the choices (with their help) are [`DatasetName::ALL`].
pub(crate) fn dataset_parser() -> impl TypedValueParser<Value = DatasetName> {
    PossibleValuesParser::new(
        DatasetName::ALL.map(|d| PossibleValue::new(d.as_str()).help(d.help())),
    )
    .try_map(|name| name.parse::<DatasetName>())
}

/// A sensor preset's parser: the choices (with their help) are [`SensorPreset::ALL`].
pub(crate) fn sensor_preset_parser() -> impl TypedValueParser<Value = SensorPreset> {
    PossibleValuesParser::new(
        SensorPreset::ALL.map(|p| PossibleValue::new(p.as_str()).help(p.help())),
    )
    .try_map(|name| name.parse::<SensorPreset>())
}

/// The help of a `--sensor` that takes a preset or a sensor file (resolved by
/// [`veila_data::spec::sensor_from_spec`]), naming the presets of [`SensorPreset::ALL`];
/// `default` says what an absent `--sensor` means.
pub(crate) fn sensor_spec_help(default: &str) -> String {
    format!(
        "Sensor: a preset ({}; `veila sensors NAME` prints one as a file) or a .toml/.json sensor \
         file. {default}",
        SensorPreset::names()
    )
}
