"""Type hints and documentation of the native module ``veila._veila`` (re-exported by ``veila``)."""

from os import PathLike
from typing import Dict, List, Optional, Sequence, Tuple, Union

import numpy as np
import numpy.typing as npt

_Path = Union[str, PathLike]
_Points = npt.NDArray[np.floating]

PROTOCOLS: List[str]
"""The protocol names: ``r2dm``, ``text2lidar``, ``lidargen``, ``lidm``, ``lidm-nuscenes``."""

SENSOR_PRESETS: List[str]
"""The sensor presets ``project`` and ``unproject`` take (``veila_geom::SensorPreset::ALL``):
``hdl64e``, ``hdl32e``, ``hdl32e-per-beam``."""

def prepare_scan(points: _Points, protocol: str = "r2dm") -> npt.NDArray[np.float64]:
    """The points a protocol's metric sees for one raw scan.

    ``points`` is ``(N, 3+)`` (x, y, z, further columns ignored), float32 or float64. The scan goes
    through the peer's projection to its range-image grid (nearest point per pixel), its range caps
    and, for LiDARGen and LiDM, its normalised range image and back. Returns ``(M, 3)`` float64.
    Raises ``ValueError`` on a non-finite coordinate or an unknown protocol.
    """

def points_from_image(image: npt.NDArray[np.floating], protocol: str = "r2dm") -> List[npt.NDArray[np.float64]]:
    """The points of each sample of a peer's generated range-image array.

    Layouts: ``r2dm`` / ``text2lidar``: range in metres, ``(H, W)``, ``(C, H, W)`` or ``(N, C, H, W)``
    with ``C`` 1 or 5 (``[range, x, y, z, reflectance]``, R2DM's sample files); ``lidargen``:
    channel 0 is ``log2(r + 1) / 6`` in ``[0, 1]``; ``lidm`` / ``lidm-nuscenes``: ``(H, W)``,
    ``(N, H, W)`` or ``(N, 1, H, W)`` in ``[0, 1]`` (LiDM's ``.npz`` batches). One ``(M, 3)`` array per
    sample.
    """

def score(
    generated: Sequence[npt.NDArray[np.floating]],
    reference: Sequence[npt.NDArray[np.floating]],
    protocol: str = "r2dm",
    region: str = "all",
    generated_images: bool = False,
    reference_images: bool = False,
) -> Dict[str, float]:
    """JSD and MMD of a protocol's whole pipeline: ``{"jsd": ..., "mmd": ...}`` (raw values; R2DM and
    LiDM print the MMD multiplied by 1e4).

    Each element of ``generated`` / ``reference`` is a raw scan ``(N, 3+)``, or, with
    ``*_images=True``, a peer range-image array (see :func:`points_from_image`). ``region`` is
    ``all``, ``front`` (x > 0) or ``rear``.
    """

def jsd_raw(generated: Sequence[_Points], reference: Sequence[_Points], region: str = "all") -> float:
    """R2DM's BEV JSD (Jensen-Shannon distance) on the raw points: no projection, no range caps."""

def mmd_raw(generated: Sequence[_Points], reference: Sequence[_Points], region: str = "all") -> float:
    """R2DM's BEV MMD (Gaussian kernel, sigma 0.5) on the raw points: no projection, no range caps."""

def chamfer_distance(a: _Points, b: _Points) -> float:
    """Chamfer distance in PyTorch3D's convention: mean squared nearest distances, both ways, summed."""

def frechet_distance(
    a: npt.NDArray[np.float64], b: npt.NDArray[np.float64], newton_schulz: Optional[int] = None
) -> float:
    """Fréchet distance of two feature matrices (rows = samples; numpy covariance, exact matrix square
    root). ``newton_schulz=k`` uses k Newton-Schulz iterations instead and raises ``ValueError`` when
    they diverge (rank-deficient covariances)."""

