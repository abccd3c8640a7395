"""Texture of LiDAR scans along their beams, for comparing the simulator's range noise with real scans.

Each KITTI-layout scan (`*.bin`, float32 x, y, z, intensity) is projected to a range image of
`rows x cols` pixels over elevations [-25, 3] degrees (the nearest return wins a pixel, as the
workspace's projection does), and every pair of horizontal neighbours with two returns gives a
relative step `s = |r1 - r2| / min(r1, r2)`. Printed per folder, over its scans: the share of
lower-half pairs with `s < 3e-4` (the "smooth" share of veila_metrics::texture), the median `s` in
the lower half (mostly ground) and the share of upper-half pairs with `s > 1` (depth edges), as
mean and spread over scans.

    python xtask/scripts/range_texture.py FOLDER [FOLDER ...]

Needs numpy. Used for BENCHMARKS.md, "The simulator's range noise".
"""

import glob
import os
import sys

import numpy as np


def range_image(points, rows, cols, up_deg=3.0, down_deg=-25.0, min_range_m=1.45):
    r = np.linalg.norm(points[:, :3], axis=1)
    keep = r > min_range_m
    p, r = points[keep], r[keep]
    azimuth = np.arctan2(p[:, 1], p[:, 0])
    elevation = np.degrees(np.arcsin(p[:, 2] / r))
    col = ((0.5 * (1.0 - azimuth / np.pi)) * cols).astype(int) % cols
    row = np.floor((up_deg - elevation) / (up_deg - down_deg) * rows).astype(int)
    inside = (row >= 0) & (row < rows)
    img = np.full((rows, cols), np.inf)
    np.minimum.at(img, (row[inside], col[inside]), r[inside])
    img[np.isinf(img)] = np.nan
    return img


def steps_along_rows(img):
    nxt = np.roll(img, -1, axis=1)
    s = np.abs(img - nxt) / np.minimum(img, nxt)
    return s[np.isfinite(s)]


def texture(img):
    half = img.shape[0] // 2
    lower = steps_along_rows(img[half:])
    upper = steps_along_rows(img[:half])
    return (lower < 3e-4).mean(), np.median(lower), (upper > 1.0).mean()


def main():
    if len(sys.argv) < 2:
        sys.exit(__doc__)
    for folder in sys.argv[1:]:
        files = sorted(glob.glob(os.path.join(folder, "**", "*.bin"), recursive=True))
        if not files:
            sys.exit(f"{folder}: no *.bin scans")
        for rows, cols in [(64, 1024), (32, 256)]:
            stats = np.array(
                [texture(range_image(np.fromfile(f, np.float32).reshape(-1, 4), rows, cols)) for f in files]
            )
            mean, std = stats.mean(0), stats.std(0)
            print(
                f"{folder} {rows}x{cols} ({len(files)} scans): smooth lower {mean[0]:.3f} ± {std[0]:.3f}, "
                f"median step lower {100 * mean[1]:.3f} ± {100 * std[1]:.3f} %, "
                f"edges upper {mean[2]:.4f} ± {std[2]:.4f}"
            )


if __name__ == "__main__":
    main()
