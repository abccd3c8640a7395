"""Snowflake-return counts of the public reference LiDAR snowfall simulation (Hahner et al., CVPR 2022,
github.com/SysCV/LiDAR_snow_sim) on a real KITTI scan, for veila-data/tests/it/weather_real.rs.

Run by hand (not in CI), from the repository root, with numpy, scipy, PyYAML and tqdm installed:

    python3 veila-data/tests/data/snow_reference/compare_snow_reference.py --ref /path/to/LiDAR_snow_sim

`--ref` is a checkout of the reference repository (measured at commit af376b3); nothing of it is copied
here. The script imports the reference's own modules and calls them:
  * `tools.snowfall.sampling.dart_throwing` draws the 64 flake layers (Gunn-Marshall sizes, overlap
    rejection) with `np.random.default_rng(seed)`; layers are cached in `--work`.
  * `tools.snowfall.simulation.process_single_channel` simulates every channel, with the channel-to-layer
    order shuffled by `random.Random(seed)` as the reference's `augment(shuffle=True)` does. `augment`
    itself is not called: its last steps (the ground-fitted noise-floor dropout and the camera-FOV crop)
    only delete non-snow points or crop, and veila leaves both out deliberately. Flake returns (label 2)
    and intensity-only changes (label 1) are counted over the full 360 degree scan.

Inputs as the reference expects them: KITTI reflectance x 255; channel = ring from the nearest of 64
uniform elevations from -24.9 to +2.0 deg (veila's `BeamTable::hdl64e`, ring 0 lowest; the reference's
per-channel HDL-64 S3 calibration is applied by this index, as Robo3D does for KITTI);
beam divergence 3 mrad.

Variants (the reference code is never edited; each is a change of its inputs or a wrapper around one of
its functions, and every variant reuses the same occlusion lists):
  * `reference`: as published.
  * `no_focal`: per-channel intensity correction off (focal_slope = 0 in the calibration passed in).
  * `reset_power`: the power constant of the hard target is its own: the occlusion dict is reordered so
    the hard target (key -1) comes first, before any flake overwrites the constant.
  * `no_focal_reset_power`: both.
Writes `--out` (default: snow_reference.json next to this script).
"""
import argparse
import copy
import json
import os
import random
import sys
import time
import types

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
DEFAULT_SCAN = os.path.join(HERE, "../../../../../shared/data/real/kitti/training/velodyne/000000.bin")


def stub_modules():
    """Modules the reference imports at top level but that the two functions used here never call."""
    for name in ["matplotlib", "matplotlib.pyplot", "lib", "lib.OpenPCDet", "lib.OpenPCDet.pcdet",
                 "lib.OpenPCDet.pcdet.utils", "lib.OpenPCDet.pcdet.utils.calibration_kitti",
                 "tools.wet_ground", "tools.wet_ground.planes",
                 "tools.wet_ground.augmentation"]:
        if name not in sys.modules:
            sys.modules[name] = types.ModuleType(name)
    sys.modules["tools.wet_ground.planes"].calculate_plane = None
    sys.modules["tools.wet_ground.augmentation"].estimate_laser_parameters = None
    sys.modules["lib.OpenPCDet.pcdet.utils"].calibration_kitti = sys.modules[
        "lib.OpenPCDet.pcdet.utils.calibration_kitti"]


