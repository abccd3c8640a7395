"""pytest suite of the `veila` wheel: the same reference values as the Rust tests
(veila-metrics/tests/data/peer_protocols.json, made by peer_protocols.py from numpy reproductions of the
peers' scripts). Real-scan checks skip when ../shared/data/real is absent."""

import json
from pathlib import Path

import numpy as np
import pytest

import veila

REPO = Path(__file__).resolve().parents[2]
DATA = REPO / "veila-metrics" / "tests" / "data"
REAL = REPO.parent / "shared" / "data" / "real"
REF = json.loads((DATA / "peer_protocols.json").read_text())

needs_real = pytest.mark.skipif(not REAL.is_dir(), reason=f"{REAL} is absent")


def xyz(rel):
    return veila.read_points(REAL / rel, keep_nan_intensity=True)[0]


def close(got, want, tol=1e-4):
    assert abs(got - want) <= tol * abs(want), (got, want)


@needs_real
@pytest.mark.parametrize("set_name", ["kitti", "nuscenes"])
@pytest.mark.parametrize("protocol", veila.PROTOCOLS)
def test_protocols_give_the_peer_numbers_from_raw_scans(set_name, protocol):
    s = REF["sets"][set_name]
    gen = [xyz(p) for p in s["generated"]]
    ref = [xyz(p) for p in s["reference"]]
    got = veila.score(gen, ref, protocol=protocol)
    want = REF["raw"][set_name][protocol]
    close(got["jsd"], want["jsd"])
    close(got["mmd"], want["mmd"])
    # the prepared points themselves: same count as numpy
    assert [len(veila.prepare_scan(g, protocol)) for g in gen] == [
        p["points"] for p in want["generated_points"]
    ]


@needs_real
@pytest.mark.parametrize("key", sorted(REF["samples"]))
def test_peer_sample_files(key):
    want = REF["samples"][key]
    arrays = veila.read_sample_arrays(DATA / "peer_samples" / key.split(" ")[0])
    ref = [xyz(p) for p in REF["samples_reference"]]
    got = veila.score(list(arrays.values()), ref, protocol=want["protocol"], generated_images=True)
    close(got["jsd"], want["jsd"])
    close(got["mmd"], want["mmd"])


def test_pickles_are_refused():
    with pytest.raises(ValueError, match="never loads pickles"):
        veila.read_sample_arrays(DATA / "peer_samples" / "pickled.npy")


def test_raw_metrics_and_a_closed_form():
    a = np.array([[10.0, 5.0, -1.0], [-20.0, 3.0, 0.5]])
    assert veila.jsd_raw([a], [a]) == 0.0
    assert veila.mmd_raw([a], [a]) == 0.0
    # two points 1 m apart on x: each nearest squared distance is 1, both ways -> 2
    assert veila.chamfer_distance(np.array([[0.0, 0, 0]]), np.array([[1.0, 0, 0]])) == pytest.approx(2.0)


def test_frechet_distance_and_newton_schulz_divergence():
    rng = np.random.default_rng(0)
    a, b = rng.normal(size=(400, 4)), rng.normal(1.0, 1.0, size=(300, 4))
    ma, mb = a.mean(0), b.mean(0)
    ca, cb = np.cov(a, rowvar=False), np.cov(b, rowvar=False)
    w, v = np.linalg.eigh(ca)
    sa = v @ np.diag(np.sqrt(w)) @ v.T
    tr = np.sqrt(np.clip(np.linalg.eigvalsh(sa @ cb @ sa), 0, None)).sum()
    want = ((ma - mb) ** 2).sum() + np.trace(ca) + np.trace(cb) - 2 * tr
    assert veila.frechet_distance(a, b) == pytest.approx(want, rel=1e-10)
    few_a, few_b = rng.normal(size=(5, 16)), rng.normal(size=(5, 16))
    with pytest.raises(ValueError, match="Newton–Schulz diverged"):
        veila.frechet_distance(few_a, few_b, newton_schulz=100)


def test_project_unproject_round_trip():
    pts = np.array([[10.0, 0.0, -1.0], [0.0, 20.0, -1.5], [-15.0, -5.0, 0.2]], dtype=np.float32)
    img = veila.project(pts, sensor="hdl64e")
    assert img["mask"].sum() == 3
    back, _ = veila.unproject(img["range"], sensor="hdl64e")
    assert back.shape == (3, 3)
    # same ranges; directions within the pixel's angular size
    r_in = np.sort(np.linalg.norm(pts, axis=1))
    r_out = np.sort(np.linalg.norm(back, axis=1))
    np.testing.assert_allclose(r_out, r_in, rtol=1e-5)


@needs_real
def test_generate_is_deterministic_and_follows_the_seed():
    k, t = veila.read_calibration(REAL / "kitti" / "training" / "calib" / "000001.txt", 1242, 375)
    assert k.shape == (3, 4) and t.shape == (4, 4)
    rng = np.random.default_rng(1)
    image = rng.integers(0, 256, size=(375, 1242, 3), dtype=np.uint8)
    a = veila.generate(image, k, t, steps=2, seed=3)
    b = veila.generate(image, k, t, steps=2, seed=3)
    c = veila.generate(image, k, t, steps=2, seed=4)
    assert a["points"].shape[1] == 3 and len(a["points"]) == a["mask"].sum() > 0
    np.testing.assert_array_equal(a["range"], b["range"])
    assert not np.array_equal(a["range"], c["range"])
    with pytest.raises(ValueError, match="cam_from_lidar"):
        veila.generate(image, k, t[:3], steps=2)
