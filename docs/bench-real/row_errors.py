"""Where a generated scan's error sits on a real KITTI frame, by beam row (BENCHMARKS.md, issue 18).

Bins the real velodyne scan and a generated scan (both KITTI .bin, LiDAR frame) onto the same
32 x 256 grid (uniform beams from +3 to -25 degrees, nearest return per cell), keeps the columns
within 40 degrees of the camera's axis, and prints range MAE and bias (generated - real) per band
of four beam rows and per side. An approximation of `bench-real`'s projection, for reading where
the error is, not a benchmark figure.

    veila generate --image IMG --calib CALIB --residual-weight 0 --out /tmp/gen
    python docs/bench-real/row_errors.py REAL.bin /tmp/gen/scan_000.bin
"""

import sys

import numpy as np


def grid(points, rows=32, cols=256, fov_up=3.0, fov_down=-25.0):
    r = np.linalg.norm(points[:, :3], axis=1)
    az = np.degrees(np.arctan2(points[:, 1], points[:, 0]))
    el = np.degrees(np.arcsin(points[:, 2] / np.maximum(r, 1e-6)))
    row = np.floor((fov_up - el) / (fov_up - fov_down) * rows).astype(int)
    col = np.floor((180.0 - az) / 360.0 * cols).astype(int) % cols
    g = np.full((rows, cols), np.inf)
    ok = (row >= 0) & (row < rows) & (r > 0.5)
    np.minimum.at(g, (row[ok], col[ok]), r[ok])
    g[np.isinf(g)] = np.nan
    return g


def main(real_bin, generated_bins):
    real = grid(np.fromfile(real_bin, np.float32).reshape(-1, 4))
    az = 180.0 - (np.arange(real.shape[1]) + 0.5) * 360.0 / real.shape[1]
    view = np.abs(az) < 40.0
    for name in generated_bins:
        gen = grid(np.fromfile(name, np.float32).reshape(-1, 4))
        both = ~np.isnan(real) & ~np.isnan(gen) & view[None, :]
        err = gen - real
        print(f"{name}: MAE in view {np.abs(err[both]).mean():.2f} m over {both.sum()} cells")
        for r0 in range(0, real.shape[0], 4):
            m = both.copy()
            m[:r0] = False
            m[r0 + 4 :] = False
            if m.any():
                print(
                    f"  rows {r0:2d}-{r0 + 3:2d}: MAE {np.abs(err[m]).mean():5.2f}  bias {err[m].mean():+6.2f}"
                    f"  real {real[m].mean():5.1f}  generated {gen[m].mean():5.1f}  ({m.sum()} cells)"
                )
        for lo, hi, side in [(0.0, 40.0, "left"), (-40.0, 0.0, "right")]:
            m = both & ((az > lo) & (az < hi))[None, :]
            print(f"  {side:5s}: MAE {np.abs(err[m]).mean():5.2f}  bias {err[m].mean():+6.2f}")


if __name__ == "__main__":
    if len(sys.argv) < 3:
        sys.exit(__doc__)
    main(sys.argv[1], sys.argv[2:])
