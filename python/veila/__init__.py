"""Veila from Python: LiDAR generation metrics exactly as the peers report them, projection, dataset
readers and image-to-scan generation, on numpy arrays.

Every number comes from the Rust crates of the Veila workspace (``veila-metrics``, ``veila-geom``,
``veila-data``, ``veila-diffusion``); this package converts arrays and errors.

Protocols (``PROTOCOLS``): ``r2dm``, ``text2lidar``, ``lidargen``, ``lidm``, ``lidm-nuscenes``. Each is a
peer's whole evaluation pipeline: its projection to its range-image grid, its range caps, then its JSD
and MMD. Raw scans scored this way give the peer's own number (checked to 1e-4 against numpy
reproductions of the peers' scripts).

>>> import numpy as np, veila
>>> scan = veila.read_points("000000.bin")[0]            # doctest: +SKIP
>>> veila.score([scan], [scan], protocol="r2dm")          # doctest: +SKIP
{'jsd': 0.0, 'mmd': 0.0}
"""

import os as _os

# candle's own thread pool keeps a worker spinning after each of its ops, on the cores that the
# engine's kernels (rayon) need next; the `veila` binary turns it off at start-up (training step
# 264 -> 236 ms, BENCHMARKS.md), and so does this import where the variable is not set already. The
# extension reads it at its first tensor operation, so it must be set before that.
_os.environ.setdefault("CANDLE_NUM_THREADS", "1")

from ._veila import (  # noqa: E402
    PROTOCOLS,
    SENSOR_PRESETS,
    chamfer_distance,
    frechet_distance,
    generate,
    jsd_raw,
    mmd_raw,
    points_from_image,
    prepare_scan,
    project,
    read_calibration,
    read_image,
    read_points,
    read_sample_arrays,
    score,
    unproject,
)

__all__ = [
    "PROTOCOLS",
    "SENSOR_PRESETS",
    "chamfer_distance",
    "frechet_distance",
    "generate",
    "jsd_raw",
    "mmd_raw",
    "points_from_image",
    "prepare_scan",
    "project",
    "read_calibration",
    "read_image",
    "read_points",
    "read_sample_arrays",
    "score",
    "unproject",
]
