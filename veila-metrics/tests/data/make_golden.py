#!/usr/bin/env python3
"""Regenerate golden.json for veila-metrics' tests from numpy / scipy.

    pip install numpy scipy
    python3 veila-metrics/tests/data/make_golden.py

Every input is written into the JSON next to the expected values, so the Rust tests do not need to
reproduce the random generator. The reference computations follow the public protocols literally:
numpy.histogramdd for BEV histograms, scipy.spatial.distance.jensenshannon for JSD, explicit
double loops for the R2DM (Frobenius) and LiDARGen (spectral norm) MMDs, LiDM's floor/unique/normalise
recipe with a brute-force 2-D Chamfer, scipy.linalg.sqrtm (and an independent eigh-based value) for the
Frechet distance and scipy.spatial.cKDTree for the Chamfer distance.
"""
import json
import os

import numpy as np
import scipy
import scipy.linalg
from scipy.spatial import cKDTree
from scipy.spatial.distance import jensenshannon

rng = np.random.default_rng(20261121)
out = {"numpy": np.__version__, "scipy": scipy.__version__}


# ---------------------------------------------------------------- BEV scans
def make_scan(n, spread):
    """float32 points: a noisy ring 'scene' plus uniform clutter and a few hand-placed edge cases."""
    r = rng.uniform(1.0, 90.0, n)
    th = rng.uniform(-np.pi, np.pi, n)
    z = rng.normal(-1.0, spread, n)
    pts = np.stack([r * np.cos(th), r * np.sin(th), z], axis=1)
    special = np.array(
        [
            [80.0, 0.0, 0.0],     # beyond 70 m: dropped by the range filter
            [-40.0, 20.0, 0.0],   # exactly on bin edge x = -40 -> bin 25
            [0.0, -40.0, 1.0],    # exactly on edge y = -40, x = 0 -> bins (50, 25)
            [3.0, 0.0, 0.0],      # |p| == 3: dropped (strict)
            [0.0, 0.0, 69.0],     # |p| = 69 but x = y = 0 -> bin (50, 50)
            [-0.0, 5.0, 0.0],     # x = -0.0: rear region
        ]
    )
    return np.concatenate([pts, special]).astype(np.float32)


def bev_hist(pts):
    p = pts.astype(np.float64)
    r = np.linalg.norm(p, axis=1)
    keep = (r > 3.0) & (r < 70.0)
    h, _ = np.histogramdd(p[keep][:, :2], bins=100, range=[[-80, 80], [-80, 80]])
    return h


gen = [make_scan(400, 0.5) for _ in range(3)]
ref = [make_scan(350, 1.0) for _ in range(4)]


def region(pts, name):
    if name == "all":
        return pts
    if name == "front":
        return pts[pts[:, 0] > 0]
    return pts[pts[:, 0] <= 0]


def hist_sparse(h):
    flat = h.reshape(-1)
    nz = np.nonzero(flat)[0]
    return [[int(i), int(flat[i])] for i in nz]


def jsd_sets(g, r):
    hg = sum(bev_hist(s) for s in g)
    hr = sum(bev_hist(s) for s in r)
    return float(jensenshannon((hg / hg.sum()).reshape(-1), (hr / hr.sum()).reshape(-1)))


def mmd(xs, ys, dist, sigma=0.5):
    def k(a, b):
        return np.exp(-dist(a, b) ** 2 / (2 * sigma**2))

    kxx = np.mean([k(a, b) for a in xs for b in xs])
    kyy = np.mean([k(a, b) for a in ys for b in ys])
    kxy = np.mean([k(a, b) for a in xs for b in ys])
    return float(kxx + kyy - 2 * kxy)


def normed(scans):
    hs = [bev_hist(s) for s in scans]
    return [h / h.sum() for h in hs]


def frob(a, b):
    return np.linalg.norm((a - b).reshape(-1))


def spec(a, b):
    return np.linalg.norm(a - b, 2)


# LiDM minimum matching distance (64-beam config)
def lidm_bev(pts, half=50.0, cell=0.5):
    p = pts.astype(np.float64)
    m = (p[:, 0] > -half) & (p[:, 0] < half) & (p[:, 1] > -half) & (p[:, 1] < half)
    v = np.floor(p[m][:, :2] / cell)
    v = np.unique(v, axis=0)
    size = np.ceil(2 * half / cell)
    min_bound = np.ceil(-half / cell)
    return (v - min_bound) / size


def cd2(a, b):
    d = ((a[:, None, :] - b[None, :, :]) ** 2).sum(-1)
    return float((d.min(1).mean() + d.min(0).mean()) / 2)


def mmd_lidm(g, r):
    bg = [lidm_bev(s) for s in g]
    br = [lidm_bev(s) for s in r]
    return float(np.mean([min(cd2(x, y) for y in bg) for x in br]))


bev = {"generated": [s.tolist() for s in gen], "reference": [s.tolist() for s in ref], "regions": {}}
for name in ["all", "front", "rear"]:
    g = [region(s, name) for s in gen]
    r = [region(s, name) for s in ref]
    bev["regions"][name] = {
        "hist_generated": [hist_sparse(bev_hist(s)) for s in g],
        "hist_reference": [hist_sparse(bev_hist(s)) for s in r],
        "jsd": jsd_sets(g, r),
        "mmd_r2dm": mmd(normed(g), normed(r), frob),
        "mmd_lidargen": mmd(normed(g), normed(r), spec),
        "mmd_lidm": mmd_lidm(g, r),
    }
