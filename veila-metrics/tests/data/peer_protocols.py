#!/usr/bin/env python3
"""Reference values for `veila eval --protocol ...`: the peers' whole evaluation pipelines, reproduced in numpy.

    python3 -m venv /tmp/vv && /tmp/vv/bin/pip install "numpy==1.26.4" "scipy==1.11.4"
    /tmp/vv/bin/python veila-metrics/tests/data/peer_protocols.py [DATA_ROOT]

DATA_ROOT defaults to ../shared/data/real beside the workspace. Writes peer_protocols.json and the small
synthetic peer sample files in peer_samples/ next to this script. Run by hand; the Rust tests read the JSON.

What each protocol does to a raw scan before its metric (written from the peers' code at the commits
listed in ../shared/reference/peer-systems-and-metric-protocols.md; numpy 1.x dtype rules, as in the
peers' environments: float32 arrays stay float32 when combined with Python or numpy scalars):

* r2dm (kazuto1011/r2dm `data/kitti_360/kitti_360.py: load_points_as_images`, `evaluate.py`): every
  point goes to a 64x1024 grid (uniform elevation +3..-25 deg, floor, clipped), nearest point wins
  (scatter in order of decreasing float32 range); the pixel keeps that point's own xyz and range; the
  pixel counts when 1.45 <= r <= 80 (dataset mask) and 0.5 < r < 63 (evaluation mask). The BEV metrics
  then bin the kept xyz (3 < |p| < 70 m, 100 x 100 over +-80 m).
* text2lidar (wuyang98/Text2LiDAR, R2DM's code): the same at 32x1024 with the same +3..-25 deg rows.
* lidargen (vzyrianov/lidargen `metrics/histogram/*`): LaserScan projection to 64x1024 (nearest wins,
  no range filter), range -> clip(log2(r + 1e-4 + 1) / 6, 0, 1) (so everything beyond 63 m is put at
  63 m), back to points through the pixel-corner angles, 3 < r < 70 m. JSD as R2DM, MMD with the spectral
  norm.
* lidm / lidm-nuscenes (hancyran/LiDAR-Diffusion `lidm/utils/lidar_utils.py`, `lidm/data/base.py`,
  `lidm/eval/metric_utils.py`): keep 1 < r < 56 m (45 m), project to 64x1024 +3..-25 deg (32x1024 +10..-30
  deg), nearest wins, log2(r + 1e-4 + 1) / depth_scale (6; 6.5) scaled to [-1, 1] and back, unprojected
  through the pixel-corner angles, kept when 1 < r < 56 (45), as float32. JSD: 0.05 m occupancy over
  +-50 m (+-30 m) summed over scans; MMD: minimum matching 2-D Chamfer over 0.5 m occupancy.

Deviations, each below the 1e-4 agreement the tests ask for: R2DM bins with torch.histogramdd in float32
and computes its MMD with torch in float32; here numpy.histogramdd and float64 kernels are used (the
peer's float32 MMD is itself only good to ~1e-3 relative: it is a difference of O(1) kernel means). LiDM
computes its Chamfer distances in float32 CUDA; here exactly, with a k-d tree. numpy's argsort is not
stable: points of one pixel with bit-identical float32 range could win in another order (none do here).
"""
import json
import os
import sys
from pathlib import Path

import numpy as np
import scipy
from scipy.spatial import cKDTree
from scipy.spatial.distance import jensenshannon

HERE = Path(__file__).resolve().parent
ROOT = Path(sys.argv[1]) if len(sys.argv) > 1 else HERE.parents[2] / ".." / "shared" / "data" / "real"

