//! `veila_metrics::texture` against its numpy / scipy reference (`tests/data/texture_reference.py` writes
//! `tests/data/texture_reference.json`) and against closed forms.

use serde_json::Value;
use veila_geom::RangeImage;
use veila_metrics::Error;
use veila_metrics::texture::{
    Direction, RowBand, STEP_BINS, StepHistogram, drop_disagreement, nearest_scan,
    pairwise_range_mae, raydrop_per_row, raydrop_row_distance, relative_step, scan_distance,
    step_histogram, texture_distance, texture_jsd,
};

fn reference() -> Value {
    let path = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/tests/data/texture_reference.json"
    );
    serde_json::from_str(&std::fs::read_to_string(path).expect("texture_reference.json"))
        .expect("valid json")
}

fn image(v: &Value) -> RangeImage {
    let (rows, cols) = (
        v["rows"].as_u64().unwrap() as u32,
        v["cols"].as_u64().unwrap() as u32,
    );
    let mut img = RangeImage::new_empty(rows, cols);
    img.range_m = v["range_m"]
        .as_array()
        .unwrap()
        .iter()
        .map(|x| match x.as_str() {
            Some("nan") => f32::NAN,
            Some("inf") => f32::INFINITY,
            Some(other) => panic!("unexpected range {other}"),
            None => x.as_f64().unwrap() as f32,
        })
        .collect();
    img.mask = v["mask"]
        .as_array()
        .unwrap()
        .iter()
        .map(|b| b.as_bool().unwrap())
        .collect();
    img
}

fn region(v: &Value) -> Option<Vec<bool>> {
    v.as_array()
        .map(|a| a.iter().map(|b| b.as_bool().unwrap()).collect())
}

fn direction_name(d: Direction) -> &'static str {
    match d {
        Direction::AlongRow => "along_row",
        Direction::AcrossRows => "across_rows",
    }
}

fn band_name(b: RowBand) -> &'static str {
    match b {
        RowBand::All => "all",
        RowBand::Upper => "upper",
        RowBand::Lower => "lower",
    }
}

/// `want` null means NaN; otherwise within 1e-12 relative.
fn assert_close(got: f64, want: &Value, what: &str) {
    match want.as_f64() {
        None => {
            assert!(want.is_null(), "{what}: bad reference {want}");
            assert!(got.is_nan(), "{what}: got {got}, want NaN");
        }
        Some(w) => {
            let err = (got - w).abs() / w.abs().max(1e-300);
            assert!(
                err <= 1e-12 || got == w,
                "{what}: got {got:.17e}, want {w:.17e}, rel err {err:.3e}"
            );
        }
    }
}

fn assert_histogram(got: &StepHistogram, want: &Value, what: &str) {
    let counts: Vec<u64> = want["counts"]
        .as_array()
        .unwrap()
        .iter()
        .map(|c| c.as_u64().unwrap())
        .collect();
    assert_eq!(got.counts(), counts.as_slice(), "{what}: counts");
    assert_eq!(
        got.smooth_count(),
        want["smooth"].as_u64().unwrap(),
        "{what}: smooth"
    );
    assert_eq!(
        got.edge_count(),
        want["edge"].as_u64().unwrap(),
        "{what}: edge"
    );
}

fn shape<T>(r: Result<T, Error>) -> bool {
    matches!(r, Err(Error::ShapeMismatch { .. }))
}

fn constant(rows: u32, cols: u32, r: f32) -> RangeImage {
    RangeImage::try_from_range_m(rows, cols, vec![r; (rows * cols) as usize]).unwrap()
}

