//! Self-contained HTML reports: one file with inline CSS, images embedded as
//! `data:image/png;base64,...` and no reference to anything outside it (a Content-Security-Policy in
//! the page enforces that), so a report can be mailed, archived or attached to a CI run as is.
//!
//! All text is HTML-escaped. A small inline script checks on load that every image decoded and
//! records the result on `<body>` (`data-images-ok="N/N"`, `data-report-ready="1"`), which lets a
//! headless browser verify a page.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use anyhow::{Context, Result};
use veila_data::image::RgbImage;
use veila_data::vis::density::{BevGrid, histogram};
use veila_data::vis::plot::{Plot, Series, SeriesStyle};
use veila_data::vis::render::{BevOptions, render_bev};
use veila_metrics::{MetricReport, Region};

/// One table cell.
#[derive(Debug, Clone, PartialEq)]
pub(crate) enum Cell {
    /// Text, left-aligned.
    Text(String),
    /// A number (already formatted), right-aligned, with an optional smaller second line.
    Num { value: String, note: Option<String> },
    /// Nothing (a metric not computed for a region).
    Empty,
}

#[derive(Debug, Clone)]
enum Block {
    Section(String),
    Paragraph(String),
    Table {
        caption: Option<String>,
        header: Vec<String>,
        rows: Vec<Vec<Cell>>,
    },
    KeyValue(Vec<(String, String)>),
    Figures(Vec<Figure>),
}

#[derive(Debug, Clone)]
struct Figure {
    caption: String,
    png: Vec<u8>,
}

/// A self-contained HTML report under construction.
#[derive(Debug, Clone)]
pub(crate) struct HtmlReport {
    title: String,
    blocks: Vec<Block>,
}

impl HtmlReport {
    /// An empty report with a page title (also the `<h1>`).
    pub(crate) fn new(title: impl Into<String>) -> Self {
        HtmlReport {
            title: title.into(),
            blocks: Vec::new(),
        }
    }

    /// Start a section with a heading.
    pub(crate) fn section(&mut self, heading: impl Into<String>) -> &mut Self {
        self.blocks.push(Block::Section(heading.into()));
        self
    }

    /// A paragraph of plain text.
    pub(crate) fn paragraph(&mut self, text: impl Into<String>) -> &mut Self {
        self.blocks.push(Block::Paragraph(text.into()));
        self
    }

    /// A two-column table of names and values (metadata).
    pub(crate) fn key_values(&mut self, rows: Vec<(String, String)>) -> &mut Self {
        self.blocks.push(Block::KeyValue(rows));
        self
    }

    /// A table with a header row.
    pub(crate) fn table(
        &mut self,
        caption: Option<String>,
        header: Vec<String>,
        rows: Vec<Vec<Cell>>,
    ) -> &mut Self {
        self.blocks.push(Block::Table {
            caption,
            header,
            rows,
        });
        self
    }

    /// One image (PNG bytes) with a caption.
    pub(crate) fn image(&mut self, caption: impl Into<String>, png: Vec<u8>) -> &mut Self {
        self.figures(vec![(caption.into(), png)])
    }

    /// Images shown side by side (wrapping on narrow screens), each with its caption.
    pub(crate) fn figures(&mut self, figures: Vec<(String, Vec<u8>)>) -> &mut Self {
        self.blocks.push(Block::Figures(
            figures
                .into_iter()
                .map(|(caption, png)| Figure { caption, png })
                .collect(),
        ));
        self
    }

    /// Number of images in the report.
    pub(crate) fn image_count(&self) -> usize {
        self.blocks
            .iter()
            .map(|b| match b {
                Block::Figures(f) => f.len(),
                _ => 0,
            })
            .sum()
    }