def kitti_rings(xyz):
    el = np.degrees(np.arctan2(xyz[:, 2], np.hypot(xyz[:, 0], xyz[:, 1])))
    table = -24.9 + 26.9 * np.arange(64) / 63.0
    return np.abs(el[:, None] - table[None, :]).argmin(axis=1)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--ref", required=True, help="checkout of SysCV/LiDAR_snow_sim")
    ap.add_argument("--scan", default=DEFAULT_SCAN)
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--rates", type=float, nargs="+", default=[1.0, 2.5], help="snowfall mm/h")
    ap.add_argument("--terminal-velocity", type=float, default=1.6)
    ap.add_argument("--work", default=os.path.join(HERE, "../../../../target/snow_reference"))
    ap.add_argument("--out", default=os.path.join(HERE, "snow_reference.json"))
    ap.add_argument("--merge", nargs="+", help="only merge these result files into --out")
    args = ap.parse_args()
    if args.merge:
        parts = [json.load(open(p)) for p in args.merge]
        results = parts[0]
        results["runs"] = [r for part in parts for r in part["runs"]]
        write(results, args.out)
        return

    sys.path.insert(0, os.path.abspath(args.ref))
    stub_modules()
    import yaml
    import tools.snowfall.sampling as sampling
    import tools.snowfall.simulation as simulation

    with open(os.path.join(args.ref, "calib", "20171102_64E_S3.yaml")) as f:
        channel_infos = yaml.safe_load(f)["lasers"]
    flat_infos = copy.deepcopy(channel_infos)
    for c in flat_infos:
        c["focal_slope"] = 0.0

    pts = np.fromfile(args.scan, dtype="<f4").reshape(-1, 4).astype(np.float64)
    pc = np.column_stack([pts[:, :3], pts[:, 3] * 255.0, kitti_rings(pts[:, :3])])
    divergence_deg = float(np.degrees(3e-3))

    original_get_occlusions = simulation.get_occlusions
    cache = {}

    def cached_get_occlusions(beam_angles, ranges_orig, root_path, particle_file, beam_divergence):
        key = (particle_file, len(ranges_orig), float(ranges_orig.sum()))
        if key not in cache:
            cache[key] = original_get_occlusions(beam_angles=beam_angles, ranges_orig=ranges_orig,
                                                 root_path=root_path, particle_file=particle_file,
                                                 beam_divergence=beam_divergence)
        occ = cache[key]
        if state["reset_power"]:
            occ = [dict([(-1, d[-1])] + [(k, v) for k, v in d.items() if k != -1]) for d in occ]
        return occ

    state = {"reset_power": False}
    simulation.get_occlusions = cached_get_occlusions

    results = {
        "_generator": "veila-data/tests/data/snow_reference/compare_snow_reference.py",
        "reference": "SysCV/LiDAR_snow_sim (commit of --ref checked by hand: af376b3)",
        "numpy": np.__version__,
        "scan": os.path.relpath(os.path.abspath(args.scan), os.path.abspath(os.path.join(HERE, "../../../.."))),
        "points": int(len(pc)),
        "terminal_velocity_m_s": args.terminal_velocity,
        "beam_divergence_rad": 3e-3,
        "runs": [],
    }
    variants = [("reference", channel_infos, False), ("no_focal", flat_infos, False),
                ("reset_power", channel_infos, True), ("no_focal_reset_power", flat_infos, True)]
    for rate in args.rates:
        r_eq = sampling.snowfall_rate_to_rainfall_rate(rate, args.terminal_velocity)
        occ = sampling.compute_occupancy(rate, args.terminal_velocity)
        for seed in args.seeds:
            prefix = f"gunn_{rate}_{args.terminal_velocity}_seed{seed}"
            npy = os.path.join(args.work, "training", "snowflakes", "npy")
            os.makedirs(npy, exist_ok=True)
            rng = np.random.default_rng(seed)
            flakes = 0
            t0 = time.time()
            for layer in range(1, 65):
                path = os.path.join(npy, f"{prefix}_{layer}.npy")
                if os.path.exists(path):
                    samples = np.load(path)
                else:
                    samples = sampling.dart_throwing(occ, r_eq, 80.0, rng, distribution="gunn")
                    np.save(path, samples)
                flakes += len(samples)
            t_sample = time.time() - t0
            order = list(range(64))
            random.Random(seed).shuffle(order)
            cache.clear()
            for name, infos, reset in variants:
                state["reset_power"] = reset
                t0 = time.time()
                labels = np.zeros(len(pc), dtype=np.int64)
                for ch in range(64):
                    _, idx, out = simulation.process_single_channel(
                        args.work, prefix, pc, divergence_deg, order, infos, ch)
                    labels[idx] = out[:, 4].astype(np.int64)
                run = {"snowfall_mm_h": rate, "seed": seed, "variant": name,
                       "flakes_per_layer_mean": flakes / 64.0,
                       "flake_returns": int((labels == 2).sum()),
                       "intensity_changed": int((labels == 1).sum()),
                       "seconds": round(time.time() - t0, 1), "sampling_seconds": round(t_sample, 1)}
                print(json.dumps(run), flush=True)
                results["runs"].append(run)
                with open(args.out + ".partial", "w") as f:
                    json.dump(results, f, indent=1)
    write(results, args.out)
    os.remove(args.out + ".partial")


def write(results, out):
    """Add the per-(rate, variant) mean and sample standard deviation of flake returns over seeds."""
    summary = {}
    for run in results["runs"]:
        summary.setdefault(f"{run['snowfall_mm_h']}/{run['variant']}", []).append(run["flake_returns"])
    results["summary"] = {k: {"mean": float(np.mean(v)), "std": float(np.std(v, ddof=1)) if len(v) > 1 else 0.0,
                              "n": len(v)} for k, v in sorted(summary.items())}
    with open(out, "w") as f:
        json.dump(results, f, indent=1)


if __name__ == "__main__":
    main()