#[test]
fn step_histograms_shares_w1_and_jsd_match_numpy_scipy() {
    let r = reference();
    let (a, b) = (image(&r["images"]["a"]), image(&r["images"]["b"]));
    let mut checked = 0;
    for (rname, reg) in r["regions"].as_object().unwrap() {
        let reg = region(reg);
        for d in Direction::ALL {
            for band in RowBand::ALL {
                let key = format!("{rname}/{}/{}", direction_name(d), band_name(band));
                let want = &r["histograms"][&key];
                assert!(want.is_object(), "{key} missing from the reference");
                let ha = step_histogram(std::slice::from_ref(&a), reg.as_deref(), d, band).unwrap();
                let hb = step_histogram(std::slice::from_ref(&b), reg.as_deref(), d, band).unwrap();
                let pooled =
                    step_histogram(&[a.clone(), b.clone()], reg.as_deref(), d, band).unwrap();
                assert_histogram(&ha, &want["a"], &format!("{key} a"));
                assert_histogram(&hb, &want["b"], &format!("{key} b"));
                assert_histogram(&pooled, &want["pooled"], &format!("{key} pooled"));
                let mut merged = ha.clone();
                merged.merge(&hb);
                assert_eq!(merged, pooled, "{key}: merge = pooled set");
                assert_close(
                    ha.smooth_share(),
                    &want["a_smooth_share"],
                    &format!("{key} smooth"),
                );
                assert_close(
                    ha.edge_share(),
                    &want["a_edge_share"],
                    &format!("{key} edge"),
                );
                assert_close(
                    texture_distance(&ha, &hb),
                    &want["w1"],
                    &format!("{key} w1"),
                );
                assert_close(texture_jsd(&ha, &hb), &want["jsd"], &format!("{key} jsd"));
                checked += 1;
            }
        }
    }
    assert_eq!(checked, 18);
}

#[test]
fn raydrop_per_row_and_its_distance_match_numpy() {
    let r = reference();
    let (a, b) = (image(&r["images"]["a"]), image(&r["images"]["b"]));
    for (rname, reg) in r["regions"].as_object().unwrap() {
        let reg = region(reg);
        let want = &r["raydrop"][rname];
        let pa = raydrop_per_row(std::slice::from_ref(&a), reg.as_deref()).unwrap();
        let pb = raydrop_per_row(std::slice::from_ref(&b), reg.as_deref()).unwrap();
        let pooled = raydrop_per_row(&[a.clone(), b.clone()], reg.as_deref()).unwrap();
        for (got, key) in [(&pa, "a"), (&pb, "b"), (&pooled, "pooled")] {
            let w = want[key].as_array().unwrap();
            assert_eq!(got.len(), w.len(), "{rname} {key}: rows");
            for (i, (g, w)) in got.iter().zip(w).enumerate() {
                assert_close(*g, w, &format!("{rname} {key} row {i}"));
            }
        }
        assert_close(
            raydrop_row_distance(&pa, &pb).unwrap(),
            &want["distance"],
            &format!("{rname} distance"),
        );
    }
}

#[test]
fn pairwise_diversity_matches_numpy() {
    let r = reference();
    let (a, b) = (image(&r["images"]["a"]), image(&r["images"]["b"]));
    for (rname, reg) in r["regions"].as_object().unwrap() {
        let reg = region(reg);
        let want = &r["diversity"][rname];
        assert_close(
            pairwise_range_mae(&a, &b, reg.as_deref()).unwrap(),
            &want["range_mae"],
            &format!("{rname} range mae"),
        );
        assert_close(
            drop_disagreement(&a, &b, reg.as_deref()).unwrap(),
            &want["drop_disagreement"],
            &format!("{rname} drop disagreement"),
        );
    }
}

#[test]
fn nearest_scan_matches_numpy_and_breaks_the_tie_to_the_lowest_index() {
    let r = reference();
    let pool: Vec<RangeImage> = r["nearest"]["pool"]
        .as_array()
        .unwrap()
        .iter()
        .map(image)
        .collect();
    for (qname, want) in r["nearest"]["queries"].as_object().unwrap() {
        let q = image(&r["images"][qname.as_str()]);
        for (i, (p, w)) in pool
            .iter()
            .zip(want["distances"].as_array().unwrap())
            .enumerate()
        {
            assert_close(
                scan_distance(&q, p).unwrap(),
                w,
                &format!("{qname} vs pool {i}"),
            );
        }
        let (index, d) = nearest_scan(&q, &pool).unwrap();
        assert_eq!(
            index as u64,
            want["index"].as_u64().unwrap(),
            "{qname}: index"
        );
        assert_close(d, &want["distance"], &format!("{qname}: distance"));
    }
    // the reference pool holds the nearest scan of `a` twice (indices 2 and 4): the lower index wins,
    // also when the order is reversed
    let a = image(&r["images"]["a"]);
    let reversed: Vec<RangeImage> = pool.iter().rev().cloned().collect();
    assert_eq!(nearest_scan(&a, &reversed).unwrap().0, 0);
}

