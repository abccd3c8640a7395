"""Vectorised numpy reference for veila-geom's projection benchmark (equation 1 of the paper).

Projects a KITTI scan (f32 x, y, z, reflectance) into a 64 x 1024 range image with the HDL-64E field of
view (+3 / -25 deg, valid range 0.5..120 m), nearest point wins (ties: lower index), points outside the
field of view rejected -- the same rules as `veila_geom::Projector` -- and reports the median time per
scan. Run from anywhere:

    python3 veila-geom/benches/numpy_reference.py [scan.bin] [repeats]

(`pip install numpy` if needed). The default scan is KITTI 000000 under ../shared/data/real.
"""
import os
import sys
import time

import numpy as np

H, W = 64, 1024
FOV_UP, FOV_DOWN = np.radians(3.0), np.radians(-25.0)
MIN_R, MAX_R = 0.5, 120.0


def project(pts):
    """Return (range image, index image, occupied pixel count) for an (N, 4) float32 array."""
    xyz = pts[:, :3].astype(np.float64)
    d = np.sqrt((xyz * xyz).sum(1))
    ok = np.isfinite(xyz).all(1) & (d >= MIN_R) & (d <= MAX_R)
    idx = np.nonzero(ok)[0]
    x, y, z, d = xyz[idx, 0], xyz[idx, 1], xyz[idx, 2], d[idx]
    f = FOV_UP - FOV_DOWN
    u = 0.5 * (1.0 - np.arctan2(y, x) / np.pi) * W
    v = (1.0 - (np.arcsin(z / d) - FOV_DOWN) / f) * H
    col = np.floor(u).astype(np.int64) % W
    row = np.floor(v).astype(np.int64)
    row[v == H] = H - 1  # the bottom edge belongs to the last row
    keep = (row >= 0) & (row < H)
    idx, d, row, col = idx[keep], d[keep], row[keep], col[keep]
    pix = row * W + col
    # nearest wins, ties to the lower index: sort by (pixel, range, index), keep the first of each pixel
    order = np.lexsort((idx, d, pix))
    pix_s = pix[order]
    first = np.ones(len(pix_s), dtype=bool)
    first[1:] = pix_s[1:] != pix_s[:-1]
    win = order[first]
    rng = np.zeros(H * W, dtype=np.float32)
    index = np.full(H * W, -1, dtype=np.int64)
    rng[pix[win]] = d[win]
    index[pix[win]] = idx[win]
    return rng.reshape(H, W), index.reshape(H, W), len(win)


def main():
    here = os.path.dirname(os.path.abspath(__file__))
    default = os.path.join(here, "../../../shared/data/real/kitti/training/velodyne/000000.bin")
    path = sys.argv[1] if len(sys.argv) > 1 else default
    repeats = int(sys.argv[2]) if len(sys.argv) > 2 else 30
    pts = np.fromfile(path, dtype="<f4").reshape(-1, 4)
    project(pts)  # warm up
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        _, _, occupied = project(pts)
        times.append(time.perf_counter() - t0)
    times.sort()
    med = times[len(times) // 2]
    print(f"numpy {np.__version__}: {len(pts)} points, {occupied} occupied pixels")
    print(f"median {med * 1e3:.2f} ms per scan (min {times[0] * 1e3:.2f} ms) over {repeats} runs, "
          f"{len(pts) / med / 1e6:.1f} Mpoints/s")


if __name__ == "__main__":
    main()
