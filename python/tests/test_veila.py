"""pytest suite of the `veila` wheel, against the same reference values as the Rust tests:

- ``veila-metrics/tests/data/golden.json`` (numpy / scipy, made by ``make_golden.py`` next to it): BEV
  JSD and MMD, Chamfer and Fréchet distances;
- ``veila-metrics/tests/data/peer_protocols.json`` (numpy reproductions of the peers' scripts, made by
  ``peer_protocols.py``): the five peer protocols on peer sample files and on real scans;
- closed forms computed here with numpy (equation 1 of the paper for the projection, files written
  with numpy for the readers, ``P2 R0_rect Tr_velo_to_cam`` for a KITTI calibration).

Checks on real scans skip when ``../shared/data/real`` is absent."""

import json
import os
from pathlib import Path

import numpy as np
import pytest

import veila

REPO = Path(__file__).resolve().parents[2]
DATA = REPO / "veila-metrics" / "tests" / "data"
SAMPLES = DATA / "peer_samples"
REAL = REPO.parent / "shared" / "data" / "real"
REF = json.loads((DATA / "peer_protocols.json").read_text())
GOLDEN = json.loads((DATA / "golden.json").read_text())

needs_real = pytest.mark.skipif(not REAL.is_dir(), reason=f"{REAL} is absent")


def rel(got, want):
    return abs(got - want) / max(abs(want), 1e-300)


def xyz(rel_path):
    return veila.read_points(REAL / rel_path, keep_nan_intensity=True)[0]


# ------------------------------------------------------------------ metrics (golden.json, numpy/scipy)


def golden_scans(key):
    return [np.array(s, dtype=np.float32) for s in GOLDEN["bev"][key]]


@pytest.mark.parametrize("region", ["all", "front", "rear"])
def test_bev_jsd_and_mmd_match_numpy_scipy(region):
    want = GOLDEN["bev"]["regions"][region]
    gen, ref = golden_scans("generated"), golden_scans("reference")
    assert rel(veila.jsd_raw(gen, ref, region=region), want["jsd"]) <= 1e-12
    assert rel(veila.mmd_raw(gen, ref, region=region), want["mmd_r2dm"]) <= 1e-9
    # float64 input gives the same numbers (converted to float32 points, as the Rust test does)
    gen64 = [g.astype(np.float64) for g in gen]
    assert veila.jsd_raw(gen64, ref, region=region) == veila.jsd_raw(gen, ref, region=region)


def test_chamfer_matches_scipy_ckdtree():
    c = GOLDEN["chamfer"]
    a, b = np.array(c["a"], np.float32), np.array(c["b"], np.float32)
    assert rel(veila.chamfer_distance(a, b), c["value"]) <= 1e-12
    # a closed form: two points 1 m apart, each squared nearest distance 1, both ways
    assert veila.chamfer_distance(np.array([[0.0, 0, 0]]), np.array([[1.0, 0, 0]])) == pytest.approx(2.0)


@pytest.mark.parametrize("case", GOLDEN["frechet"], ids=[c["name"] for c in GOLDEN["frechet"]])
def test_frechet_matches_mpmath_and_numpy(case):
    d = case["dim"]
    a = np.array(case["a"], np.float64).reshape(-1, d)
    b = np.array(case["b"], np.float64).reshape(-1, d)
    got = veila.frechet_distance(a, b)
    assert rel(got, case["fd_mp"]) <= 1e-11
    assert rel(got, case["fd_eigh"]) <= 1e-7


def test_frechet_newton_schulz_converges_or_says_it_diverged():
    rng = np.random.default_rng(0)
    a, b = rng.normal(size=(400, 4)), rng.normal(1.0, 1.0, size=(300, 4))
    assert veila.frechet_distance(a, b, newton_schulz=50) == pytest.approx(veila.frechet_distance(a, b), rel=1e-8)
    few_a, few_b = rng.normal(size=(5, 16)), rng.normal(size=(5, 16))
    with pytest.raises(ValueError, match="Newton–Schulz diverged"):
        veila.frechet_distance(few_a, few_b, newton_schulz=100)