#[test]
fn a_constant_range_image_is_all_underflow_smooth_and_edgeless() {
    let img = constant(4, 16, 12.5);
    for band in RowBand::ALL {
        let h =
            step_histogram(std::slice::from_ref(&img), None, Direction::AlongRow, band).unwrap();
        let pairs = band.rows(4).len() as u64 * 16;
        assert_eq!(h.total(), pairs, "{band:?}");
        assert_eq!(h.counts()[0], pairs, "{band:?}: underflow");
        assert_eq!(h.smooth_share(), 1.0, "{band:?}");
        assert_eq!(h.edge_share(), 0.0, "{band:?}");
        let p = h.probabilities();
        assert_eq!(p[0], 1.0);
        assert!(p[1..].iter().all(|&x| x == 0.0));
    }
    // across rows: 3 row pairs in all, one in each half (the straddling pair is in neither)
    let count = |band| {
        step_histogram(
            std::slice::from_ref(&img),
            None,
            Direction::AcrossRows,
            band,
        )
        .unwrap()
        .total()
    };
    assert_eq!(
        (
            count(RowBand::All),
            count(RowBand::Upper),
            count(RowBand::Lower)
        ),
        (48, 16, 16)
    );
}

#[test]
fn bins_shares_and_thresholds_follow_the_definition() {
    assert_eq!(relative_step(5.0, 10.0), 1.0);
    assert_eq!(relative_step(10.0, 5.0), 1.0);
    for k in 0..STEP_BINS {
        let c = StepHistogram::bin_center(k);
        assert_eq!(c, -6.125 + 0.25 * k as f64);
        assert_eq!(
            StepHistogram::bin_of(10f64.powf(c)),
            Some(k),
            "centre of bin {k}"
        );
    }
    assert_eq!(StepHistogram::bin_of(0.0), Some(0));
    assert_eq!(StepHistogram::bin_of(9.99e-7), Some(0));
    assert_eq!(StepHistogram::bin_of(1e-6), Some(1));
    assert_eq!(StepHistogram::bin_of(99.999), Some(STEP_BINS - 2));
    assert_eq!(StepHistogram::bin_of(100.0), Some(STEP_BINS - 1));
    assert_eq!(StepHistogram::bin_of(f64::INFINITY), Some(STEP_BINS - 1));
    assert_eq!(StepHistogram::bin_of(f64::NAN), None);
    // smooth is strictly below 3e-4, an edge strictly above 1
    let mut h = StepHistogram::new();
    for s in [0.0, 2.9999e-4, 3e-4, 3.0001e-4, 1.0, 1.0000001, f64::NAN] {
        h.add(s);
    }
    assert_eq!((h.total(), h.smooth_count(), h.edge_count()), (6, 2, 1));
    assert_eq!(h.smooth_share(), 2.0 / 6.0);
    assert_eq!(h.edge_share(), 1.0 / 6.0);
}

#[test]
fn w1_is_zero_on_itself_and_a_quarter_decade_per_bin_apart() {
    let single = |bin: usize, n: u64| {
        let mut h = StepHistogram::new();
        for _ in 0..n {
            h.add(10f64.powf(StepHistogram::bin_center(bin)));
        }
        assert_eq!(h.counts()[bin], n);
        h
    };
    for i in 0..STEP_BINS {
        for j in 0..STEP_BINS {
            let (a, b) = (single(i, 3), single(j, 7));
            let want = 0.25 * (i as f64 - j as f64).abs();
            assert_eq!(texture_distance(&a, &b), want, "bins {i} and {j}");
            assert_eq!(texture_distance(&b, &a), want, "bins {j} and {i}");
            let jsd = texture_jsd(&a, &b);
            if i == j {
                assert_eq!(jsd, 0.0);
            } else {
                assert!((jsd - std::f64::consts::LN_2.sqrt()).abs() < 1e-15, "{jsd}");
            }
        }
    }
    let mut mixed = single(0, 5);
    mixed.merge(&single(10, 2));
    mixed.merge(&single(33, 9));
    assert_eq!(texture_distance(&mixed, &mixed), 0.0);
    assert_eq!(texture_jsd(&mixed, &mixed), 0.0);
    // half the mass moved by 4 bins: 0.5 * 4 * 0.25
    let mut half = single(3, 1);
    half.merge(&single(7, 1));
    assert_eq!(texture_distance(&single(3, 2), &half), 0.5);
    let empty = StepHistogram::new();
    assert!(texture_distance(&empty, &mixed).is_nan());
    assert!(texture_distance(&mixed, &empty).is_nan());
    assert!(texture_jsd(&empty, &mixed).is_nan());
}