SETS = {
    "kitti": {
        "generated": [
            "kitti/training/velodyne/000000.bin",
            "kitti/training/velodyne/000001.bin",
        ],
        "reference": [
            "semantickitti/sequences/00/velodyne/000000.bin",
            "semantickitti/sequences/00/velodyne/000001.bin",
        ],
    },
    "nuscenes": {
        "generated": [
            "nuscenes/samples/LIDAR_TOP/n015-2018-07-24-11-22-45+0800__LIDAR_TOP__1532402927647951.pcd.bin",
        ],
        "reference": [
            "kitti/training/velodyne/000000.bin",
            "semantickitti/sequences/00/velodyne/000000.bin",
        ],
    },
}


def read_xyz(rel):
    cols = 5 if rel.endswith(".pcd.bin") else 4
    pts = np.fromfile(ROOT / rel, dtype=np.float32).reshape(-1, cols)
    return np.ascontiguousarray(pts[:, :3])


# ------------------------------------------------------------------ R2DM / Text2LiDAR
def r2dm_points(xyz, H, W=1024):
    """kitti_360.py spherical projection + evaluate.py masks; returns the kept (N, 3) float32 xyz."""
    x, y, z = xyz[:, [0]], xyz[:, [1]], xyz[:, [2]]
    depth = np.linalg.norm(xyz, ord=2, axis=1, keepdims=True)
    mask = (depth >= 1.45) & (depth <= 80.0)
    h_up, h_down = np.deg2rad(3), np.deg2rad(-25)
    elevation = np.arcsin(z / depth) + abs(h_down)
    grid_h = 1 - elevation / (h_up - h_down)
    grid_h = np.floor(grid_h * H).clip(0, H - 1).astype(np.int32)
    azimuth = -np.arctan2(y, x)
    grid_w = (azimuth / np.pi + 1) / 2 % 1
    grid_w = np.floor(grid_w * W).clip(0, W - 1).astype(np.int32)
    order = np.argsort(-depth.squeeze(1))
    img = np.zeros((H, W, 5), dtype=np.float32)  # x, y, z, depth, mask
    vals = np.concatenate([xyz, depth, mask.astype(np.float32)], axis=1)
    # sequential scatter (the peer's numba loop): later = nearer wins; fancy assignment keeps the last
    img[grid_h[order, 0], grid_w[order, 0]] = vals[order]
    img *= img[:, :, [4]]
    d = img[:, :, 3]
    keep = (img[:, :, 4] > 0) & (d > 0.5) & (d < 63.0)
    return img[keep][:, :3]


def r2dm_unproject_depth(depth):
    """utils/lidar.py LiDARUtility.to_xyz with the linear HDL-64E ray angles, float32 (depth (H, W) metres)."""
    H, W = depth.shape
    el = (1 - np.arange(H, dtype=np.float32) / H) * (3 - -25) + -25
    az = (1 - np.arange(W, dtype=np.float32) / W) * (180 - -180) + -180
    el, az = np.meshgrid(el, az, indexing="ij")
    phi, theta = np.deg2rad(el).astype(np.float32), np.deg2rad(az).astype(np.float32)
    d = depth.astype(np.float32)
    mask = (d > 1.45) & (d < 80.0)
    xyz = np.stack([d * np.cos(phi) * np.cos(theta), d * np.cos(phi) * np.sin(theta), d * np.sin(phi)], 0)
    return xyz * mask, d * mask


def r2dm_sample_points(sample):
    """evaluate.py Samples: a (5, H, W) [depth, x, y, z, reflectance] image, mask 0.5 < depth < 63."""
    d = sample[0]
    keep = (d > 0.5) & (d < 63.0)
    return np.stack([sample[1][keep], sample[2][keep], sample[3][keep]], 1).astype(np.float32)


def r2dm_hist(pts):
    depth = np.linalg.norm(pts, ord=2, axis=1)
    m = (depth > 3.0) & (depth < 70.0)
    h, _ = np.histogramdd(pts[m, 0:2].astype(np.float64), bins=100, range=[[-80, 80], [-80, 80]])
    return h.astype(np.float32)


