#!/usr/bin/env python3
"""scipy reference values and timings for veila-metrics' benchmarks (writes benches/scipy_reference.json).

    pip install numpy scipy
    python3 veila-metrics/benches/scipy_reference.py [--dims 512,2048] [--data DIR]

1. Chamfer distance (PyTorch3D convention: squared NN distances, each direction averaged, summed) between the
   real KITTI scans 000000.bin and 000001.bin with scipy.spatial.cKDTree (tree builds included in the time).
2. Frechet distance at the given feature dimensions with scipy.linalg.sqrtm, on features produced by the
   SplitMix64 generator that benches/bench_main.rs implements identically (see `features`).
"""
import argparse
import json
import os
import time

import numpy as np
import scipy
import scipy.linalg
from scipy.spatial import cKDTree

HERE = os.path.dirname(os.path.abspath(__file__))


def splitmix_uniform(seed, count):
    """u_k = splitmix64(seed * 2^32 + k) >> 11 scaled to [0, 1), k = 0..count-1 (uint64 wrap-around)."""
    with np.errstate(over="ignore"):
        z = (np.uint64(seed) << np.uint64(32)) + np.arange(count, dtype=np.uint64)
        z = (z + np.uint64(1)) * np.uint64(0x9E3779B97F4A7C15)
        z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
        z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
        z = z ^ (z >> np.uint64(31))
    return (z >> np.uint64(11)).astype(np.float64) / float(2**53)


def features(seed, n, d, decay):
    """n x d features: x_ij = (u_ij - 0.5) (1 + j)^-decay + 0.3 (u_i0 - 0.5): a decaying spectrum plus one
    shared factor, so the covariance is dense and ill-conditioned like real network features."""
    u = splitmix_uniform(seed, n * d).reshape(n, d)
    scale = (1.0 + np.arange(d)) ** (-decay)
    return (u - 0.5) * scale + 0.3 * (u[:, :1] - 0.5)


def fd_scipy(a, b):
    mu1, mu2 = a.mean(0), b.mean(0)
    s1, s2 = np.cov(a, rowvar=False), np.cov(b, rowvar=False)
    t = time.perf_counter()
    covmean = scipy.linalg.sqrtm(s1.dot(s2))
    covmean = np.real(covmean)
    fd = ((mu1 - mu2) ** 2).sum() + np.trace(s1) + np.trace(s2) - 2 * np.trace(covmean)
    return float(fd), time.perf_counter() - t


def read_kitti(path):
    return np.fromfile(path, dtype="<f4").reshape(-1, 4)[:, :3]


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--dims", default="512,2048")
    ap.add_argument(
        "--data",
        default=os.path.join(HERE, "../../../shared/data/real/kitti/training/velodyne"),
    )
    args = ap.parse_args()
    out = {"numpy": np.__version__, "scipy": scipy.__version__}

    a_path, b_path = os.path.join(args.data, "000000.bin"), os.path.join(args.data, "000001.bin")
    if os.path.exists(a_path) and os.path.exists(b_path):
        a = read_kitti(a_path).astype(np.float64)
        b = read_kitti(b_path).astype(np.float64)
        times = []
        for _ in range(3):
            t = time.perf_counter()
            da, _ = cKDTree(b).query(a)
            db, _ = cKDTree(a).query(b)
            cd = float((da**2).mean() + (db**2).mean())
            times.append(time.perf_counter() - t)
        out["chamfer_kitti"] = {"value": cd, "points": [len(a), len(b)], "seconds": min(times)}
        print(f"chamfer KITTI 000000/000001: {cd:.17g}  ({min(times):.3f} s, best of 3)")
    else:
        print("skipping chamfer: KITTI scans not found")

    out["frechet"] = []
    for d in [int(x) for x in args.dims.split(",")]:
        n = 2 * d
        a = features(1, n, d, 0.25)
        b = features(2, n, d, 0.20)
        fd, secs = fd_scipy(a, b)
        out["frechet"].append({"dim": d, "samples": n, "value": fd, "seconds": secs})
        print(f"frechet d={d} n={n}: {fd:.17g}  (sqrtm + trace {secs:.2f} s)")

    with open(os.path.join(HERE, "scipy_reference.json"), "w") as f:
        json.dump(out, f, indent=1)


if __name__ == "__main__":
    main()