#[test]
fn a_region_that_excludes_everything_gives_empty_and_nan() {
    let (a, b) = (constant(4, 8, 10.0), constant(4, 8, 11.0));
    let none = vec![false; 32];
    for d in Direction::ALL {
        let h = step_histogram(&[a.clone(), b.clone()], Some(&none), d, RowBand::All).unwrap();
        assert!(h.is_empty());
        assert!(h.smooth_share().is_nan() && h.edge_share().is_nan());
        assert!(h.probabilities().iter().all(|p| p.is_nan()));
        assert!(texture_distance(&h, &h).is_nan() && texture_jsd(&h, &h).is_nan());
    }
    let rows = raydrop_per_row(std::slice::from_ref(&a), Some(&none)).unwrap();
    assert_eq!(rows.len(), 4);
    assert!(rows.iter().all(|x| x.is_nan()));
    assert!(raydrop_row_distance(&rows, &rows).unwrap().is_nan());
    assert!(pairwise_range_mae(&a, &b, Some(&none)).unwrap().is_nan());
    assert!(drop_disagreement(&a, &b, Some(&none)).unwrap().is_nan());
    // no pixel valid in both: NaN MAE, full disagreement
    let dropped = RangeImage::new_empty(4, 8);
    assert!(pairwise_range_mae(&a, &dropped, None).unwrap().is_nan());
    assert_eq!(drop_disagreement(&a, &dropped, None).unwrap(), 1.0);
    // a drop against a return costs log2(1 + r)
    let d = scan_distance(&a, &dropped).unwrap();
    assert!((d - 11f64.log2()).abs() < 1e-15, "{d}");
    // a single column has no along-row pair
    let column = constant(4, 1, 3.0);
    let h = step_histogram(&[column], None, Direction::AlongRow, RowBand::All).unwrap();
    assert!(h.is_empty());
}

#[test]
fn mismatched_sizes_are_errors_not_panics() {
    let a = constant(4, 8, 10.0);
    let wide = constant(4, 9, 10.0);
    let mut short_range = a.clone();
    short_range.range_m.pop();
    let mut short_mask = a.clone();
    short_mask.mask.push(true);
    let bad_region = vec![true; 31];
    for d in Direction::ALL {
        assert!(shape(step_histogram(
            &[a.clone(), wide.clone()],
            None,
            d,
            RowBand::All
        )));
        assert!(shape(step_histogram(
            &[short_range.clone()],
            None,
            d,
            RowBand::All
        )));
        assert!(shape(step_histogram(
            &[a.clone(), short_mask.clone()],
            None,
            d,
            RowBand::All
        )));
        assert!(shape(step_histogram(
            std::slice::from_ref(&a),
            Some(&bad_region),
            d,
            RowBand::Upper
        )));
        let mut h = StepHistogram::new();
        assert!(shape(h.add_image(&short_mask, None, d, RowBand::Lower)));
    }
    assert!(matches!(
        step_histogram(&[], None, Direction::AlongRow, RowBand::All),
        Err(Error::Empty { .. })
    ));
    assert!(shape(raydrop_per_row(&[a.clone(), wide.clone()], None)));
    assert!(shape(raydrop_per_row(
        std::slice::from_ref(&a),
        Some(&bad_region)
    )));
    assert!(shape(raydrop_per_row(&[short_range.clone()], None)));
    assert!(matches!(
        raydrop_per_row(&[], None),
        Err(Error::Empty { .. })
    ));
    assert!(shape(raydrop_row_distance(&[0.0; 4], &[0.0; 5])));
    for f in [pairwise_range_mae, drop_disagreement] {
        assert!(shape(f(&a, &wide, None)));
        assert!(shape(f(&a, &short_range, None)));
        assert!(shape(f(&short_mask, &a, None)));
        assert!(shape(f(&a, &a, Some(&bad_region))));
    }
    assert!(shape(scan_distance(&a, &wide)));
    assert!(shape(nearest_scan(&a, &[a.clone(), wide.clone()])));
    assert!(shape(nearest_scan(&a, &[short_mask.clone()])));
    assert!(shape(nearest_scan(&short_range, std::slice::from_ref(&a))));
    assert!(matches!(nearest_scan(&a, &[]), Err(Error::Empty { .. })));
    let nothing = RangeImage::new_empty(0, 8);
    assert!(matches!(
        nearest_scan(&nothing, std::slice::from_ref(&nothing)),
        Err(Error::Empty { .. })
    ));
}

