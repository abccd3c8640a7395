//! `veila eval --report`: a self-contained HTML page whose images decode, checked without a browser
//! (structure, escaping, embedded PNGs decoded independently) and, where Chromium is installed, in a
//! headless browser (every `<img>` decoded, the metric table present).

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use glam::Vec3;
use veila_data::vis::render::{BevOptions, render_bev};

fn veila() -> Command {
    Command::new(env!("CARGO_BIN_EXE_veila"))
}

fn write_bin(path: &Path, pts: &[Vec3]) {
    let mut bytes = Vec::new();
    for p in pts {
        for v in [p.x, p.y, p.z, 0.5] {
            bytes.extend_from_slice(&v.to_le_bytes());
        }
    }
    std::fs::write(path, bytes).unwrap();
}

/// A ring-shaped scan with a wall, from a fixed xorshift stream.
fn scan(seed: u32, n: usize, wall_y: f32) -> Vec<Vec3> {
    let mut s = seed.wrapping_mul(2_654_435_761).wrapping_add(1);
    let mut next = || {
        s ^= s << 13;
        s ^= s >> 17;
        s ^= s << 5;
        s as f32 / u32::MAX as f32
    };
    let mut pts: Vec<Vec3> = (0..n)
        .map(|_| {
            let r = 4.0 + 40.0 * next();
            let t = std::f32::consts::TAU * next();
            Vec3::new(r * t.cos(), r * t.sin(), -1.7 + 0.2 * next())
        })
        .collect();
    pts.extend((0..n / 4).map(|_| Vec3::new(-30.0 + 60.0 * next(), wall_y, -1.5 + 3.0 * next())));
    pts
}

/// Generated and reference folders with three scans each; the generated folder's name carries
/// markup that the report must escape.
fn inputs(dir: &Path) -> (PathBuf, PathBuf) {
    let g = dir.join("gen<script>alert(\"x\")&");
    let r = dir.join("ref");
    std::fs::create_dir_all(&g).unwrap();
    std::fs::create_dir_all(&r).unwrap();
    for i in 0..3u32 {
        write_bin(&g.join(format!("{i:06}.bin")), &scan(i, 3000, 10.0));
        write_bin(&r.join(format!("{i:06}.bin")), &scan(100 + i, 3000, 12.0));
    }
    (g, r)
}

fn run_report(dir: &Path) -> (PathBuf, PathBuf, String) {
    let (g, r) = inputs(dir);
    let html = dir.join("report.html");
    let json = dir.join("metrics.json");
    let out = veila()
        .arg("--quiet")
        .arg("eval")
        .arg("--generated")
        .arg(&g)
        .arg("--reference")
        .arg(&r)
        .args(["--metrics", "jsd,mmd,chamfer"])
        .arg("--json")
        .arg(&json)
        .arg("--report")
        .arg(&html)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(json.is_file());
    let text = std::fs::read_to_string(&html).unwrap();
    (g, html, text)
}

/// An independent base64 decoder (a 256-entry reverse table; padding and whitespace ignored).
fn base64_decode(s: &str) -> Vec<u8> {
    let mut table = [255u8; 256];
    for (i, c) in (b'A'..=b'Z')
        .chain(b'a'..=b'z')
        .chain(b'0'..=b'9')
        .chain([b'+', b'/'])
        .enumerate()
    {
        table[c as usize] = i as u8;
    }
    let vals: Vec<u8> = s
        .bytes()
        .filter(|b| !b.is_ascii_whitespace() && *b != b'=')
        .map(|b| {
            let v = table[b as usize];
            assert_ne!(v, 255, "not a base64 character: {:?}", b as char);
            v
        })
        .collect();
    let mut out = Vec::with_capacity(vals.len() * 3 / 4);
    for q in vals.chunks(4) {
        let mut n = 0u32;
        for (k, v) in q.iter().enumerate() {
            n |= (*v as u32) << (18 - 6 * k);
        }
        let bytes = [(n >> 16) as u8, (n >> 8) as u8, n as u8];
        out.extend_from_slice(&bytes[..q.len().saturating_sub(1)]);
    }
    out
}

