//! Issue 47: sizes that come from an input are checked before anything is allocated (a feature row
//! too wide for its covariance, a scan too big for a nearest-neighbour index), settings outside
//! their sense are refused (Newton–Schulz with 0 iterations), and CM-SC refuses a class map
//! outside the train-id space instead of reporting a near-0 % agreement.

use glam::Vec3;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use veila_metrics::{Error, crossmodal, fd, nn::PointIndex};

#[test]
fn a_feature_row_too_wide_for_its_covariance_is_refused_before_allocation() {
    // the (4, 65536) arrays: 34 GB per 65536 x 65536 covariance
    let rows = vec![0.5f32; 4 * 65536];
    let e = fd::FeatureStats::from_rows(&rows, 65536, "a.npy").unwrap_err();
    let msg = e.to_string();
    assert!(matches!(e, Error::ShapeMismatch { .. }), "{msg}");
    assert!(
        msg.contains("a.npy") && msg.contains("65536") && msg.contains("4096"),
        "{msg}"
    );
    let e = fd::frechet_distance_rows(&rows, &rows, 65536, fd::SqrtMethod::Eigen).unwrap_err();
    assert!(e.to_string().contains("at most 4096"), "{e}");
    // the limit itself is accepted
    assert!(fd::FeatureStats::try_new(fd::MAX_FEATURE_DIM, "x").is_ok());
}

#[test]
fn newton_schulz_needs_at_least_one_iteration() {
    let mut rng = ChaCha8Rng::seed_from_u64(47);
    let a: Vec<f64> = (0..200).map(|_| rng.random_range(-1.0..1.0)).collect();
    let b: Vec<f64> = (0..200).map(|_| rng.random_range(-1.0..2.0)).collect();
    for iterations in [0, fd::SqrtMethod::MAX_ITERATIONS + 1] {
        let e = fd::frechet_distance_rows(&a, &b, 4, fd::SqrtMethod::NewtonSchulz { iterations })
            .unwrap_err();
        assert!(
            matches!(e, Error::InvalidParameter { .. })
                && e.to_string().contains("between 1 and 1000"),
            "{e}"
        );
    }
    // converged, it matches the exact method (an independent computation of the trace term)
    let exact = fd::frechet_distance_rows(&a, &b, 4, fd::SqrtMethod::Eigen).unwrap();
    let ns = fd::frechet_distance_rows(&a, &b, 4, fd::SqrtMethod::NewtonSchulz { iterations: 60 })
        .unwrap();
    assert!(
        (exact - ns).abs() < 1e-8 * exact.max(1.0),
        "{exact} vs {ns}"
    );
}

#[test]
fn a_scan_too_big_for_an_index_is_refused_naming_it() {
    let n = nn_limit() + 1;
    let pts = vec![Vec3::new(1.0, 2.0, 3.0); n];
    let e = PointIndex::build(&pts, "generated scan 3").unwrap_err();
    let msg = e.to_string();
    assert!(
        msg.contains("generated scan 3") && msg.contains(&n.to_string()),
        "{msg}"
    );
}

fn nn_limit() -> usize {
    veila_metrics::nn::MAX_INDEX_POINTS
}

#[test]
fn cm_sc_refuses_raw_ids_where_train_ids_are_expected() {
    // train ids pass
    crossmodal::check_train_ids(&[0, 1, 9, 19], "m.png").unwrap();
    // simulate's raw ids (40 road, 50 building, 70 vegetation): refused, named as raw ids
    let e = crossmodal::check_train_ids(&[0, 40, 40, 50, 70], "m.png").unwrap_err();
    let msg = e.to_string();
    assert!(
        matches!(
            e,
            Error::LabelSpace {
                label: 40,
                index: 1,
                ..
            }
        ),
        "{msg}"
    );
    assert!(msg.contains("m.png") && msg.contains("raw id"), "{msg}");
    // values that are neither: refused without the raw-id hint
    let msg = crossmodal::check_train_ids(&[3, 200], "m.png")
        .unwrap_err()
        .to_string();
    assert!(msg.contains("200") && !msg.contains("raw id"), "{msg}");
}

/// Many coincident points: a query at the same distance from every one of them (two sets of
/// duplicates) once visited every node of the tree, so Chamfer on two such scans was quadratic.
#[test]
fn chamfer_on_large_sets_of_coincident_points_prunes_the_tree() {
    let n = 200_000;
    let p = Vec3::new(10.0, -3.0, 1.5);
    let q = Vec3::new(11.0, -3.0, 1.5);
    let a = vec![p; n];
    let b = vec![q; n];
    let index = PointIndex::build(&a, "a").unwrap();
    // a query off the duplicates, and one on them: a handful of nodes, not the whole tree
    for query in [q, p] {
        let visited = index.nodes_visited(query);
        assert!(
            visited <= 256,
            "{visited} nodes visited for {query} among {n} coincident points"
        );
    }
    let identical = veila_metrics::chamfer::chamfer_distance(&a, &a).unwrap();
    assert_eq!(identical.value(), 0.0);
    let apart = veila_metrics::chamfer::chamfer_distance(&a, &b).unwrap();
    assert_eq!((apart.a_to_b, apart.b_to_a), (1.0, 1.0));
}
