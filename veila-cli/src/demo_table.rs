//! The tables `veila demo` prints: the metrics of the generated scan next to each baseline's
//! (lower is better for every row; the cm-dc rows of the true scan are the floor), the ring
//! spread, and the texture figures with the true scan's beside them.

use std::collections::BTreeMap;

use veila_metrics::MetricValue;
use veila_metrics::texture::TextureSummary;

/// A baseline's column: its name and its metrics.
pub(crate) type Column<'a> = (&'a str, &'a [MetricValue]);

/// The metrics table: one column for the generated scan and one per baseline (lower is better
/// for every row; the cm-dc rows of the true scan are the floor), then the ring spread.
pub(crate) fn print_table(
    metrics: &[MetricValue],
    baselines: &[Column<'_>],
    ring_spread: &BTreeMap<&'static str, Option<f64>>,
) {
    print!(
        "{:<38} {:<10} {:<6} {:>12}",
        "metric", "protocol", "region", "generated"
    );
    for (name, _) in baselines {
        print!(" {name:>12}");
    }
    println!();
    for m in metrics {
        print!(
            "{:<38} {:<10} {:<6} {:>12.4}",
            m.name,
            m.protocol.name(),
            m.region.name(),
            m.value
        );
        for (_, theirs) in baselines {
            match theirs
                .iter()
                .find(|x| x.name == m.name && x.region == m.region)
            {
                Some(x) if !m.name.contains("true scan") => print!(" {:>12.4}", x.value),
                _ => print!(" {:>12}", "-"),
            }
        }
        println!();
    }
    let fmt = |v: Option<&Option<f64>>| match v {
        Some(Some(x)) => format!("{x:.3}"),
        _ => "n/a".to_string(),
    };
    print!(
        "{:<38} {:<10} {:<6} {:>12}",
        "ring spread (m)",
        "veila",
        "all",
        fmt(ring_spread.get("generated"))
    );
    for (name, _) in baselines {
        print!(" {:>12}", fmt(ring_spread.get(name)));
    }
    println!("   (true scan: {})", fmt(ring_spread.get("true")));
}

/// The texture rows under the metrics table: each scan's figures, the true scan's in brackets
/// (what a realistic scan matches).
pub(crate) fn print_texture(
    baselines: &[Column<'_>],
    texture: &BTreeMap<&'static str, TextureSummary>,
) {
    type Pick = fn(&TextureSummary) -> f64;
    let rows: [(&str, &str, Pick); 3] = [
        ("depth edges (% of pairs, > 100 % jump)", "upper", |t| {
            t.depth_edges_upper_pct
        }),
        ("smooth pairs (% of pairs, < 0.03 %)", "lower", |t| {
            t.smooth_lower_pct
        }),
        ("texture distance to true (decades)", "all", |t| {
            t.w1_along_decades
        }),
    ];
    for (name, band, pick) in rows {
        let cell = |k: &str| {
            texture
                .get(k)
                .map(pick)
                .map_or("n/a".into(), |v| format!("{v:.4}"))
        };
        print!(
            "{name:<38} {:<10} {band:<6} {:>12}",
            "veila",
            cell("generated")
        );
        for (name, _) in baselines {
            print!(" {:>12}", cell(name));
        }
        println!("   (true scan: {})", cell("true"));
    }
}