/// The payloads of every `data:image/png;base64,` URL in the page.
fn embedded_pngs(html: &str) -> Vec<Vec<u8>> {
    let key = "src=\"data:image/png;base64,";
    html.match_indices(key)
        .map(|(i, _)| {
            let rest = &html[i + key.len()..];
            let end = rest.find('"').unwrap();
            base64_decode(&rest[..end])
        })
        .collect()
}

#[test]
fn report_is_self_contained_escaped_and_its_images_decode() {
    let dir = tempfile::tempdir().unwrap();
    let (g, _html, text) = run_report(dir.path());

    // self-contained: no network or file references, no external stylesheets or scripts
    for bad in [
        "http://",
        "https://",
        "src=\"file:",
        "href=",
        "url(",
        "@import",
        "<link",
        "src=\"/",
    ] {
        assert!(!text.contains(bad), "the report references {bad:?}");
    }
    // markup in user-provided names is escaped; the only script is the report's own
    assert!(!text.contains("<script>alert"), "unescaped folder name");
    assert!(text.contains("gen&lt;script&gt;alert(&quot;x&quot;)&amp;"));
    assert_eq!(text.matches("<script").count(), 1);
    assert!(text.contains("document.body.dataset.imagesOk"));

    // the metric table: metric names, protocols, regions
    for needle in [
        "<td>jsd</td>",
        "<td>mmd</td>",
        "<td>chamfer</td>",
        "<td>r2dm</td>",
        "<td>pytorch3d</td>",
        ">all</th>",
        ">front</th>",
        ">rear</th>",
    ] {
        assert!(text.contains(needle), "missing {needle}");
    }
    // the JSD value of the JSON is in the table, formatted to four significant digits
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.path().join("metrics.json")).unwrap())
            .unwrap();
    let jsd_all = json["metrics"]
        .as_array()
        .unwrap()
        .iter()
        .find(|m| m["name"] == "jsd" && m["region"] == "all")
        .unwrap()["value"]
        .as_f64()
        .unwrap();
    assert!(jsd_all > 1e-3 && jsd_all < 1.0, "{jsd_all}");
    let decimals = (3 - jsd_all.log10().floor() as i32) as usize;
    assert!(
        text.contains(&format!(">{jsd_all:.decimals$}<")),
        "JSD {jsd_all} not in the table"
    );

    // every embedded image is a PNG that decodes; the first is the BEV preview of the first
    // generated scan with the options its caption states (±50 m, 0.2 m per pixel)
    let pngs = embedded_pngs(&text);
    assert_eq!(pngs.len(), text.matches("<img ").count());
    assert_eq!(
        pngs.len(),
        5,
        "two BEV previews, the difference image, two plots"
    );
    for p in &pngs {
        assert_eq!(&p[..8], b"\x89PNG\r\n\x1a\n");
        let img = veila_data::image::load_from_memory(p).unwrap();
        assert!(img.width() > 100 && img.height() > 100);
    }
    let cloud = veila_data::scan::read_points(&g.join("000000.bin"))
        .unwrap()
        .cloud;
    let opts = BevOptions {
        half_extent_m: 50.0,
        resolution_m: 0.2,
        z_min_m: -2.5,
        z_max_m: 1.5,
    };
    assert!(text.contains("±50 m, 0.2 m per pixel"));
    let expected = render_bev(&cloud, &opts).unwrap();
    let got = veila_data::image::load_from_memory(&pngs[0])
        .unwrap()
        .into_rgb8();
    assert_eq!(
        got, expected,
        "the BEV preview is not the first generated scan"
    );

    // nothing else was left in the folder (atomic writes)
    let mut names: Vec<String> = std::fs::read_dir(dir.path())
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    names.sort();
    assert_eq!(names.len(), 4, "{names:?}");
}