# ------------------------------------------------------- peer protocols (peer_protocols.json, numpy)


@pytest.mark.parametrize("key", sorted(REF["samples"]))
def test_peer_sample_files_give_the_numpy_points(key):
    want = REF["samples"][key]
    arrays = veila.read_sample_arrays(SAMPLES / key.split(" ")[0])
    samples = [s for a in arrays.values() for s in veila.points_from_image(a, want["protocol"])]
    assert len(samples) >= len(want["generated_points"])
    for got, w in zip(samples, want["generated_points"]):
        assert got.shape == (w["points"], 3)
        tol = 1e-3 * max(len(got), 1)
        assert abs(got[:, 0].sum() - w["sum_x"]) <= tol
        assert abs(got[:, 1].sum() - w["sum_y"]) <= tol


@needs_real
@pytest.mark.parametrize("key", sorted(REF["samples"]))
def test_peer_sample_files_score_the_numpy_numbers(key):
    want = REF["samples"][key]
    arrays = veila.read_sample_arrays(SAMPLES / key.split(" ")[0])
    ref = [xyz(p) for p in REF["samples_reference"]]
    got = veila.score(list(arrays.values()), ref, protocol=want["protocol"], generated_images=True)
    assert rel(got["jsd"], want["jsd"]) <= 1e-4
    assert rel(got["mmd"], want["mmd"]) <= 1e-4


@needs_real
@pytest.mark.parametrize("set_name", ["kitti", "nuscenes"])
@pytest.mark.parametrize("protocol", veila.PROTOCOLS)
def test_protocols_give_the_peer_numbers_from_raw_scans(set_name, protocol):
    s = REF["sets"][set_name]
    gen = [xyz(p) for p in s["generated"]]
    ref = [xyz(p) for p in s["reference"]]
    want = REF["raw"][set_name][protocol]
    got = veila.score(gen, ref, protocol=protocol)
    assert rel(got["jsd"], want["jsd"]) <= 1e-4
    assert rel(got["mmd"], want["mmd"]) <= 1e-4
    for g, w in zip(gen, want["generated_points"]):
        p = veila.prepare_scan(g, protocol)
        assert len(p) == w["points"]
        assert abs(p[:, 0].sum() - w["sum_x"]) <= 1e-3 * len(p)


def test_metric_input_errors_are_value_errors():
    a = np.zeros((4, 3))
    with pytest.raises(ValueError, match="unknown protocol"):
        veila.score([a], [a], protocol="r3dm")
    with pytest.raises(ValueError, match="unknown region"):
        veila.jsd_raw([a], [a], region="left")
    with pytest.raises(ValueError, match=r"generated\[0\]"):
        veila.score([np.zeros((4, 2))], [a])
    with pytest.raises(ValueError, match="generated is empty"):
        veila.score([], [a])
    with pytest.raises(ValueError):
        veila.prepare_scan(np.array([[np.nan, 0.0, 0.0]]))
    with pytest.raises(ValueError, match="columns"):
        veila.frechet_distance(np.zeros((3, 2)), np.zeros((3, 4)))


# ------------------------------------------------------------ projection (equation 1, numpy)


