"""Generated sequences ("generated"): simulated on first use, then read by the real loaders.

``make_source("generated", kind="lidar", num_frames=200)`` generates a LiDAR sequence in KITTI
layout (or ``kind="rgbd"``: an RGB-D sequence in TUM layout) into a cache folder keyed by the
generation parameters, reuses it when present, and returns its frames through
:class:`~frontends.sources.kitti.KittiSource` / :class:`~frontends.sources.tum.TumSource`, so the
generated data exercises exactly the code that reads real data.

Cache root: ``root`` if given, else ``$NEURAL_REMAP_SLAM_CACHE/generated``, else
``~/.cache/neural-remap-slam/generated``.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
from pathlib import Path
from typing import Any, ClassVar, Literal

import numpy as np

from common.atomic_io import write_text_atomic
from frontends.errors import DatasetError
from frontends.frame import Frame
from frontends.sources.base import SensorKind, Source

log = logging.getLogger(__name__)

GENERATOR_VERSION = 2
"""Bump when the generator's output changes, so stale cache entries are not reused."""

LIDAR_SEQUENCE = "00"
RGBD_SEQUENCE = "room"


def default_cache_root() -> Path:
    """Where generated sequences are cached when no ``root`` is given."""
    env = os.environ.get("NEURAL_REMAP_SLAM_CACHE")
    base = Path(env).expanduser() if env else Path.home() / ".cache" / "neural-remap-slam"
    return base / "generated"


def _cache_key(params: dict[str, Any]) -> str:
    text = json.dumps(params, sort_keys=True, default=str)
    return hashlib.sha1(text.encode()).hexdigest()[:12]


