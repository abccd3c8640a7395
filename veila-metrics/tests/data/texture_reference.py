#!/usr/bin/env python3
"""Reference values for `veila_metrics::texture`, written independently in numpy / scipy.

    python3 -m venv /tmp/vv && /tmp/vv/bin/pip install "numpy==1.26.4" "scipy==1.11.4"
    /tmp/vv/bin/python veila-metrics/tests/data/texture_reference.py

Writes texture_reference.json next to this script: the inputs (seeded, generated here) and every value the
Rust test `tests/it/texture.rs` compares. Run by hand; the Rust tests read the JSON.

Definitions (those of the module's docs):
* valid pixel: mask & isfinite(r) & (r > 0); a pair counts when both pixels are valid and in the region;
* along-row pairs (r, c)-(r, (c+1) % cols); across-row pairs (r, c)-(r+1, c); a band keeps a pair when
  both rows are in it (upper = rows 0..rows//2, lower = rows//2..rows);
* s = |r1 - r2| / min(r1, r2) in float64; histogram: [s < 1e-6] + numpy.histogram(log10 s, 32 bins of
  0.25 decade over [-6, 2]) of the rest below 1e2 + [s >= 1e2]; smooth: s < 3e-4; edge: s > 1;
* W1: scipy.stats.wasserstein_distance of the bin centres weighted by the probabilities; JSD:
  scipy.spatial.distance.jensenshannon of the counts;
* ray drop per row: invalid / total over the region pixels of each row, pooled over the set;
* scan distance: mean over all pixels of |e_a - e_b|, e = log2(1 + r) where valid, else 0.
"""
import json
from pathlib import Path

import numpy as np
import scipy
from scipy.spatial.distance import jensenshannon
from scipy.stats import wasserstein_distance

HERE = Path(__file__).resolve().parent
ROWS, COLS = 4, 16
NBINS = 34
CENTRES = -6.125 + 0.25 * np.arange(NBINS)
EDGES = np.linspace(-6.0, 2.0, 33)
rng = np.random.default_rng(20240611)


def f32(x):
    return np.float32(x)


def image_a():
    base = rng.uniform(5.0, 40.0, size=(ROWS, 1))
    r = (base * (1.0 + 1e-3 * rng.standard_normal((ROWS, COLS)))).astype(np.float32)
    m = np.ones((ROWS, COLS), dtype=bool)
    r[0, 2] = r[0, 3]  # exact tie: s = 0
    r[0, 8] = f32(8.0)  # a few ulps apart: s ~ 1.2e-6 and ~ 2.4e-7
    r[0, 9] = np.nextafter(np.nextafter(f32(8.0), f32(9.0)), f32(9.0))
    for _ in range(8):
        r[0, 9] = np.nextafter(r[0, 9], f32(9.0))
    r[0, 10] = np.nextafter(r[0, 9], f32(9.0))
    # steps near 3e-4 on both sides of the threshold
    r[1, 3] = f32(10.0)
    r[1, 4] = f32(10.0 * (1 + 3e-4) + 2e-6)
    r[1, 5] = f32(r[1, 4] * (1 + 3e-4) - 4e-6)
    r[1, 6] = f32(r[1, 5] * (1 + 3e-4))
    r[1, 10] = 0.0  # zero range with the mask set: invalid
    r[1, 12] = f32(5.0)  # s = 1 exactly: not an edge
    r[1, 13] = f32(10.0)
    r[2, 3] = np.nan  # NaN with the mask set: invalid
    r[2, 9] = np.inf  # infinity with the mask set: invalid
    r[2, 15] = f32(3.0)  # wrap-around depth edge to column 0 (s = 9)
    r[2, 0] = f32(30.0)
    r[3, 0] = f32(12.0)
    m[3, 0] = False  # mask off with a positive range: invalid
    r[3, 7] = f32(0.4)  # huge jump: s = 374, overflow
    r[3, 8] = f32(150.0)
    r[3, 11] = f32(-2.0)  # negative range: invalid
    return r, m


