#!/usr/bin/env python3
"""numpy reference of `veila_metrics::segmentation` on real SemanticKITTI labels (issue 56).

Reads `semantic-kitti.yaml`'s `learning_map` and the `.label` files of sequence 00 under
`../shared/data/real/semantickitti` (relative to the repository root, or the folder given as the
first argument), maps the ground truth to train ids, makes a deterministic prediction from it
(for point i of a scan, h = (i * 2654435761) mod 2^32: 12 % of the points (h mod 100 < 12) get
(7 gt + i) mod 20, 3 % (12 <= h mod 100 < 15) get 0; afterwards every 19 becomes 18), and scores
it the way semantic-kitti-api's `auxiliary/np_ioueval.py` does: one confusion matrix (rows
prediction, columns ground truth) over both scans, the columns of class 0 zeroed, IoU =
TP / (TP + FP + FN + 1e-15), mIoU over classes 1-19, accuracy = sum TP / (sum over classes 1-19 of
TP + FP + 1e-15). It also writes the mean over the classes 1-19 present in the ground truth.

Writes `segmentation_reference.json` next to this script; `veila-metrics/tests/it/segmentation.rs`
must match it within 1e-6. Needs numpy only (the yaml block is read by hand).

    python3 veila-metrics/tests/data/segmentation_reference.py
"""

import json
import os
import re
import sys

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.abspath(os.path.join(HERE, "..", "..", ".."))
NUM_CLASSES = 20
IGNORE = [0]
SCANS = ["000000", "000001"]


def learning_map(yaml_path):
    pairs, inside = [], False
    for line in open(yaml_path):
        if re.match(r"^learning_map:", line):
            inside = True
            continue
        if inside:
            m = re.match(r"^\s+(\d+)\s*:\s*(\d+)", line)
            if m:
                pairs.append((int(m.group(1)), int(m.group(2))))
            elif re.match(r"^\S", line):
                break
    return pairs


def perturb(gt):
    i = np.arange(gt.size, dtype=np.uint64)
    h = (i * np.uint64(2654435761)) % np.uint64(2**32)
    r = h % np.uint64(100)
    pred = gt.astype(np.int64).copy()
    wrong = r < 12
    pred[wrong] = (7 * gt[wrong].astype(np.int64) + i[wrong].astype(np.int64)) % NUM_CLASSES
    pred[(r >= 12) & (r < 15)] = 0
    pred[pred == 19] = 18
    return pred


def main():
    data = sys.argv[1] if len(sys.argv) > 1 else os.path.join(ROOT, "..", "shared", "data", "real", "semantickitti")
    pairs = learning_map(os.path.join(data, "semantic-kitti.yaml"))
    lut = np.zeros(1 << 16, dtype=np.int64)
    for raw, train in pairs:
        lut[raw] = train
    conf = np.zeros((NUM_CLASSES, NUM_CLASSES), dtype=np.int64)
    counts = []
    for scan in SCANS:
        raw = np.fromfile(os.path.join(data, "sequences", "00", "labels", scan + ".label"), dtype="<u4")
        gt = lut[raw & 0xFFFF]
        pred = perturb(gt)
        np.add.at(conf, (pred, gt), 1)
        counts.append(int(raw.size))
    c = conf.copy()
    c[:, IGNORE] = 0
    tp = np.diag(c)
    fp = c.sum(axis=1) - tp
    fn = c.sum(axis=0) - tp
    include = [k for k in range(NUM_CLASSES) if k not in IGNORE]
    iou = tp / (tp + fp + fn + 1e-15)
    miou = float(np.mean(iou[include]))
    present = [k for k in include if c[:, k].sum() > 0]
    acc = float(tp.sum() / (tp[include].sum() + fp[include].sum() + 1e-15))
    out = {
        "scans": [f"sequences/00/labels/{s}.label" for s in SCANS],
        "points": counts,
        "learning_map": pairs,
        "confusion": conf.tolist(),
        "iou": iou.tolist(),
        "miou": miou,
        "present": present,
        "miou_present": float(np.mean(iou[present])),
        "accuracy": acc,
    }
    with open(os.path.join(HERE, "segmentation_reference.json"), "w") as f:
        json.dump(out, f, indent=1)
        f.write("\n")
    print(f"mIoU {miou:.6f} (present {out['miou_present']:.6f}, {len(present)} classes), accuracy {acc:.6f}")


if __name__ == "__main__":
    main()