    /// The page.
    pub(crate) fn to_html(&self) -> String {
        let mut h = String::with_capacity(
            64 * 1024
                + self
                    .blocks
                    .iter()
                    .map(|b| match b {
                        Block::Figures(f) => f.iter().map(|f| f.png.len() * 4 / 3 + 256).sum(),
                        _ => 0,
                    })
                    .sum::<usize>(),
        );
        let title = escape(&self.title);
        h.push_str("<!DOCTYPE html>\n<html lang=\"en\">\n<head>\n<meta charset=\"utf-8\">\n");
        h.push_str(
            "<meta name=\"viewport\" content=\"width=device-width, initial-scale=1\">\n\
             <meta http-equiv=\"Content-Security-Policy\" content=\"default-src 'none'; \
             img-src data:; style-src 'unsafe-inline'; script-src 'unsafe-inline'\">\n",
        );
        let _ = writeln!(h, "<title>{title}</title>");
        h.push_str("<style>\n");
        h.push_str(CSS);
        h.push_str("</style>\n</head>\n<body data-report-ready=\"0\">\n<main>\n");
        let _ = writeln!(h, "<h1>{title}</h1>");
        for b in &self.blocks {
            match b {
                Block::Section(t) => {
                    let _ = writeln!(h, "<h2>{}</h2>", escape(t));
                }
                Block::Paragraph(t) => {
                    let _ = writeln!(h, "<p>{}</p>", escape(t));
                }
                Block::KeyValue(rows) => {
                    h.push_str("<table class=\"meta\">\n<tbody>\n");
                    for (k, v) in rows {
                        let _ = writeln!(
                            h,
                            "<tr><th scope=\"row\">{}</th><td>{}</td></tr>",
                            escape(k),
                            escape(v)
                        );
                    }
                    h.push_str("</tbody>\n</table>\n");
                }
                Block::Table {
                    caption,
                    header,
                    rows,
                } => {
                    h.push_str("<table class=\"data\">\n");
                    if let Some(c) = caption {
                        let _ = writeln!(h, "<caption>{}</caption>", escape(c));
                    }
                    h.push_str("<thead><tr>");
                    for c in header {
                        let _ = write!(h, "<th scope=\"col\">{}</th>", escape(c));
                    }
                    h.push_str("</tr></thead>\n<tbody>\n");
                    for row in rows {
                        h.push_str("<tr>");
                        for c in row {
                            match c {
                                Cell::Text(t) => {
                                    let _ = write!(h, "<td>{}</td>", escape(t));
                                }
                                Cell::Num { value, note } => {
                                    let _ = write!(h, "<td class=\"num\">{}", escape(value));
                                    if let Some(n) = note {
                                        let _ =
                                            write!(h, "<span class=\"note\">{}</span>", escape(n));
                                    }
                                    h.push_str("</td>");
                                }
                                Cell::Empty => h.push_str("<td class=\"num empty\">&ndash;</td>"),
                            }
                        }
                        h.push_str("</tr>\n");
                    }
                    h.push_str("</tbody>\n</table>\n");
                }
                Block::Figures(figs) => {
                    h.push_str("<div class=\"figures\">\n");
                    for f in figs {
                        let cap = escape(&f.caption);
                        let _ = writeln!(
                            h,
                            "<figure><img alt=\"{cap}\" src=\"data:image/png;base64,{}\">\
                             <figcaption>{cap}</figcaption></figure>",
                            base64_encode(&f.png)
                        );
                    }
                    h.push_str("</div>\n");
                }
            }
        }
        let _ = writeln!(
            h,
            "</main>\n<footer>Written by veila {} &middot; self-contained: no external resources</footer>",
            escape(env!("CARGO_PKG_VERSION"))
        );
        h.push_str(SCRIPT);
        h.push_str("</body>\n</html>\n");
        h
    }
}

const CSS: &str = "\
:root { color-scheme: light; --fg: #1d1d1f; --muted: #5f6368; --line: #d9dce1; --stripe: #f6f7f9; }
* { box-sizing: border-box; }
body { margin: 0; background: #fff; color: var(--fg);
  font: 15px/1.5 system-ui, -apple-system, 'Segoe UI', Roboto, 'Helvetica Neue', Arial, sans-serif; }
main { max-width: 1120px; margin: 0 auto; padding: 28px 24px 8px; }
h1 { font-size: 26px; margin: 0 0 16px; letter-spacing: -0.01em; }
h2 { font-size: 19px; margin: 32px 0 10px; padding-bottom: 4px; border-bottom: 1px solid var(--line); }
p { max-width: 78ch; }
table { border-collapse: collapse; margin: 8px 0 16px; }
th, td { padding: 5px 12px; border-bottom: 1px solid var(--line); text-align: left; vertical-align: top; }
table.meta th { color: var(--muted); font-weight: 500; white-space: nowrap; }
table.meta td { font-family: ui-monospace, SFMono-Regular, Menlo, Consolas, monospace; font-size: 13px;
  word-break: break-all; }