def test_project_puts_each_point_in_the_pixel_of_equation_1():
    rows, cols, up, down = 64, 1024, np.radians(3.0), np.radians(-25.0)
    rng = np.random.default_rng(7)
    n = 3000
    r = rng.uniform(2.0, 100.0, n)
    az = rng.uniform(-np.pi, np.pi, n)
    el = rng.uniform(down + 1e-3, up - 1e-3, n)
    pts = np.stack([r * np.cos(el) * np.cos(az), r * np.cos(el) * np.sin(az), r * np.sin(el)], 1)
    pts = pts.astype(np.float32)
    p = pts.astype(np.float64)
    d = np.linalg.norm(p, axis=1)
    u = 0.5 * (1 - np.arctan2(p[:, 1], p[:, 0]) / np.pi) * cols
    v = (1 - (np.arcsin(p[:, 2] / d) - down) / (up - down)) * rows
    # away from pixel boundaries (the Rust side's exact tests handle those), one point per pixel
    clear = (np.abs(u - np.round(u)) > 1e-3) & (np.abs(v - np.round(v)) > 1e-3)
    pix = np.floor(v).astype(int) * cols + np.floor(u).astype(int) % cols
    _, first, count = np.unique(pix, return_index=True, return_counts=True)
    keep = np.zeros(n, bool)
    keep[first[count == 1]] = True
    keep &= clear
    pts, pix, d = pts[keep], pix[keep], d[keep]
    intensity = np.linspace(0.0, 1.0, len(pts), dtype=np.float32)

    img = veila.project(pts, intensity=intensity, sensor="hdl64e")
    assert img["range"].shape == (rows, cols) and img["mask"].dtype == np.bool_
    assert img["mask"].sum() == len(pts)
    np.testing.assert_array_equal(np.flatnonzero(img["mask"]), np.sort(pix))
    np.testing.assert_allclose(img["range"].ravel()[pix], d, rtol=1e-6)
    np.testing.assert_array_equal(img["intensity"].ravel()[pix], intensity)

    # unprojection: same ranges, direction within the pixel's angular size, intensities carried
    back, back_i = veila.unproject(img["range"], img["intensity"], sensor="hdl64e")
    order = np.argsort(pix)
    np.testing.assert_allclose(np.linalg.norm(back, axis=1), d[order], rtol=1e-5)
    cos = np.sum(back * pts[order], axis=1) / (np.linalg.norm(back, axis=1) * d[order])
    pixel_diag = np.hypot(2 * np.pi / cols, (up - down) / rows)
    assert np.all(np.arccos(np.clip(cos, -1, 1)) <= pixel_diag)
    np.testing.assert_array_equal(back_i, intensity[order])


def test_project_drops_out_of_view_and_checks_its_input():
    pts = np.array([[10.0, 0.0, 9.0], [10.0, 0.0, -1.0]])  # 42 deg up: outside the HDL-64E's view
    assert veila.project(pts)["mask"].sum() == 1
    assert veila.project(pts, sensor="hdl32e", rows=16, cols=256)["range"].shape == (16, 256)
    with pytest.raises(ValueError, match="unknown sensor"):
        veila.project(pts, sensor="vlp16")
    with pytest.raises(ValueError, match="shape"):
        veila.project(np.zeros((3, 2)))
    with pytest.raises(ValueError, match="intensity"):
        veila.unproject(np.ones((64, 1024), np.float32), np.ones((64, 8), np.float32))


@pytest.mark.parametrize("preset", veila.SENSOR_PRESETS)
def test_every_sensor_preset_projects_and_unprojects(preset):
    # the wheel's presets are the library's list, each one a sensor (hdl32e-per-beam included)
    # ring 18 of the HDL-32E looks 6.7 deg down; the uniform presets ignore rings
    img = veila.project(np.array([[10.0, 0.0, -1.0]]), sensor=preset, rings=[18])
    assert img["mask"].sum() == 1
    back, _ = veila.unproject(img["range"], sensor=preset)
    assert back.shape == (1, 3)


# -------------------------------------------------------------------- readers (files written by numpy)


def test_read_points_reads_a_kitti_bin_written_by_numpy(tmp_path):
    rng = np.random.default_rng(3)
    rec = rng.normal(0, 20, size=(500, 4)).astype(np.float32)
    rec[:, 3] = rng.uniform(0, 1, 500)
    rec[7, 3] = np.nan  # intensity alone NaN
    rec[9, 0] = np.inf  # coordinate non-finite: always dropped
    f = tmp_path / "000000.bin"
    rec.tofile(f)
    xyz_all, i_all = veila.read_points(f, keep_nan_intensity=True)
    finite = np.isfinite(rec[:, :3]).all(1)
    np.testing.assert_array_equal(xyz_all, rec[finite, :3])
    np.testing.assert_array_equal(i_all, rec[finite, 3])
    xyz_fin, _ = veila.read_points(str(f))
    np.testing.assert_array_equal(xyz_fin, rec[finite & np.isfinite(rec[:, 3]), :3])