#[test]
fn no_report_when_the_evaluation_fails() {
    let dir = tempfile::tempdir().unwrap();
    let (g, r) = inputs(dir.path());
    // a generated scan without a finite point fails the evaluation
    write_bin(&g.join("000009.bin"), &[Vec3::splat(f32::NAN)]);
    let html = dir.path().join("report.html");
    let out = veila()
        .arg("--quiet")
        .arg("eval")
        .arg("--generated")
        .arg(&g)
        .arg("--reference")
        .arg(&r)
        .arg("--report")
        .arg(&html)
        .output()
        .unwrap();
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("000009.bin"));
    assert!(!html.exists());

    // a report in a missing folder is refused before any work
    let missing = dir.path().join("no/such/report.html");
    std::fs::remove_file(g.join("000009.bin")).unwrap();
    let out = veila()
        .arg("--quiet")
        .arg("eval")
        .arg("--generated")
        .arg(&g)
        .arg("--reference")
        .arg(&r)
        .arg("--report")
        .arg(&missing)
        .output()
        .unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("no/such") && err.contains("does not exist"),
        "{err}"
    );
    // and no temporary files anywhere
    let leftovers: Vec<_> = std::fs::read_dir(dir.path())
        .unwrap()
        .map(|e| e.unwrap().file_name())
        .filter(|n| n.to_string_lossy().starts_with(".veila-"))
        .collect();
    assert!(leftovers.is_empty(), "{leftovers:?}");
}

/// `/usr/bin/chromium`, or `chromium` on PATH.
fn find_chromium() -> Option<PathBuf> {
    let fixed = PathBuf::from("/usr/bin/chromium");
    if fixed.is_file() {
        return Some(fixed);
    }
    std::env::var_os("PATH").and_then(|paths| {
        std::env::split_paths(&paths)
            .map(|d| d.join("chromium"))
            .find(|p| p.is_file())
    })
}

#[test]
fn headless_chromium_decodes_every_image() {
    let Some(chromium) = find_chromium() else {
        eprintln!("skipping: chromium not found");
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let (_g, html, text) = run_report(dir.path());
    let n_images = text.matches("<img ").count();
    assert!(n_images > 0);
    let profile = dir.path().join("chromium-profile");
    let dom_path = dir.path().join("dom.html");
    let dom_file = std::fs::File::create(&dom_path).unwrap();
    let mut child = Command::new(&chromium)
        .args([
            "--headless",
            "--no-sandbox",
            "--disable-gpu",
            "--disable-dev-shm-usage",
            "--no-first-run",
            "--virtual-time-budget=5000",
        ])
        .arg(format!("--user-data-dir={}", profile.display()))
        .arg("--dump-dom")
        .arg(format!("file://{}", html.canonicalize().unwrap().display()))
        .stdout(dom_file)
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let deadline = Instant::now() + Duration::from_secs(120);
    let status = loop {
        if let Some(s) = child.try_wait().unwrap() {
            break s;
        }
        if Instant::now() > deadline {
            let _ = child.kill();
            let _ = child.wait();
            panic!("chromium did not finish within 120 s");
        }
        std::thread::sleep(Duration::from_millis(50));
    };
    assert!(status.success(), "chromium failed: {status}");
    let dom = std::fs::read_to_string(&dom_path).unwrap();
    assert!(
        dom.contains("data-report-ready=\"1\""),
        "the page's load handler did not run: {}",
        &dom[..dom.len().min(400)]
    );
    let want = format!("data-images-ok=\"{n_images}/{n_images}\"");
    assert!(
        dom.contains(&want),
        "expected {want}; body: {}",
        dom.lines().find(|l| l.contains("<body")).unwrap_or("")
    );
    for needle in ["<td>jsd</td>", "<td>mmd</td>", "<td>chamfer</td>"] {
        assert!(dom.contains(needle), "{needle} not in the rendered page");
    }
}