table.data thead th { background: var(--stripe); border-bottom: 2px solid var(--line); }
table.data tbody tr:nth-child(even) { background: var(--stripe); }
caption { caption-side: top; text-align: left; color: var(--muted); padding: 0 0 6px; }
td.num { text-align: right; font-variant-numeric: tabular-nums;
  font-family: ui-monospace, SFMono-Regular, Menlo, Consolas, monospace; font-size: 13.5px; }
td.empty { color: var(--muted); }
.note { display: block; color: var(--muted); font-size: 12px; }
.figures { display: flex; flex-wrap: wrap; gap: 18px; align-items: flex-start; }
figure { margin: 0; flex: 1 1 420px; max-width: 720px; }
figure img { display: block; max-width: 100%; height: auto; border: 1px solid var(--line); }
figcaption { color: var(--muted); font-size: 13px; margin-top: 6px; max-width: 60ch; }
footer { max-width: 1120px; margin: 24px auto; padding: 0 24px; color: var(--muted); font-size: 12px; }
";

/// Marks the page once every image has (or has not) decoded, for headless-browser checks.
const SCRIPT: &str = "<script>
window.addEventListener('load', function () {
  var imgs = Array.prototype.slice.call(document.images);
  var ok = imgs.filter(function (img) { return img.complete && img.naturalWidth > 0; }).length;
  document.body.dataset.imagesOk = ok + '/' + imgs.length;
  document.body.dataset.reportReady = '1';
});
</script>
";

/// HTML-escape text for element content and attribute values.
pub(crate) fn escape(text: &str) -> String {
    let mut out = String::with_capacity(text.len());
    for c in text.chars() {
        match c {
            '&' => out.push_str("&amp;"),
            '<' => out.push_str("&lt;"),
            '>' => out.push_str("&gt;"),
            '"' => out.push_str("&quot;"),
            '\'' => out.push_str("&#39;"),
            _ => out.push(c),
        }
    }
    out
}

/// Standard base64 (RFC 4648, with padding), for `data:` URLs.
pub(crate) fn base64_encode(bytes: &[u8]) -> String {
    use base64::Engine as _;
    base64::engine::general_purpose::STANDARD.encode(bytes)
}

/// A metric value with sensible precision: four significant digits, scientific notation outside
/// 1e-3 ..= 1e5.
pub(crate) fn format_value(v: f64) -> String {
    if !v.is_finite() {
        return format!("{v}");
    }
    if v == 0.0 {
        return "0".into();
    }
    let a = v.abs();
    if (1e-3..1e5).contains(&a) {
        let decimals = (3 - a.log10().floor() as i32).clamp(0, 6) as usize;
        format!("{v:.decimals$}")
    } else {
        format!("{v:.3e}")
    }
}

/// The metric table of a report: one row per (metric, protocol), one column per region (in the
/// order all, front, rear, of those present). Values raw; where papers print a scaled value, it is
/// shown underneath.
pub(crate) fn metric_table(report: &MetricReport) -> (Vec<String>, Vec<Vec<Cell>>) {
    let regions: Vec<Region> = [Region::All, Region::Front, Region::Rear]
        .into_iter()
        .filter(|r| report.metrics.iter().any(|m| m.region == *r))
        .collect();
    let mut keys: Vec<(String, veila_metrics::Protocol)> = Vec::new();
    for m in &report.metrics {
        if !keys.iter().any(|(n, p)| *n == m.name && *p == m.protocol) {
            keys.push((m.name.clone(), m.protocol));
        }
    }
    let mut header = vec!["metric".to_string(), "protocol".to_string()];
    header.extend(regions.iter().map(|r| r.name().to_string()));
    let rows = keys
        .iter()
        .map(|(name, protocol)| {
            let mut row = vec![Cell::Text(name.clone()), Cell::Text(protocol.name().into())];
            for r in &regions {
                let m = report
                    .metrics
                    .iter()
                    .find(|m| m.name == *name && m.protocol == *protocol && m.region == *r);
                row.push(match m {
                    Some(m) => Cell::Num {
                        value: format_value(m.value),
                        note: m
                            .paper_scale
                            .map(|s| format!("×{s:.0e}: {}", format_value(m.value * s))),
                    },
                    None => Cell::Empty,
                });
            }
            row
        })
        .collect();
    (header, rows)
}