def test_reader_errors_name_the_file(tmp_path):
    bad = tmp_path / "truncated.bin"
    np.zeros(10, np.float32).tofile(bad)  # 40 bytes: not a whole number of 16-byte records
    with pytest.raises(ValueError, match="truncated.bin"):
        veila.read_points(bad)
    with pytest.raises(ValueError, match="missing.bin"):
        veila.read_points(tmp_path / "missing.bin")
    with pytest.raises(ValueError, match="never loads pickles"):
        veila.read_sample_arrays(SAMPLES / "pickled.npy")
    calib = tmp_path / "calib.txt"
    calib.write_text("P0: 1 2 3\n")
    with pytest.raises(ValueError, match="calib.txt"):
        veila.read_calibration(calib, 1242, 375)
    assert bad.stat().st_size == 40  # inputs never written


def test_read_sample_arrays_reads_npy_and_npz_written_by_numpy(tmp_path):
    rng = np.random.default_rng(5)
    a = rng.uniform(0, 1, size=(2, 1, 8, 16)).astype(np.float32)
    b = rng.uniform(0, 80, size=(8, 16))
    np.save(tmp_path / "a.npy", a)
    np.savez_compressed(tmp_path / "s.npz", first=a, second=b)
    (got,) = veila.read_sample_arrays(tmp_path / "a.npy").values()
    np.testing.assert_array_equal(got, a)
    got = veila.read_sample_arrays(tmp_path / "s.npz")
    assert sorted(got) == ["first", "second"]
    np.testing.assert_array_equal(got["first"], a)
    np.testing.assert_allclose(got["second"], b.astype(np.float32))


def kitti_calib(tmp_path):
    rng = np.random.default_rng(11)
    p2 = np.array([[721.5, 0, 609.6, 44.9], [0, 721.5, 172.9, 0.2], [0, 0, 1, 0.003]])
    # a small rotation (Rodrigues): the reader refuses an R0_rect that is not rigid
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    kx = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    angle = 0.01
    r0 = np.eye(3) + np.sin(angle) * kx + (1 - np.cos(angle)) * kx @ kx
    tr = np.array([[0.0, -1, 0, -0.004], [0, 0, -1, -0.076], [1, 0, 0, -0.27]])
    text = "".join(
        f"{k}: " + " ".join(f"{x:.12e}" for x in m.ravel()) + "\n"
        for k, m in [("P0", p2), ("P1", p2), ("P2", p2), ("P3", p2), ("R0_rect", r0), ("Tr_velo_to_cam", tr), ("Tr_imu_to_velo", tr)]
    )
    f = tmp_path / "calib.txt"
    f.write_text(text)
    r0_4, tr_4 = np.eye(4), np.eye(4)
    r0_4[:3, :3], tr_4[:3] = r0, tr
    return f, p2 @ r0_4 @ tr_4


def test_read_calibration_projects_like_p2_r0_tr(tmp_path):
    f, want = kitti_calib(tmp_path)
    k, t = veila.read_calibration(f, 1242, 375)
    assert k.shape == (3, 4) and t.shape == (4, 4)
    got = k.astype(np.float64) @ t.astype(np.float64)
    pts = np.array([[10.0, 2.0, -1.0, 1], [30.0, -5.0, 0.5, 1], [6.0, 0.0, 0.0, 1]]).T
    a, b = got @ pts, want @ pts
    np.testing.assert_allclose(a[:2] / a[2], b[:2] / b[2], atol=1e-2)  # pixels


# ---------------------------------------------------------------------------------- generation


def veila_bundle_kind():
    """``"residual"``, ``"prior"`` or ``"direct"``: the kind of the source tree's models/default."""
    cfg = json.loads((Path(__file__).resolve().parents[2] / "models" / "default" / "bundle.json").read_text())
    return "residual" if cfg.get("residual") else "prior" if cfg.get("prior") else "direct"


