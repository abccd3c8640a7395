"""Reference numbers for veila-data/tests/it/real_data.rs, computed independently with numpy (+ PyYAML)
from the real sample files in ../shared/data/real (not copied into the repository).

Run from the repository root:  python3 veila-data/tests/data/make_golden_real.py
Writes veila-data/tests/data/golden_real.json.
"""
import json
import os

import numpy as np
import yaml
from PIL import Image

ROOT = os.path.join(os.path.dirname(__file__), "../../../../shared/data/real")
out = {"_generator": "veila-data/tests/data/make_golden_real.py (numpy %s)" % np.__version__}


def kitti_calib(path):
    d = {}
    for line in open(path):
        if ":" in line:
            k, v = line.split(":", 1)
            d[k.strip()] = np.array([float(x) for x in v.split()])
    return d


for fid in ["000000", "000001"]:
    pts = np.fromfile(f"{ROOT}/kitti/training/velodyne/{fid}.bin", dtype="<f4").reshape(-1, 4)
    c = kitti_calib(f"{ROOT}/kitti/training/calib/{fid}.txt")
    P2 = c["P2"].reshape(3, 4)
    R0 = np.eye(4)
    R0[:3, :3] = c["R0_rect"].reshape(3, 3)
    Tr = np.eye(4)
    Tr[:3, :] = c["Tr_velo_to_cam"].reshape(3, 4)
    W, H = Image.open(f"{ROOT}/kitti/training/image_2/{fid}.png").size
    X = np.c_[pts[:, :3].astype(np.float64), np.ones(len(pts))]
    cam = (R0 @ Tr @ X.T)            # rectified camera frame
    img = P2 @ cam                   # projective image coordinates
    w = img[2]
    ok = w > 0.1
    u = img[0, ok] / w[ok]
    v = img[1, ok] / w[ok]
    inside = (u >= -0.5) & (u < W - 0.5) & (v >= -0.5) & (v < H - 0.5)
    out[f"kitti_{fid}"] = {"points": int(len(pts)), "width": W, "height": H,
                           "in_image_2": int(inside.sum())}

# SemanticKITTI histogram through learning_map
cfg = yaml.safe_load(open(f"{ROOT}/semantickitti/semantic-kitti.yaml"))
lm = cfg["learning_map"]
lut = np.zeros(1 << 16, dtype=np.int64)
for k, v in lm.items():
    lut[k] = v
for fid in ["000000", "000001"]:
    pts = np.fromfile(f"{ROOT}/semantickitti/sequences/00/velodyne/{fid}.bin", dtype="<f4").reshape(-1, 4)
    lab = np.fromfile(f"{ROOT}/semantickitti/sequences/00/labels/{fid}.label", dtype="<u4")
    train = lut[lab & 0xFFFF]
    hist = np.bincount(train, minlength=20)
    out[f"semantickitti_{fid}"] = {"points": int(len(pts)), "labels": int(len(lab)),
                                   "train_histogram": [int(x) for x in hist],
                                   "raw_semantic_ids": sorted(int(x) for x in np.unique(lab & 0xFFFF))}

# nuScenes: CAM_FRONT points in the image, devkit rule (depth > 1 m, 1 px margin) and the plain rule
calib = json.load(open(f"{ROOT}/nuscenes/calib/ca9a282c9e77460f8360f564131a8af5.json"))
pts = np.fromfile(f"{ROOT}/nuscenes/{calib['lidar']['file']}", dtype="<f4").reshape(-1, 5)
cam = calib["cameras"]["CAM_FRONT"]
T = np.array(cam["lidar2cam"]["matrix_4x4_row_major"])
K = np.array(cam["intrinsic_3x3"])
W, H = Image.open(f"{ROOT}/nuscenes/{cam['file']}").size
X = np.c_[pts[:, :3].astype(np.float64), np.ones(len(pts))]
pc = (T @ X.T)[:3]
d = pc[2]
uvw = K @ pc
ok = d > 1.0
u = uvw[0, ok] / uvw[2, ok]
v = uvw[1, ok] / uvw[2, ok]
devkit = (u > 1) & (u < W - 1) & (v > 1) & (v < H - 1)
plain = (u >= -0.5) & (u < W - 0.5) & (v >= -0.5) & (v < H - 0.5)
out["nuscenes_cam_front"] = {"points": int(len(pts)), "width": W, "height": H,
                             "in_image_devkit_rule": int(devkit.sum()),
                             "in_image_depth_gt_1m": int(plain.sum()),
                             "rings": int(len(np.unique(pts[:, 4]))),
                             "within_1m": int((np.linalg.norm(pts[:, :3].astype(np.float64), axis=1) < 1.0).sum())}

json.dump(out, open(os.path.join(os.path.dirname(__file__), "golden_real.json"), "w"), indent=1)
print(json.dumps(out, indent=1))