out["bev"] = bev

# JSD of explicit vectors
p = rng.uniform(0, 1, 50)
p[::7] = 0.0
q = rng.uniform(0, 1, 50)
q[::5] = 0.0
out["js_vectors"] = {"p": p.tolist(), "q": q.tolist(), "distance": float(jensenshannon(p, q))}


# ---------------------------------------------------------------- Frechet distance
def fd_sqrtm(a, b):
    mu1, mu2 = a.mean(0), b.mean(0)
    s1, s2 = np.cov(a, rowvar=False), np.cov(b, rowvar=False)
    covmean = scipy.linalg.sqrtm(s1.dot(s2))
    covmean = np.real(covmean)
    return float(((mu1 - mu2) ** 2).sum() + np.trace(s1) + np.trace(s2) - 2 * np.trace(covmean))


def fd_eigh(a, b):
    """Independent exact reference: Tr sqrt(S1^1/2 S2 S1^1/2) through numpy eigh / eigvalsh."""
    mu1, mu2 = a.mean(0), b.mean(0)
    s1, s2 = np.cov(a, rowvar=False), np.cov(b, rowvar=False)
    w, v = np.linalg.eigh(s1)
    r1 = (v * np.sqrt(np.clip(w, 0, None))) @ v.T
    m = r1 @ s2 @ r1
    mu = np.linalg.eigvalsh((m + m.T) / 2)
    tr = np.sqrt(np.clip(mu, 0, None)).sum()
    return float(((mu1 - mu2) ** 2).sum() + np.trace(s1) + np.trace(s2) - 2 * tr)


def fd_mp(a, b, dps=50):
    """High-precision reference (mpmath, 50 digits): removes the sqrt(eps) noise that double-precision
    square roots of singular covariances carry."""
    import mpmath as mp

    mp.mp.dps = dps

    def cov(x):
        n, d = x.shape
        xm = mp.matrix(x.tolist())
        mu = [mp.fsum(xm[i, j] for i in range(n)) / n for j in range(d)]
        c = mp.matrix(d, d)
        for i in range(d):
            for j in range(d):
                c[i, j] = mp.fsum((xm[k, i] - mu[i]) * (xm[k, j] - mu[j]) for k in range(n)) / (n - 1)
        return mu, c

    mu1, s1 = cov(a)
    mu2, s2 = cov(b)
    d = a.shape[1]
    w, v = mp.eigsy(s1)
    r1 = v * mp.diag([mp.sqrt(max(x, 0)) for x in w]) * v.T
    m = r1 * s2 * r1
    mu = mp.eigsy((m + m.T) / 2, eigvals_only=True)
    tr = mp.fsum(mp.sqrt(max(x, 0)) for x in mu)
    mean = mp.fsum((mu1[i] - mu2[i]) ** 2 for i in range(d))
    return float(mean + mp.fsum(s1[i, i] for i in range(d)) + mp.fsum(s2[i, i] for i in range(d)) - 2 * tr)


fd_cases = []
for name, (na, nb, d, rank) in {
    "full_rank": (60, 45, 8, None),
    "more_dims_than_samples": (5, 7, 12, None),
    "singular_covariance": (40, 40, 10, 4),
}.items():
    if rank is None:
        a = rng.normal(0.0, 1.0, (na, d)) @ rng.normal(0, 1, (d, d))
        b = rng.normal(0.3, 1.2, (nb, d)) @ rng.normal(0, 1, (d, d))
    else:
        basis = rng.normal(0, 1, (rank, d))
        a = rng.normal(0.0, 1.0, (na, rank)) @ basis
        b = rng.normal(0.5, 1.0, (nb, rank)) @ basis
    a = a.astype(np.float32).astype(np.float64)
    b = b.astype(np.float32).astype(np.float64)
    fd_cases.append(
        {
            "name": name,
            "dim": d,
            "a": a.reshape(-1).tolist(),
            "b": b.reshape(-1).tolist(),
            "fd_eigh": fd_eigh(a, b),
            "fd_mp": fd_mp(a, b),
            "fd_scipy_sqrtm": fd_sqrtm(a, b),
            "cov_a": np.cov(a, rowvar=False).reshape(-1).tolist(),
        }
    )
out["frechet"] = fd_cases

# ---------------------------------------------------------------- Chamfer distance (PyTorch3D convention)
ca = rng.normal(0, 10, (300, 3)).astype(np.float32)
cb = (rng.normal(0, 10, (220, 3)) + np.array([1.0, -2.0, 0.5])).astype(np.float32)
da, _ = cKDTree(cb.astype(np.float64)).query(ca.astype(np.float64))
db, _ = cKDTree(ca.astype(np.float64)).query(cb.astype(np.float64))
out["chamfer"] = {
    "a": ca.tolist(),
    "b": cb.tolist(),
    "a_to_b": float((da**2).mean()),
    "b_to_a": float((db**2).mean()),
    "value": float((da**2).mean() + (db**2).mean()),
}

path = os.path.join(os.path.dirname(os.path.abspath(__file__)), "golden.json")
with open(path, "w") as f:
    json.dump(out, f)
print("wrote", path)
for c in fd_cases:
    print(c["name"], "mp", c["fd_mp"], "eigh", c["fd_eigh"], "sqrtm", c["fd_scipy_sqrtm"])
for k, v in bev["regions"].items():
    print(k, {kk: vv for kk, vv in v.items() if not kk.startswith("hist")})