def r2dm_jsd(hg, hr):
    p = np.sum(hr, axis=0).astype(np.float32)
    p = (p / np.sum(hr, dtype=np.float32)).flatten()
    q = np.sum(hg, axis=0).astype(np.float32)
    q = (q / np.sum(hg, dtype=np.float32)).flatten()
    return float(jensenshannon(p, q))


def r2dm_mmd(hg, hr):
    p = np.stack([h.flatten() / h.sum() for h in hr]).astype(np.float64)
    q = np.stack([h.flatten() / h.sum() for h in hg]).astype(np.float64)

    def k(a, b):
        d2 = ((a[:, None, :] - b[None, :, :]) ** 2).sum(-1)
        return np.exp(-d2 / (2 * 0.5**2))

    return float(k(p, p).mean() + k(q, q).mean() - 2 * k(p, q).mean())


# ------------------------------------------------------------------ LiDARGen
FOV_UP, FOV_DOWN = 3.0 / 180.0 * np.pi, -25.0 / 180.0 * np.pi


def lidargen_range_image(xyz, H=64, W=1024):
    """LaserScan.do_range_projection: float32 range image, -1 where empty."""
    fov = abs(FOV_DOWN) + abs(FOV_UP)
    depth = np.linalg.norm(xyz, 2, axis=1)
    yaw = -np.arctan2(xyz[:, 1], xyz[:, 0])
    pitch = np.arcsin(xyz[:, 2] / depth)
    proj_x = 0.5 * (yaw / np.pi + 1.0) * W
    proj_y = (1.0 - (pitch + abs(FOV_DOWN)) / fov) * H
    proj_x = np.maximum(0, np.minimum(W - 1, np.floor(proj_x))).astype(np.int32)
    proj_y = np.maximum(0, np.minimum(H - 1, np.floor(proj_y))).astype(np.int32)
    order = np.argsort(depth)[::-1]
    img = np.full((H, W), -1, dtype=np.float32)
    img[proj_y[order], proj_x[order]] = depth[order]
    return img


def lidargen_normalise(img):
    """hist_utils.load_kitti: range -> clip(log2(r + 1e-4 + 1) / 6, 0, 1)."""
    img = np.where(img < 0, 0, img) + 0.0001
    return np.clip(np.log2(img + 1) / 6, 0, 1)


def lidargen_points(norm):
    """histogram.range_image_to_point_cloud_fast, for any H x W (the peer's is fixed at 64 x 1024)."""
    H, W = norm.shape
    depth = (np.exp2(norm * 6) - 1).flatten()
    fov = abs(FOV_DOWN) + abs(FOV_UP)
    x, y = np.meshgrid(np.arange(0, float(W)), np.arange(0, float(H)))
    x *= 1 / float(W)
    y *= 1 / float(H)
    yaw = (np.pi * (x * 2 - 1)).flatten()
    pitch = ((1.0 - y) * fov - abs(FOV_DOWN)).flatten()
    pts = np.zeros((len(yaw), 3))
    pts[:, 0] = np.cos(yaw) * np.cos(pitch) * depth
    pts[:, 1] = -np.sin(yaw) * np.cos(pitch) * depth
    pts[:, 2] = np.sin(pitch) * depth
    m = (depth > 3.0) & (depth < 70.0)
    return pts[m]


def lidargen_hist(pts):
    h, _ = np.histogramdd(pts[:, 0:2], bins=100, range=([-80.0, 80.0], [-80.0, 80.0]))
    return h


def lidargen_jsd(hg, hr):
    p = np.sum(np.stack(hr), 0)
    q = np.sum(np.stack(hg), 0)
    return float(jensenshannon((p / p.sum()).flatten(), (q / q.sum()).flatten()))


def lidargen_mmd(hg, hr):
    a = [h / np.sum(h) for h in hr]
    b = [h / np.sum(h) for h in hg]

    def disc(s1, s2):
        t = 0.0
        for u in s1:
            for v in s2:
                d = np.linalg.norm(u - v, 2)
                t += np.exp(-d * d / (2 * 0.5 * 0.5))
        return t / (len(s1) * len(s2))

    return float(disc(a, a) + disc(b, b) - 2 * disc(a, b))