def image_b():
    base = rng.uniform(5.0, 40.0, size=(ROWS, 1))
    r = (base * (1.0 + 1e-2 * rng.standard_normal((ROWS, COLS)))).astype(np.float32)
    m = rng.uniform(size=(ROWS, COLS)) > 0.2
    r[~m] = 0.0
    r[0, 5] = f32(2.0)  # edges of s ~ 1..20
    r[1, 1] = f32(60.0)
    r[3, 14] = r[3, 15]  # tie
    return r, m


A = image_a()
B = image_b()


def valid(img):
    r, m = img
    with np.errstate(invalid="ignore"):
        return m & np.isfinite(r) & (r > 0)


def band_rows(band):
    return {"all": (0, ROWS), "upper": (0, ROWS // 2), "lower": (ROWS // 2, ROWS)}[band]


def steps(img, region, direction, band):
    r = img[0].astype(np.float64)
    u = valid(img) & (np.ones_like(img[1]) if region is None else region)
    lo, hi = band_rows(band)
    if direction == "along_row":
        a, b = r[lo:hi], np.roll(r, -1, axis=1)[lo:hi]
        ok = u[lo:hi] & np.roll(u, -1, axis=1)[lo:hi]
    else:
        a, b = r[lo : hi - 1], r[lo + 1 : hi]
        ok = u[lo : hi - 1] & u[lo + 1 : hi]
    a, b = a[ok], b[ok]
    return np.abs(a - b) / np.minimum(a, b)


def histogram(s):
    under = s < 1e-6
    over = s >= 1e2
    mid = s[~under & ~over]
    counts = np.concatenate([[under.sum()], np.histogram(np.log10(mid), bins=EDGES)[0], [over.sum()]])
    assert counts.sum() == s.size
    return {
        "counts": [int(c) for c in counts],
        "smooth": int((s < 3e-4).sum()),
        "edge": int((s > 1.0).sum()),
    }


def num(x):
    x = float(x)
    return None if np.isnan(x) else x


def w1(ha, hb):
    ca, cb = np.array(ha["counts"], float), np.array(hb["counts"], float)
    if ca.sum() == 0 or cb.sum() == 0:
        return None
    return float(wasserstein_distance(CENTRES, CENTRES, ca / ca.sum(), cb / cb.sum()))


def jsd(ha, hb):
    ca, cb = np.array(ha["counts"], float), np.array(hb["counts"], float)
    if ca.sum() == 0 or cb.sum() == 0:
        return None
    return float(jensenshannon(ca, cb))


def raydrop(imgs, region):
    reg = np.ones((ROWS, COLS), bool) if region is None else region
    inv = sum(((~valid(i)) & reg).sum(axis=1) for i in imgs)
    tot = reg.sum(axis=1) * len(imgs)
    with np.errstate(invalid="ignore", divide="ignore"):
        return inv / tot


def encode(img):
    r = np.where(valid(img), img[0].astype(np.float64), 0.0)
    return np.where(valid(img), np.log2(1.0 + r), 0.0)


def scan_distance(a, b):
    return float(np.mean(np.abs(encode(a) - encode(b))))


def image_json(img):
    r, m = img
    enc = []
    for x in r.ravel():
        x = float(x)
        enc.append("nan" if np.isnan(x) else ("inf" if np.isinf(x) else x))
    return {"rows": ROWS, "cols": COLS, "range_m": enc, "mask": [bool(v) for v in m.ravel()]}


camera = np.zeros((ROWS, COLS), bool)
camera[: ROWS - 1, 3:13] = True  # row 3 lies wholly outside: its ray drop is NaN
wrap = np.zeros((ROWS, COLS), bool)
wrap[:, [14, 15, 0, 1]] = True
REGIONS = {"none": None, "camera": camera, "wrap": wrap}

out = {
    "generator": f"texture_reference.py, numpy {np.__version__}, scipy {scipy.__version__}",
    "images": {"a": image_json(A), "b": image_json(B)},
    "regions": {k: (None if v is None else [bool(x) for x in v.ravel()]) for k, v in REGIONS.items()},
    "histograms": {},
    "raydrop": {},
    "diversity": {},
}

all_s = np.concatenate([steps(A, None, "along_row", "all"), steps(A, None, "across_rows", "all")])
assert (np.abs(all_s - 3e-4) < 3e-6).sum() >= 2 and (all_s < 3e-4).any()
assert ((all_s > 3e-4) & (all_s < 3.1e-4)).any() and ((all_s < 3e-4) & (all_s > 2.9e-4)).any()
assert (all_s == 0).any() and (all_s == 1.0).any() and (all_s >= 100).any()
assert ((all_s > 1e-6) & (all_s < 1e-5)).any()

for rname, reg in REGIONS.items():
    for d in ["along_row", "across_rows"]:
        for band in ["all", "upper", "lower"]:
            ha = histogram(steps(A, reg, d, band))
            hb = histogram(steps(B, reg, d, band))
            pooled = histogram(np.concatenate([steps(A, reg, d, band), steps(B, reg, d, band)]))
            out["histograms"][f"{rname}/{d}/{band}"] = {
                "a": ha,
                "b": hb,
                "pooled": pooled,
                "a_smooth_share": num(ha["smooth"] / sum(ha["counts"])) if sum(ha["counts"]) else None,
                "a_edge_share": num(ha["edge"] / sum(ha["counts"])) if sum(ha["counts"]) else None,
                "w1": w1(ha, hb),
                "jsd": jsd(ha, hb),
            }
    pa, pb = raydrop([A], reg), raydrop([B], reg)
    both = np.isfinite(pa) & np.isfinite(pb)
    out["raydrop"][rname] = {
        "a": [num(x) for x in pa],
        "b": [num(x) for x in pb],
        "pooled": [num(x) for x in raydrop([A, B], reg)],
        "distance": num(np.mean(np.abs(pa[both] - pb[both]))) if both.any() else None,
    }
    vr = valid(A) & valid(B) & (np.ones((ROWS, COLS), bool) if reg is None else reg)
    ra, rb = A[0].astype(np.float64), B[0].astype(np.float64)
    rr = np.ones((ROWS, COLS), bool) if reg is None else reg
    out["diversity"][rname] = {
        "range_mae": num(np.mean(np.abs(ra[vr] - rb[vr]))) if vr.any() else None,
        "drop_disagreement": num(np.mean((valid(A) != valid(B))[rr])),
    }

# memorisation: a pool with a near copy of A twice (an exact tie: the lower index wins)
near = (A[0].copy(), A[1].copy())
near[0][1, 1] = f32(near[0][1, 1] * 1.01)
near[1][2, 5] = False
far1 = (np.full((ROWS, COLS), f32(20.0)), np.ones((ROWS, COLS), bool))
far2 = (np.full((ROWS, COLS), f32(0.0)), np.zeros((ROWS, COLS), bool))
pool = [B, far1, near, far2, (near[0].copy(), near[1].copy())]
queries = {"a": A, "b": B}
out["nearest"] = {"pool": [image_json(p) for p in pool], "queries": {}}
for qname, q in queries.items():
    d = np.array([scan_distance(q, p) for p in pool])
    out["nearest"]["queries"][qname] = {"distances": [float(x) for x in d], "index": int(np.argmin(d)),
                                        "distance": float(d.min())}
assert out["nearest"]["queries"]["a"]["index"] == 2
assert out["nearest"]["queries"]["a"]["distances"][2] == out["nearest"]["queries"]["a"]["distances"][4]

(HERE / "texture_reference.json").write_text(json.dumps(out, indent=1, allow_nan=False) + "\n")
print("wrote", HERE / "texture_reference.json")
