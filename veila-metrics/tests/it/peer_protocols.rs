//! The peers' whole pipelines on real scans against their numpy reproductions
//! (`tests/data/peer_protocols.py` writes `tests/data/peer_protocols.json`). Skipped with a message when
//! `../shared/data/real` is absent.

use std::path::{Path, PathBuf};

use serde_json::Value;
use veila_metrics::Region;
use veila_metrics::protocol::{PeerProtocol, PeerSummary};

fn data_root() -> Option<PathBuf> {
    let p = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/data/real");
    if p.is_dir() {
        Some(p)
    } else {
        eprintln!("skipping: {} is absent", p.display());
        None
    }
}

fn reference() -> Value {
    let path = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/tests/data/peer_protocols.json"
    );
    serde_json::from_str(&std::fs::read_to_string(path).expect("peer_protocols.json")).unwrap()
}

/// xyz of a KITTI `.bin` (4 f32) or nuScenes `.pcd.bin` (5 f32) scan.
fn read_xyz(path: &Path) -> Vec<[f32; 3]> {
    let bytes = std::fs::read(path).unwrap();
    let cols = if path.to_string_lossy().ends_with(".pcd.bin") {
        5
    } else {
        4
    };
    bytes
        .chunks_exact(4 * cols)
        .map(|r| {
            let f = |i: usize| f32::from_le_bytes(r[4 * i..4 * i + 4].try_into().unwrap());
            [f(0), f(1), f(2)]
        })
        .collect()
}

fn rel(got: f64, want: f64) -> f64 {
    (got - want).abs() / want.abs().max(1e-300)
}

#[test]
fn every_protocol_reproduces_the_peer_scripts_on_real_scans() {
    let Some(root) = data_root() else { return };
    let r = reference();
    let mut worst = 0.0f64;
    for (set_name, set) in r["sets"].as_object().unwrap() {
        let load = |key: &str| -> Vec<Vec<[f32; 3]>> {
            set[key]
                .as_array()
                .unwrap()
                .iter()
                .map(|p| read_xyz(&root.join(p.as_str().unwrap())))
                .collect()
        };
        let (gen_scans, ref_scans) = (load("generated"), load("reference"));
        for proto in PeerProtocol::ALL {
            let want = &r["raw"][set_name][proto.name()];
            let prepare = |scans: &[Vec<[f32; 3]>], key: &str| -> Vec<PeerSummary> {
                scans
                    .iter()
                    .enumerate()
                    .map(|(i, s)| {
                        let pts = proto.prepare_scan(s, "scan").unwrap();
                        // the prepared points themselves: same count and coordinate sums as numpy
                        let w = &want[key][i];
                        assert_eq!(
                            pts.len() as u64,
                            w["points"].as_u64().unwrap(),
                            "{set_name} {proto} {key} {i}: point count"
                        );
                        let sx: f64 = pts.iter().map(|p| p[0]).sum();
                        let sy: f64 = pts.iter().map(|p| p[1]).sum();
                        let scale = pts.len() as f64;
                        for (got, k) in [(sx, "sum_x"), (sy, "sum_y")] {
                            let w = w[k].as_f64().unwrap();
                            assert!(
                                (got - w).abs() <= 1e-3 * scale.max(1.0),
                                "{set_name} {proto} {key} {i} {k}: {got} vs {w}"
                            );
                        }
                        proto.summarise(&pts, Region::All, "scan").unwrap()
                    })
                    .collect()
            };
            let g = prepare(&gen_scans, "generated_points");
            let rf = prepare(&ref_scans, "reference_points");
            let got = proto.score(&g, &rf).unwrap();
            for m in got {
                let w = want[m.name].as_f64().unwrap();
                let e = rel(m.value, w);
                worst = worst.max(e);
                eprintln!(
                    "{set_name:9} {:14} {}: {:.10e} (numpy {w:.10e}, rel {e:.1e})",
                    proto.name(),
                    m.name,
                    m.value
                );
                assert!(
                    e <= 1e-4,
                    "{set_name} {proto} {}: {} vs numpy {w} (rel {e:.2e})",
                    m.name,
                    m.value
                );
            }
        }
    }
    eprintln!("worst relative difference {worst:.2e}");
}

#[test]
fn raw_points_differ_from_the_protocol_numbers() {
    // the reason the pipelines exist: scoring raw points gives another number than the peer reports
    let Some(root) = data_root() else { return };
    let r = reference();
    let set = &r["sets"]["kitti"];
    let load = |key: &str| -> Vec<Vec<[f32; 3]>> {
        set[key]
            .as_array()
            .unwrap()
            .iter()
            .map(|p| read_xyz(&root.join(p.as_str().unwrap())))
            .collect()
    };
    let hist = |scans: &[Vec<[f32; 3]>]| -> Vec<_> {
        scans
            .iter()
            .map(|s| {
                veila_metrics::bev::bev_histogram_sparse(
                    s,
                    &veila_metrics::bev::BevConfig::r2dm(),
                    Region::All,
                    "s",
                )
                .unwrap()
            })
            .collect()
    };
    let raw =
        veila_metrics::dist::jsd(&hist(&load("generated")), &hist(&load("reference"))).unwrap();
    let peer = r["raw"]["kitti"]["r2dm"]["jsd"].as_f64().unwrap();
    assert!(rel(raw, peer) > 1e-3, "raw {raw} vs r2dm {peer}");
}