# ------------------------------------------------------------------ LiDM
LIDM = {
    "lidm": dict(size=(64, 1024), fov=(3, -25), depth_range=(1.0, 56.0), depth_scale=6, half=50),
    "lidm-nuscenes": dict(size=(32, 1024), fov=(10, -30), depth_range=(1.0, 45.0), depth_scale=6.5, half=30),
}


def lidm_range(xyz, c):
    H, W = c["size"]
    fov_up, fov_down = c["fov"][0] / 180.0 * np.pi, c["fov"][1] / 180.0 * np.pi
    fov_range = abs(fov_down) + abs(fov_up)
    depth = np.linalg.norm(xyz, 2, axis=1)
    m = np.logical_and(depth > c["depth_range"][0], depth < c["depth_range"][1])
    depth, pcd = depth[m], xyz[m]
    yaw = -np.arctan2(pcd[:, 1], pcd[:, 0])
    pitch = np.arcsin(pcd[:, 2] / depth)
    proj_x = 0.5 * (yaw / np.pi + 1.0)
    proj_y = 1.0 - (pitch + abs(fov_down)) / fov_range
    proj_x *= W
    proj_y *= H
    proj_x = np.maximum(0, np.minimum(W - 1, np.floor(proj_x))).astype(np.int32)
    proj_y = np.maximum(0, np.minimum(H - 1, np.floor(proj_y))).astype(np.int32)
    order = np.argsort(depth)[::-1]
    img = np.full((H, W), -1, dtype=np.float32)
    img[proj_y[order], proj_x[order]] = depth[order]
    return img


def lidm_normalise(img, c):
    """base.py process_scan (log scale), then the `* .5 + .5` of the reprojection: values in [0, 1]."""
    img = np.where(img < 0, 0, img)
    img = np.log2(img + 0.0001 + 1)
    img = img / c["depth_scale"]
    img = img * 2.0 - 1.0
    img = np.clip(img, -1, 1)
    return img * 0.5 + 0.5


def lidm_points(norm, c):
    """lidar_utils.range2pcd (log scale) then .astype(float32)."""
    H, W = norm.shape
    fov_up, fov_down = c["fov"][0] / 180.0 * np.pi, c["fov"][1] / 180.0 * np.pi
    fov_range = abs(fov_down) + abs(fov_up)
    depth = (norm * c["depth_scale"]).flatten()
    depth = np.exp2(depth) - 1
    sx, sy = np.meshgrid(np.arange(W), np.arange(H))
    sx = sx.astype(np.float64) / W
    sy = sy.astype(np.float64) / H
    yaw = (np.pi * (sx * 2 - 1)).flatten()
    pitch = ((1.0 - sy) * fov_range - abs(fov_down)).flatten()
    pcd = np.zeros((len(yaw), 3))
    pcd[:, 0] = np.cos(yaw) * np.cos(pitch) * depth
    pcd[:, 1] = -np.sin(yaw) * np.cos(pitch) * depth
    pcd[:, 2] = np.sin(pitch) * depth
    m = np.logical_and(depth > c["depth_range"][0], depth < c["depth_range"][1])
    return pcd[m, :].astype(np.float32)


def lidm_cells(pcd, half, voxel):
    """metric_utils.pcd2bev_*: strict +-half window, floor(p / voxel), unique, shifted to the grid."""
    m = (pcd[:, 0] > -half) & (pcd[:, 0] < half) & (pcd[:, 1] > -half) & (pcd[:, 1] < half)
    v = np.floor(pcd[m][:, :2] / np.float32(voxel))
    v = np.unique(v, axis=0)
    return (v - np.array([np.ceil(-half / voxel), np.ceil(-half / voxel)])).astype(np.int64)