def kitti_camera(width, height):
    s = width / 1242.0
    k = np.array([[721.5 * s, 0, 609.6 * s], [0, 721.5 * s, 172.9 * s], [0, 0, 1]], np.float32)
    t = np.array([[0, -1, 0, 0], [0, 0, -1, -0.08], [1, 0, 0, -0.27], [0, 0, 0, 1]], np.float32)
    return k, t


def test_generate_is_deterministic_follows_the_seed_and_is_consistent():
    k, t = kitti_camera(414, 125)
    image = np.random.default_rng(1).integers(0, 256, size=(125, 414, 3), dtype=np.uint8)
    a = veila.generate(image, k, t, steps=2, seed=3)
    b = veila.generate(image, k, t, steps=2, seed=3)
    c = veila.generate(image, k, t, steps=2, seed=4)
    # the sampler keywords reach the sampler
    assert not np.array_equal(a["range"], veila.generate(image, k, t, steps=2, seed=3, sampler="ddim")["range"])
    assert not np.array_equal(a["range"], veila.generate(image, k, t, steps=2, seed=3, guidance=2.0)["range"])
    assert a["points"].shape[1] == 3 and len(a["points"]) == len(a["intensity"]) == a["mask"].sum() > 0
    np.testing.assert_array_equal(a["range"], b["range"])
    assert not np.array_equal(a["range"], c["range"])
    # the points are the unprojection of the range image
    np.testing.assert_allclose(np.sort(np.linalg.norm(a["points"], axis=1)), np.sort(a["range"][a["mask"]]), rtol=1e-5)


def test_generate_checks_its_input(tmp_path):
    k, t = kitti_camera(414, 125)
    image = np.zeros((125, 414, 3), np.uint8)
    with pytest.raises(ValueError, match="cam_from_lidar"):
        veila.generate(image, k, t[:3], steps=2)
    with pytest.raises(ValueError, match="intrinsics"):
        veila.generate(image, k[:2], t, steps=2)
    with pytest.raises(ValueError, match="image"):
        veila.generate(np.zeros((125, 414, 4), np.uint8), k, t, steps=2)
    with pytest.raises(ValueError, match="steps"):
        veila.generate(image, k, t, steps=0)
    with pytest.raises(ValueError, match="sampler"):
        veila.generate(image, k, t, steps=2, sampler="euler")
    with pytest.raises(ValueError, match="guidance"):
        veila.generate(image, k, t, steps=2, guidance=25.0)
    # a start level needs a bundle with a prior mean network; the bundled model's is a residual's
    if veila_bundle_kind() == "residual":
        with pytest.raises(ValueError, match="prior"):
            veila.generate(image, k, t, steps=2, start_t=0.5)
    with pytest.raises(ValueError, match="no-model"):
        veila.generate(image, k, t, steps=2, model_dir=tmp_path / "no-model")
    # implausible calibrations are refused before the model is loaded, saying what is wrong
    bad = k.copy()
    bad[0, 0] = -bad[0, 0]
    with pytest.raises(ValueError, match="focal lengths"):
        veila.generate(image, bad, t, steps=2, model_dir=tmp_path / "no-model")
    bad = k.copy()
    bad[0, 2] = 1e7
    with pytest.raises(ValueError, match="principal point"):
        veila.generate(image, bad, t, steps=2, model_dir=tmp_path / "no-model")
    far = t.copy()
    far[0, 3] = 1e30
    with pytest.raises(ValueError, match="translation"):
        veila.generate(image, k, far, steps=2, model_dir=tmp_path / "no-model")


def test_import_turns_candles_spinning_pool_off_unless_the_user_chose():
    # a fresh interpreter: the import sets CANDLE_NUM_THREADS=1 where it is unset, and keeps a
    # user's own value
    import subprocess
    import sys

    code = "import os, veila; print(os.environ['CANDLE_NUM_THREADS'])"
    env = {k: v for k, v in os.environ.items() if k != "CANDLE_NUM_THREADS"}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "1"
    env["CANDLE_NUM_THREADS"] = "3"
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True)
    assert out.stdout.strip() == "3"