def project(
    points: _Points,
    intensity: Optional[Sequence[float]] = None,
    sensor: str = "hdl64e",
    rows: Optional[int] = None,
    cols: Optional[int] = None,
    rings: Optional[Sequence[int]] = None,
) -> Dict[str, np.ndarray]:
    """Veila's spherical projection (a sensor of ``SENSOR_PRESETS``, optionally on another grid):
    ``{"range": (H, W) float32 metres, 0 where empty, "intensity": (H, W), "mask": (H, W) bool}``.
    Nearest point wins; points outside the field of view are dropped. ``rings`` (one beam index per
    point, as nuScenes stores it) places the points of ``hdl32e-per-beam``, which drops points
    without one."""

def unproject(
    range: npt.NDArray[np.float32],
    intensity: Optional[npt.NDArray[np.float32]] = None,
    sensor: str = "hdl64e",
) -> Tuple[npt.NDArray[np.float32], npt.NDArray[np.float32]]:
    """Points ``(M, 3)`` and intensities ``(M,)`` of a range image on the sensor's grid (one point per
    pixel with a positive range), the inverse of :func:`project` up to the pixel's angles."""

def read_points(path: _Path, keep_nan_intensity: bool = False) -> Tuple[npt.NDArray[np.float32], npt.NDArray[np.float32]]:
    """Reads a KITTI ``.bin``, nuScenes ``.pcd.bin``, PLY or Veila range EXR (detected from the content):
    ``(xyz (N, 3), intensity (N,))``. Non-finite points are dropped; with ``keep_nan_intensity`` a point
    whose intensity alone is NaN is kept (what geometry metrics need)."""

def read_sample_arrays(path: _Path) -> Dict[str, npt.NDArray[np.float32]]:
    """The float arrays of a peer's ``.npy`` / ``.npz`` sample set, by name (``arr_0`` ...). Pickles
    (``.pth``, ``.pkl``, object arrays ...) are refused with ``ValueError`` naming the file."""

def read_calibration(
    path: _Path, width: int, height: int, camera: Optional[str] = None
) -> Tuple[npt.NDArray[np.float32], npt.NDArray[np.float32]]:
    """The camera of a KITTI object, KITTI odometry / SemanticKITTI or nuScenes-JSON calibration file for
    an image of ``width x height``: ``(K (3, 4), cam_from_lidar (4, 4))``. ``camera`` is a KITTI
    projection index (``"0"`` to ``"3"``, default ``"2"`` = image_2) or a nuScenes channel (default
    ``"CAM_FRONT"``); the same reader as the ``veila`` binary's."""

def read_image(path: _Path) -> npt.NDArray[np.uint8]:
    """A PNG or JPEG image as ``(H, W, 3)`` uint8 RGB (the input :func:`generate` takes)."""

def generate(
    image: npt.NDArray[np.uint8],
    intrinsics: npt.NDArray[np.float32],
    cam_from_lidar: npt.NDArray[np.float32],
    steps: Optional[int] = None,
    seed: int = 0,
    model_dir: Optional[_Path] = None,
    sampler: Optional[str] = None,
    guidance: Optional[float] = None,
    start_t: Optional[float] = None,
) -> Dict[str, np.ndarray]:
    """Generates a 360° LiDAR scan from one RGB image ``(H, W, 3)`` uint8 and its calibration
    (``intrinsics`` ``(3, 3)`` or ``(3, 4)``, ``cam_from_lidar`` ``(4, 4)``), with the model bundled in
    the wheel (or the bundle folder ``model_dir``). ``sampler`` (``"ddpm"``, ``"ddim"`` or ``"dpm"``),
    ``steps``, ``guidance`` (0 to 20) and ``start_t`` (a bundle with a prior mean network: the level
    the draw starts from, above 0 to 1) override the bundle's sampler as ``veila generate``'s flags
    do; a value outside its range raises ``ValueError``. Same inputs and seed give the same scan, byte
    for byte the one ``veila generate`` writes for that image, calibration, sampler and seed. Returns
    ``{"points": (M, 3), "intensity": (M,), "range": (rows, cols), "mask": (rows, cols)}``, all in
    the LiDAR frame of ``cam_from_lidar`` (a nuScenes LiDAR, y forward, included)."""