def lidm_jsd(pg, pr, half):
    size = int(np.ceil(2 * half / 0.05))

    def summed(pcds):
        vol = np.zeros((size, size), np.float32)
        for p in pcds:
            c = lidm_cells(p, half, 0.05)
            vol[c[:, 0], c[:, 1]] += 1.0
        return vol

    r, s = summed(pr), summed(pg)
    return float(jensenshannon((r / np.sum(r)).flatten(), (s / np.sum(s)).flatten()))


def lidm_mmd(pg, pr, half):
    size = int(np.ceil(2 * half / 0.5))
    norm = lambda p: lidm_cells(p, half, 0.5).astype(np.float64) / size
    gs, rs = [norm(p) for p in pg], [norm(p) for p in pr]
    best = []
    for r in rs:
        tr = cKDTree(r)
        ds = []
        for g in gs:
            d1, _ = cKDTree(g).query(r)
            d2, _ = tr.query(g)
            ds.append((np.mean(d1**2) + np.mean(d2**2)) / 2)
        best.append(min(ds))
    return float(np.mean(best))


# ------------------------------------------------------------------ pipelines
def prepare(protocol, xyz):
    """Raw scan -> the points the protocol's metric sees."""
    if protocol == "r2dm":
        return r2dm_points(xyz, 64)
    if protocol == "text2lidar":
        return r2dm_points(xyz, 32)
    if protocol == "lidargen":
        return lidargen_points(lidargen_normalise(lidargen_range_image(xyz)))
    c = LIDM[protocol]
    return lidm_points(lidm_normalise(lidm_range(xyz, c), c), c)


def score(protocol, pg, pr):
    if protocol in ("r2dm", "text2lidar"):
        hg, hr = [r2dm_hist(p) for p in pg], [r2dm_hist(p) for p in pr]
        return {"jsd": r2dm_jsd(hg, hr), "mmd": r2dm_mmd(hg, hr)}
    if protocol == "lidargen":
        hg, hr = [lidargen_hist(p) for p in pg], [lidargen_hist(p) for p in pr]
        return {"jsd": lidargen_jsd(hg, hr), "mmd": lidargen_mmd(hg, hr)}
    half = LIDM[protocol]["half"]
    return {"jsd": lidm_jsd(pg, pr, half), "mmd": lidm_mmd(pg, pr, half)}


PROTOCOLS = ["r2dm", "text2lidar", "lidargen", "lidm", "lidm-nuscenes"]


def summary(p):
    p = np.asarray(p, dtype=np.float64)
    return {"points": int(len(p)), "sum_x": float(p[:, 0].sum()), "sum_y": float(p[:, 1].sum())}