#[test]
fn step_histograms_round_trip_through_json_and_reject_bad_counts() {
    let img = image(&reference()["images"]["a"]);
    let h = step_histogram(&[img], None, Direction::AlongRow, RowBand::All).unwrap();
    let json = serde_json::to_string(&h).unwrap();
    let back: StepHistogram = serde_json::from_str(&json).unwrap();
    assert_eq!(back, h);
    assert!(
        serde_json::from_str::<StepHistogram>(r#"{"counts":[1,2],"smooth":0,"edge":0}"#).is_err()
    );
    let too_many = format!(
        r#"{{"counts":{:?},"smooth":2,"edge":0}}"#,
        [[1u64].as_slice(), &[0; STEP_BINS - 1]].concat()
    );
    assert!(serde_json::from_str::<StepHistogram>(&too_many).is_err());
}

/// The demo's summary, closed forms: the upper half of an image whose every other column is
/// four times as far has an edge at every along-row pair; a flat lower half is all smooth; a scan
/// against itself is 0 decades away, and a scan with every step of 1e-3 (steps of s = 1e-3 fall in
/// one bin) is the distance between that bin and the underflow bin.
#[test]
fn the_demo_summary_counts_edges_above_and_smooth_ground_below() {
    let (rows, cols) = (4u32, 16u32);
    let mut r = vec![10.0f32; (rows * cols) as usize];
    for c in (0..cols as usize).step_by(2) {
        r[c] = 40.0; // row 0 (upper half): a jump of 300 % at every along-row pair
        r[cols as usize + c] = 40.0; // row 1 too
    }
    let img = RangeImage::try_from_range_m(rows, cols, r).unwrap();
    let s = veila_metrics::texture::TextureSummary::of(&img, &img).unwrap();
    assert_eq!(s.depth_edges_upper_pct, 100.0);
    assert_eq!(s.smooth_lower_pct, 100.0);
    assert_eq!(s.w1_along_decades, 0.0);
    // a geometric ramp along each row: 15 steps of s = 0.002 (log10 = -2.70: regular bin 13, the
    // histogram's bin 14) and the wrap-around step 1.002^15 - 1 = 0.0304 (log10 = -1.52: bin 18);
    // the flat reference is all underflow (bin 0), so W1 = (15 * 14 + 18) / 16 bins of 0.25
    let ramp: Vec<f32> = (0..rows * cols)
        .map(|p| (10.0 * 1.002f64.powi((p % cols) as i32)) as f32)
        .collect();
    let ramp = RangeImage::try_from_range_m(rows, cols, ramp).unwrap();
    let flat = constant(rows, cols, 10.0);
    let s = veila_metrics::texture::TextureSummary::of(&ramp, &flat).unwrap();
    assert_eq!(s.depth_edges_upper_pct, 0.0);
    assert_eq!(s.smooth_lower_pct, 0.0);
    let want = 0.25 * (15.0 * 14.0 + 18.0) / 16.0;
    assert!(
        (s.w1_along_decades - want).abs() < 1e-12,
        "{} vs {want}",
        s.w1_along_decades
    );
}
