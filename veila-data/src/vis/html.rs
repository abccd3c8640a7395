//! Self-contained HTML reports: one file with inline CSS, images embedded as
//! `data:image/png;base64,...` and no reference to anything outside it (a Content-Security-Policy in
//! the page enforces that), so a report can be mailed, archived or attached to a CI run as is.
//!
//! All text is HTML-escaped. A small inline script checks on load that every image decoded and
//! records the result on `<body>` (`data-images-ok="N/N"`, `data-report-ready="1"`), which lets a
//! headless browser verify a page.

use std::fmt::Write as _;

/// One table cell.
#[derive(Debug, Clone, PartialEq)]
pub enum Cell {
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
pub struct HtmlReport {
    title: String,
    blocks: Vec<Block>,
}

impl HtmlReport {
    /// An empty report with a page title (also the `<h1>`).
    pub fn new(title: impl Into<String>) -> Self {
        HtmlReport {
            title: title.into(),
            blocks: Vec::new(),
        }
    }

    /// Start a section with a heading.
    pub fn section(&mut self, heading: impl Into<String>) -> &mut Self {
        self.blocks.push(Block::Section(heading.into()));
        self
    }

    /// A paragraph of plain text.
    pub fn paragraph(&mut self, text: impl Into<String>) -> &mut Self {
        self.blocks.push(Block::Paragraph(text.into()));
        self
    }

    /// A two-column table of names and values (metadata).
    pub fn key_values(&mut self, rows: Vec<(String, String)>) -> &mut Self {
        self.blocks.push(Block::KeyValue(rows));
        self
    }

    /// A table with a header row.
    pub fn table(
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
    pub fn image(&mut self, caption: impl Into<String>, png: Vec<u8>) -> &mut Self {
        self.figures(vec![(caption.into(), png)])
    }

    /// Images shown side by side (wrapping on narrow screens), each with its caption.
    pub fn figures(&mut self, figures: Vec<(String, Vec<u8>)>) -> &mut Self {
        self.blocks.push(Block::Figures(
            figures
                .into_iter()
                .map(|(caption, png)| Figure { caption, png })
                .collect(),
        ));
        self
    }

    /// Number of images in the report.
    pub fn image_count(&self) -> usize {
        self.blocks
            .iter()
            .map(|b| match b {
                Block::Figures(f) => f.len(),
                _ => 0,
            })
            .sum()
    }

    /// The page.
    pub fn to_html(&self) -> String {
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
pub fn escape(text: &str) -> String {
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
pub fn base64_encode(bytes: &[u8]) -> String {
    use base64::Engine as _;
    base64::engine::general_purpose::STANDARD.encode(bytes)
}

/// A metric value with sensible precision: four significant digits, scientific notation outside
/// 1e-3 ..= 1e5.
pub fn format_value(v: f64) -> String {
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