# ------------------------------------------------------------------ synthetic peer sample files
def synthetic_depth(n, H, W, seed):
    """Smooth ring-like range images in metres (walls at 8..60 m, ground rows) with ~10% dropped pixels."""
    rng = np.random.default_rng(seed)
    rows = np.arange(H)[:, None]
    cols = np.arange(W)[None, :]
    out = []
    for k in range(n):
        wall = 8.0 + 52.0 * (0.5 + 0.5 * np.sin(2 * np.pi * (cols / W) * (2 + k) + 0.3 * rows / H))
        ground = 3.0 + 25.0 * (H - rows) / H
        d = np.where(rows > H // 2, np.minimum(ground, wall), wall)
        d = d + rng.normal(0, 0.2, (H, W))
        d[rng.random((H, W)) < 0.1] = 0.0
        out.append(d.astype(np.float32))
    return np.stack(out)


def main():
    out = {"numpy": np.__version__, "scipy": scipy.__version__, "sets": SETS, "raw": {}, "samples": {}}
    scans = {rel: read_xyz(rel) for s in SETS.values() for rel in s["generated"] + s["reference"]}
    for name, s in SETS.items():
        out["raw"][name] = {}
        for proto in PROTOCOLS:
            pg = [prepare(proto, scans[r]) for r in s["generated"]]
            pr = [prepare(proto, scans[r]) for r in s["reference"]]
            out["raw"][name][proto] = {
                **score(proto, pg, pr),
                "generated_points": [summary(p) for p in pg],
                "reference_points": [summary(p) for p in pr],
            }
            print(name, proto, out["raw"][name][proto]["jsd"], out["raw"][name][proto]["mmd"])

    sdir = HERE / "peer_samples"
    sdir.mkdir(exist_ok=True)
    ref = [prepare_ref for prepare_ref in SETS["kitti"]["reference"]]
    # R2DM: a depth-only (N, 1, H, W) array in metres and a (N, 5, H, W) [depth, x, y, z, reflectance] one
    depth = synthetic_depth(2, 16, 128, 1)
    np.save(sdir / "r2dm_depth.npy", depth[:, None])
    xyz, dm = r2dm_unproject_depth(depth[0])
    five = np.concatenate([dm[None], xyz, np.full((1, 16, 128), 0.3, np.float32)], 0)[None].astype(np.float32)
    np.save(sdir / "r2dm_5ch.npy", five)
    # LiDARGen: (N, 2, H, W), channel 0 = clip(log2(r + 1e-4 + 1) / 6, 0, 1)
    lg = lidargen_normalise(synthetic_depth(2, 16, 128, 2))
    np.save(sdir / "lidargen.npy", np.stack([lg, np.full_like(lg, 0.5)], 1).astype(np.float32))
    # LiDM: np.savez of the (N, H, W) batch in [0, 1], as scripts/sample.py writes it
    lm = np.stack([lidm_normalise(d, LIDM["lidm"]) for d in synthetic_depth(2, 16, 128, 3)]).astype(np.float32)
    np.savez(sdir / "lidm.npz", lm)
    # a pickled object array: must be refused
    np.save(sdir / "pickled.npy", np.array([{"not": "allowed"}], dtype=object), allow_pickle=True)

    def rel_points(proto, arrs):
        pts = []
        for a in arrs:
            if proto == "r2dm-5ch":
                pts.append(r2dm_sample_points(a))
            elif proto == "r2dm":
                xyz, d = r2dm_unproject_depth(a[0])
                keep = (d > 0.5) & (d < 63.0)
                pts.append(np.stack([xyz[0][keep], xyz[1][keep], xyz[2][keep]], 1))
            elif proto == "lidargen":
                pts.append(lidargen_points(a[0]))
            else:
                pts.append(lidm_points(a, LIDM[proto]))
        return pts

    refs = {p: [prepare(p, scans[r]) for r in ref] for p in ["r2dm", "lidargen", "lidm", "lidm-nuscenes"]}
    cases = {
        "r2dm_depth.npy": ("r2dm", "r2dm", list(np.load(sdir / "r2dm_depth.npy"))),
        "r2dm_5ch.npy": ("r2dm", "r2dm-5ch", list(np.load(sdir / "r2dm_5ch.npy"))),
        "lidargen.npy": ("lidargen", "lidargen", list(np.load(sdir / "lidargen.npy"))),
        "lidm.npz": ("lidm", "lidm", list(np.load(sdir / "lidm.npz")["arr_0"])),
        "lidm.npz (lidm-nuscenes)": ("lidm-nuscenes", "lidm-nuscenes", list(np.load(sdir / "lidm.npz")["arr_0"])),
    }
    for key, (proto, how, arrs) in cases.items():
        pg = rel_points(how, arrs)
        out["samples"][key] = {
            "protocol": proto,
            **score(proto, pg, refs[proto]),
            "generated_points": [summary(p) for p in pg],
        }
        print(key, out["samples"][key]["jsd"], out["samples"][key]["mmd"])
    out["samples_reference"] = ref
    with open(HERE / "peer_protocols.json", "w") as f:
        json.dump(out, f, indent=1)
        f.write("\n")


if __name__ == "__main__":
    main()