/// The command line, with arguments quoted where a shell would need it.
pub(crate) fn command_line() -> String {
    std::env::args()
        .map(|a| {
            let plain = !a.is_empty()
                && a.chars()
                    .all(|c| c.is_ascii_alphanumeric() || "-_./=:,+@%".contains(c));
            if plain {
                a
            } else {
                format!("'{}'", a.replace('\'', "'\\''"))
            }
        })
        .collect::<Vec<_>>()
        .join(" ")
}

/// Fail early (before an expensive evaluation) when a report could not be written.
pub(crate) fn check_output_dir(path: &Path) -> Result<()> {
    let dir = match path.parent() {
        Some(p) if !p.as_os_str().is_empty() => p,
        _ => Path::new("."),
    };
    if !dir.is_dir() {
        anyhow::bail!(
            "{}: the report's folder {} does not exist",
            path.display(),
            dir.display()
        );
    }
    Ok(())
}

// ------------------------------------------------------------------------------------------------
// the report of `veila eval`

/// BEV preview options of the report (stated in the captions).
pub(crate) const PREVIEW_BEV: BevOptions = BevOptions {
    half_extent_m: 50.0,
    resolution_m: 0.2,
    z_min_m: -2.5,
    z_max_m: 1.5,
};

/// At most this many scans per set feed the distribution figures (evenly spaced over the set).
pub(crate) const FIGURE_SAMPLE: usize = 64;

/// Cell size (m) of the BEV density-difference image and its half extent.
const DIFF_CELL_M: f64 = 0.5;
const DIFF_HALF_EXTENT_M: f64 = 50.0;
const DIFF_GRID: BevGrid = BevGrid {
    half_extent_m: DIFF_HALF_EXTENT_M,
    cell_m: DIFF_CELL_M,
};

/// Inputs of the `veila eval` report.
pub(crate) struct EvalReportInputs<'a> {
    pub generated_dir: &'a Path,
    pub reference_dir: &'a Path,
    pub generated: &'a [PathBuf],
    pub reference: &'a [PathBuf],
    pub metrics: &'a MetricReport,
    pub date: String,
    pub command: String,
}

/// Evenly spaced sample of at most `n` items, the first always included.
fn sample<T>(items: &[T], n: usize) -> Vec<&T> {
    if items.len() <= n {
        return items.iter().collect();
    }
    (0..n).map(|i| &items[i * items.len() / n]).collect()
}

fn read_cloud(path: &Path) -> Result<veila_data::PointCloud> {
    Ok(veila_data::scan::read_points(path)
        .with_context(|| format!("reading {} for the report", path.display()))?
        .cloud)
}