class GeneratedSource(Source):
    """A generated LiDAR (``kind="lidar"``) or RGB-D (``kind="rgbd"``) sequence.

    Args:
        kind: ``"lidar"`` (street, KITTI layout) or ``"rgbd"`` (room, TUM layout).
        root: cache root (see module docstring).
        num_frames: frames to generate.
        seed: seed of scene and noise.
        frames: optional slice of the generated frames.
        trajectory: LiDAR only: ``"loop"`` or ``"kitti"`` (a window of a real KITTI trajectory,
            needs ``kitti_poses`` and ``kitti_calib``; ``start``/``step`` select it).
        azimuth_steps: LiDAR firings per revolution (2048 ~ HDL-64E; lower for speed).
        terrain_relief_m: LiDAR only: height of hills beside the road (0: none; the key is then
            left out of the cache key, so sequences generated before the option are reused).
        street_style: LiDAR only: ``standard``, ``sparse`` or ``periodic`` street
            (:func:`frontends.generate.street.street_scene`).
        range_noise_m, dropout: LiDAR only: std-dev of the range noise and the probability
            that a return is lost. Like ``terrain_relief_m``, each of these three is in the cache
            key only when it differs from its default.
        width, height: RGB-D image size.
        workers: generation processes (None: up to 2).
        loader_options: extra keyword arguments for the wrapped KITTI/TUM loader.

    Frames, ground truth and ``gt_mesh_path`` come from the wrapped loader and the generated
    ``gt_mesh.ply`` (same world frame as the ground-truth poses). ``sequence_dir`` is the
    generated sequence folder.
    """

    sensor: ClassVar[SensorKind] = "lidar"

    def __new__(cls, kind: Literal["lidar", "rgbd"] = "lidar", **kwargs: Any) -> GeneratedSource:
        if cls is GeneratedSource and kind == "rgbd":
            cls = GeneratedRgbdSource
        return super().__new__(cls)

    def __init__(
        self,
        kind: Literal["lidar", "rgbd"] = "lidar",
        *,
        root: str | Path | None = None,
        num_frames: int = 200,
        seed: int = 0,
        frames: slice | None = None,
        trajectory: Literal["loop", "kitti"] = "loop",
        kitti_poses: str | Path | None = None,
        kitti_calib: str | Path | None = None,
        start: int = 0,
        step: int = 1,
        azimuth_steps: int = 2048,
        terrain_relief_m: float = 0.0,
        street_style: str = "standard",
        range_noise_m: float = 0.02,
        dropout: float = 0.02,
        width: int = 640,
        height: int = 480,
        workers: int | None = None,
        loader_options: dict[str, Any] | None = None,
    ) -> None:
        if kind not in ("lidar", "rgbd"):
            raise DatasetError(f"generated source: unknown kind '{kind}'; choose 'lidar' or 'rgbd'")
        super().__init__(f"generated-{kind}", frames)
        cache_root = Path(root).expanduser() if root is not None else default_cache_root()
        if kind == "lidar":
            params: dict[str, Any] = {
                "kind": kind,
                "num_frames": num_frames,
                "seed": seed,
                "trajectory": trajectory,
                "azimuth_steps": azimuth_steps,
            }
            if terrain_relief_m != 0.0:
                params["terrain_relief_m"] = float(terrain_relief_m)
            if street_style != "standard":
                params["street_style"] = street_style
            if range_noise_m != 0.02:
                params["range_noise_m"] = float(range_noise_m)
            if dropout != 0.02:
                params["dropout"] = float(dropout)
            if trajectory == "kitti":
                if kitti_poses is None or kitti_calib is None:
                    raise DatasetError(
                        "generated source: trajectory='kitti' needs kitti_poses=<poses/NN.txt> "
                        "and kitti_calib=<sequences/NN/calib.txt>"
                    )
                params.update(
                    kitti_poses=str(Path(kitti_poses).expanduser().resolve()),
                    kitti_calib=str(Path(kitti_calib).expanduser().resolve()),
                    start=start,
                    step=step,
                )
        else:
            params = {
                "kind": kind,
                "num_frames": num_frames,
                "seed": seed,
                "width": width,
                "height": height,
            }
        params["version"] = GENERATOR_VERSION
        self.cache_dir = cache_root / f"{kind}-{_cache_key(params)}"
        self._cache_setting = (
            "--root / source.root" if root is not None else "the NEURAL_REMAP_SLAM_CACHE variable"
        )
        self._params = params
        self._ensure_generated(workers)
        self.inner = self._open_loader(loader_options or {})

    # --- generation -------------------------------------------------------------------------

    @property
    def sequence_dir(self) -> Path:
        """The generated sequence folder (KITTI ``sequences/00`` or the TUM folder)."""
        return self.cache_dir / "sequences" / LIDAR_SEQUENCE

    def _generate(self, workers: int | None) -> None:
        from frontends.generate import generate_lidar_sequence
        from frontends.generate.lidar import LidarConfig

        p = self._params
        lidar = LidarConfig(
            azimuth_steps=p["azimuth_steps"],
            range_noise_m=p.get("range_noise_m", 0.02),
            dropout=p.get("dropout", 0.02),
        )
        generate_lidar_sequence(
            self.cache_dir,
            sequence=LIDAR_SEQUENCE,
            num_frames=p["num_frames"],
            trajectory=p["trajectory"],
            kitti_poses=p.get("kitti_poses"),
            kitti_calib=p.get("kitti_calib"),
            start=p.get("start", 0),
            step=p.get("step", 1),
            seed=p["seed"],
            lidar=lidar,
            terrain_relief_m=p.get("terrain_relief_m", 0.0),
            street_style=p.get("street_style", "standard"),
            workers=workers,
        )

    def _ensure_generated(self, workers: int | None) -> None:
        if self.sequence_dir.is_dir():
            log.info("%s: reusing %s", self.name, self.sequence_dir)
            return
        log.info("%s: generating %s", self.name, self.sequence_dir)
        try:
            try:
                self._generate(workers)
            except DatasetError:
                if not self.sequence_dir.is_dir():  # not a concurrent generation finished first
                    raise
            params_file = self.cache_dir / "params.json"
            text = json.dumps(self._params, indent=2, sort_keys=True) + "\n"
            write_text_atomic(params_file, text)
        except OSError as exc:  # a read-only cache, or a file where the cache folder should be
            raise DatasetError(
                f"generated data cache {self.cache_dir}: cannot write it "
                f"({exc.strerror or exc}); set {self._cache_setting} to a writable folder"
            ) from None

    def _open_loader(self, options: dict[str, Any]) -> Source:
        from frontends.sources.kitti import KittiSource

        options = {"correct_vertical_angle": False, **options}
        return KittiSource(self.cache_dir, LIDAR_SEQUENCE, **options)

    # --- forwarding to the real loader ------------------------------------------------------

    def _num_raw_frames(self) -> int:
        return self.inner._num_raw_frames()

    def _load(self, raw_index: int) -> Frame:
        return self.inner._load(raw_index)

    def _raw_gt_poses(self) -> np.ndarray | None:
        return self.inner._raw_gt_poses()

    def data_choices(self) -> dict[str, Any]:
        return self.inner.data_choices()

    @property
    def gt_mesh_path(self) -> Path | None:
        path = self.sequence_dir / "gt_mesh.ply"
        return path if path.is_file() else None


class GeneratedRgbdSource(GeneratedSource):
    """The ``kind="rgbd"`` variant of :class:`GeneratedSource` (TUM layout, read by TumSource)."""

    sensor: ClassVar[SensorKind] = "rgbd"

    @property
    def sequence_dir(self) -> Path:
        return self.cache_dir / RGBD_SEQUENCE

    def _generate(self, workers: int | None) -> None:
        from frontends.generate import generate_rgbd_sequence

        p = self._params
        generate_rgbd_sequence(
            self.sequence_dir,
            num_frames=p["num_frames"],
            seed=p["seed"],
            width=p["width"],
            height=p["height"],
            workers=workers,
        )

    def _open_loader(self, options: dict[str, Any]) -> Source:
        from frontends.generate import INTRINSICS_FILE, read_intrinsics
        from frontends.sources.tum import TumSource

        intrinsics, depth_scale = read_intrinsics(self.sequence_dir / INTRINSICS_FILE)
        options = {"intrinsics": intrinsics, "depth_scale": depth_scale, **options}
        return TumSource(self.cache_dir, RGBD_SEQUENCE, **options)
