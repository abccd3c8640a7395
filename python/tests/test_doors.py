"""One image-to-scan pipeline behind every door: the wheel's ``generate`` gives, byte for byte, the
scan that the ``veila`` binary writes (``scan_000.bin``) for the same image, calibration and seed, on
the real KITTI and nuScenes samples (``veila-cli/tests/doors.rs`` checks the binary against the Rust
library). The binary is the one ``cargo test`` builds in ``target/debug`` (CI runs it before pytest on
the same checkout, and the wheel shares that ``target/``); the test skips when it or
``../shared/data/real`` is absent."""

import json
import os
import subprocess
from pathlib import Path

import numpy as np
import pytest

import veila

REPO = Path(__file__).resolve().parents[2]
REAL = REPO.parent / "shared" / "data" / "real"
VEILA = REPO / "target" / "debug" / ("veila.exe" if os.name == "nt" else "veila")
MODEL = REPO / "models" / "default"


def first_file(folder):
    return sorted(folder.iterdir())[0]


def rig(name):
    """``(image, calibration, camera, quarter turns into the model frame)`` of a real sample."""
    if name == "kitti":
        k = REAL / "kitti" / "training"
        return k / "image_2" / "000001.png", k / "calib" / "000001.txt", "2", 0
    n = REAL / "nuscenes"
    return first_file(n / "samples" / "CAM_FRONT"), first_file(n / "calib"), "CAM_FRONT", 1


@pytest.mark.skipif(not REAL.is_dir(), reason=f"{REAL} is absent")
@pytest.mark.skipif(not VEILA.is_file(), reason=f"{VEILA} is absent (run `cargo test` or `cargo build` first)")
@pytest.mark.parametrize("name", ["kitti", "nuscenes"])
def test_generate_gives_the_cli_scan_byte_for_byte(name, tmp_path):
    image_path, calib, camera, turns = rig(name)
    out = tmp_path / "cli"
    env = {k: v for k, v in os.environ.items() if k != "VEILA_MODEL"}
    run = subprocess.run(
        [str(VEILA), "generate", "--quiet", "--image", str(image_path), "--calib", str(calib),
         "--camera", camera, "--model", str(MODEL), "--seed", "0", "--out", str(out)],
        env=env, capture_output=True, text=True,
    )
    assert run.returncode == 0, run.stderr
    report = json.loads((out / "generate.json").read_text())
    assert report["model_frame_quarter_turns"] == turns

    image = veila.read_image(image_path)
    h, w = image.shape[:2]
    k, t = veila.read_calibration(calib, w, h, camera)
    got = veila.generate(image, k, t, seed=0)
    # KITTI .bin: little-endian float32 x, y, z, intensity per point
    mine = np.column_stack([got["points"], got["intensity"]]).astype("<f4").tobytes()
    want = (out / "scan_000.bin").read_bytes()
    assert len(got["points"]) > 1000
    assert mine == want, f"{name}: {len(mine)} bytes from Python, {len(want)} from the CLI"