/// Build the report of a `veila eval` run.
pub(crate) fn eval_report(inp: &EvalReportInputs<'_>) -> Result<HtmlReport> {
    let mut rep = HtmlReport::new("veila eval report");
    let n_scans =
        |dir: &Path, files: &[PathBuf]| format!("{} ({} scans)", dir.display(), files.len());
    let mut metric_names: Vec<String> = Vec::new();
    for m in &inp.metrics.metrics {
        let label = format!("{} ({})", m.name, m.protocol.name());
        if !metric_names.contains(&label) {
            metric_names.push(label);
        }
    }
    rep.key_values(vec![
        ("command".into(), inp.command.clone()),
        (
            "generated".into(),
            n_scans(inp.generated_dir, inp.generated),
        ),
        (
            "reference".into(),
            n_scans(inp.reference_dir, inp.reference),
        ),
        ("metrics".into(), metric_names.join(", ")),
        ("date".into(), inp.date.clone()),
        (
            "version".into(),
            format!(
                "veila {} ({} build)",
                env!("CARGO_PKG_VERSION"),
                if cfg!(debug_assertions) {
                    "debug"
                } else {
                    "release"
                }
            ),
        ),
    ]);

    rep.section("Metrics");
    let (header, rows) = metric_table(inp.metrics);
    rep.table(
        Some(
            "Lower is better. Raw values; where papers print a scaled value (MMD x 1e4), it is shown \
             under the raw one. Regions: all = whole panorama, front = x > 0, rear = x <= 0."
                .into(),
        ),
        header,
        rows,
    );
    rep.paragraph(
        "Protocols: r2dm = BEV histograms of R2DM / LiDARGen (JSD; MMD with a Gaussian kernel, \
         Frobenius distance); lidargen = spectral-norm MMD; lidm = minimum matching distance over \
         0.5 m BEV occupancy (LiDAR-Diffusion); pytorch3d = Chamfer distance with squared distances, \
         means summed; frechet = Fréchet distance of feature statistics.",
    );

    // previews of the first scans
    rep.section("Bird's-eye views");
    let (g0, r0) = (&inp.generated[0], &inp.reference[0]);
    let (gc, rc) = (read_cloud(g0)?, read_cloud(r0)?);
    let name = |p: &Path| {
        p.file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default()
    };
    let bev_caption = |what: &str, p: &Path| {
        format!(
            "{what} scan {}: bird's-eye view, ±{} m, {} m per pixel, forward (+x) up, coloured by \
             height ({} m dark to {} m bright)",
            name(p),
            PREVIEW_BEV.half_extent_m,
            PREVIEW_BEV.resolution_m,
            PREVIEW_BEV.z_min_m,
            PREVIEW_BEV.z_max_m
        )
    };
    let png = |img: &RgbImage| veila_data::image_io::encode_png(img).context("encoding a PNG");
    rep.figures(vec![
        (
            bev_caption("First generated", g0),
            png(&render_bev(&gc, &PREVIEW_BEV)?)?,
        ),
        (
            bev_caption("First reference", r0),
            png(&render_bev(&rc, &PREVIEW_BEV)?)?,
        ),
    ]);

    // distributions over a sample of each set
    let gen_sample = sample(inp.generated, FIGURE_SAMPLE);
    let ref_sample = sample(inp.reference, FIGURE_SAMPLE);
    let load = |files: &[&PathBuf]| -> Result<Vec<veila_data::PointCloud>> {
        files.iter().map(|f| read_cloud(f)).collect()
    };
    let (gen_clouds, ref_clouds) = (load(&gen_sample)?, load(&ref_sample)?);
    let sample_note = |k: usize, n: usize| {
        if k == n {
            format!("{n} scan{}", if n == 1 { "" } else { "s" })
        } else {
            format!("{k} of {n} scans, evenly spaced")
        }
    };
    let (gs, rs) = (
        sample_note(gen_sample.len(), inp.generated.len()),
        sample_note(ref_sample.len(), inp.reference.len()),
    );
    let (gd, rd) = (
        DIFF_GRID.density(&gen_clouds),
        DIFF_GRID.density(&ref_clouds),
    );
    let (diff, max) = DIFF_GRID.difference_image(&gd, &rd);
    rep.image(
        format!(
            "BEV point density, generated minus reference ({gs} / {rs}; {DIFF_CELL_M} m cells, \
             ±{DIFF_HALF_EXTENT_M} m, each set normalised to sum 1). Red: the generated scans put \
             more points there, blue: fewer; signed square-root colour scale up to ±{max:.2e}."
        ),
        png(&diff)?,
    );

    rep.section("Distributions");
    let ranges = |clouds: &[veila_data::PointCloud]| -> Vec<f64> {
        clouds
            .iter()
            .flat_map(|c| c.xyz.iter().map(|p| p.length() as f64))
            .collect()
    };
    let heights = |clouds: &[veila_data::PointCloud]| -> Vec<f64> {
        clouds
            .iter()
            .flat_map(|c| c.xyz.iter().map(|p| p.z as f64))
            .collect()
    };
    let dist_plot = |title: &str, x_label: &str, g: Vec<(f64, f64)>, r: Vec<(f64, f64)>| Plot {
        title: title.into(),
        x_label: x_label.into(),
        y_label: "density".into(),
        series: vec![
            Series::new(format!("generated ({gs})"), g, SeriesStyle::Line),
            Series::new(format!("reference ({rs})"), r, SeriesStyle::Line),
        ],
        ..Plot::default()
    };
    let range_plot = dist_plot(
        "Point range",
        "range (m)",
        histogram(ranges(&gen_clouds).into_iter(), 0.0, 100.0, 100),
        histogram(ranges(&ref_clouds).into_iter(), 0.0, 100.0, 100),
    );
    let height_plot = dist_plot(
        "Point height",
        "z (m)",
        histogram(heights(&gen_clouds).into_iter(), -4.0, 4.0, 80),
        histogram(heights(&ref_clouds).into_iter(), -4.0, 4.0, 80),
    );
    rep.figures(vec![
        (
            "Distribution of point ranges (1 m bins, 0-100 m).".into(),
            range_plot.to_png(720, 450).context("plotting ranges")?,
        ),
        (
            "Distribution of point heights in the LiDAR frame (0.1 m bins, -4 to 4 m).".into(),
            height_plot.to_png(720, 450).context("plotting heights")?,
        ),
    ]);
    Ok(rep)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// An independent decoder: a lookup by search in the alphabet string, bit accumulation.
    fn decode(s: &str) -> Vec<u8> {
        let alphabet = "ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/";
        let mut out = Vec::new();
        let (mut acc, mut bits) = (0u32, 0);
        for c in s.chars().filter(|c| *c != '=') {
            acc = acc << 6 | alphabet.find(c).unwrap() as u32;
            bits += 6;
            if bits >= 8 {
                bits -= 8;
                out.push((acc >> bits & 0xff) as u8);
            }
        }
        out
    }

    #[test]
    fn base64_rfc4648_vectors_and_round_trip() {
        for (plain, enc) in [
            ("", ""),
            ("f", "Zg=="),
            ("fo", "Zm8="),
            ("foo", "Zm9v"),
            ("foob", "Zm9vYg=="),
            ("fooba", "Zm9vYmE="),
            ("foobar", "Zm9vYmFy"),
        ] {
            assert_eq!(base64_encode(plain.as_bytes()), enc);
        }
        let mut x = 0x9e37_79b9u32;
        for len in 0..300usize {
            let bytes: Vec<u8> = (0..len)
                .map(|_| {
                    x ^= x << 13;
                    x ^= x >> 17;
                    x ^= x << 5;
                    x as u8
                })
                .collect();
            let e = base64_encode(&bytes);
            assert_eq!(e.len(), len.div_ceil(3) * 4);
            assert_eq!(decode(&e), bytes, "length {len}");
        }
    }

    #[test]
    fn escaping_and_formatting() {
        assert_eq!(
            escape("<script>alert('x') & \"y\"</script>"),
            "&lt;script&gt;alert(&#39;x&#39;) &amp; &quot;y&quot;&lt;/script&gt;"
        );
        assert_eq!(format_value(0.0), "0");
        assert_eq!(format_value(0.081234), "0.08123");
        assert_eq!(format_value(12.3456), "12.35");
        assert_eq!(format_value(-1234.56), "-1235");
        assert_eq!(format_value(3.2e-5), "3.200e-5");
        assert_eq!(format_value(2.5e7), "2.500e7");
        assert_eq!(format_value(f64::NAN), "NaN");
        assert_eq!(format_value(f64::INFINITY), "inf");
    }

    #[test]
    fn page_structure() {
        let mut r = HtmlReport::new("T <1>");
        r.section("S & more")
            .paragraph("p")
            .key_values(vec![("k".into(), "v".into())])
            .table(
                None,
                vec!["a".into(), "b".into()],
                vec![vec![
                    Cell::Text("x".into()),
                    Cell::Num {
                        value: "1.0".into(),
                        note: Some("n".into()),
                    },
                ]],
            )
            .image("one", vec![1, 2, 3])
            .figures(vec![("two".into(), vec![4]), ("three".into(), vec![5])]);
        assert_eq!(r.image_count(), 3);
        let h = r.to_html();
        assert!(h.contains("<title>T &lt;1&gt;</title>") && h.contains("<h2>S &amp; more</h2>"));
        assert_eq!(h.matches("<img ").count(), 3);
        assert_eq!(h.matches("<script>").count(), 1);
        assert!(h.contains("src=\"data:image/png;base64,AQID\""));
        assert!(!h.contains("http://") && !h.contains("https://"));
    }
}
