"""``python -m slam.run ... --map RUN_DIR``: a new session in an existing map's frame.

The map folder's ``map.npz`` (its latents and session section; never its scans) is loaded with
the run's own prior and device (never what its header names) and checked before any frame is
read: its sensor, its place descriptors, voxel size and latent storage (a LiDAR run whose voxel
size comes from its first scan is checked after that scan). The run goes
into ``OUT/session`` (a complete run folder of its own) and is relocalised live
(:mod:`slam.algorithm.merge.relocalise`): its first submap, and each later one until one
verifies, is matched against the stored submaps and registered to the surface decoded from their
latents. From then on the run's pose graph, poses and map are in the map's frame
(``metrics.json`` of the session says where it was placed). A run that starts outside the
stored map joins it when it enters it.

After the last frame the session and the map are merged by
:func:`slam.algorithm.merge.merge.merge_sessions` (every submap of the session against every stored
one, one pose graph over all sessions, the remap), and ``OUT`` receives what ``slam.merge``
writes: poses of every session in the map's frame, ``sessions.csv`` (the map's sessions, then
the new one), ``loops.csv``, ``map.npz``, ``mesh.ply``, ``metrics.json`` and the recording. When
no submap of the new run verifies against the map, the run ends with one line saying so and exit
status 1; its own run folder ``OUT/session`` is kept (nothing is lost: ``python -m slam.merge``
can join it later, e.g. with a run linking both).

With ``--localise`` the run only localises in the map: its run folder is ``OUT`` itself, its poses
are in the map's frame with a status per frame (``localisation.csv``), no live submap is encoded
and no map, mesh or merge is written.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from frontends.errors import DatasetError
from slam.algorithm.merge.inputs import LATENT_STORAGE_FIELDS

if TYPE_CHECKING:
    from slam.algorithm.merge.relocalise import Relocaliser


def load_map_folder(folder: Path, cfg) -> tuple:
    """``(SessionInput, NeuralMap)`` of ``--map``, decoded with the run's own prior and device;
    refuses a map the run cannot join (another sensor, no place descriptors, other map
    settings) before any frame is read."""
    from slam.app.merge_cli import load_run

    previous = load_run(folder, cfg.mapping)
    stored = previous[0].session
    if not stored.descriptors:
        raise DatasetError(
            f"--map {folder}: the map holds no place descriptors (its run had loop closure "
            "off), so no run can be relocalised in it; re-run it with loop_closure.enabled=true"
        )
    sensor = run_sensor(cfg)
    if sensor is not None and stored.sensor != sensor:
        raise DatasetError(
            f"--map {folder}: the map was made with the {stored.sensor or 'unknown'} sensor and "
            f"this run reads {sensor}; continue it with a run of the same sensor"
        )
    check_config(previous[1], cfg, folder, before_first_scan=True)
    return previous


def run_sensor(cfg) -> str | None:
    """The sensor (``lidar``/``rgbd``) the run's source will read, from its config alone."""
    from frontends.sources import source_class

    if cfg.source.dataset == "generated":
        return cfg.generated.kind
    try:
        return str(source_class(cfg.source.dataset).sensor)
    except (DatasetError, AttributeError):
        return None


@dataclass
class ContinuedMap:
    """What a ``--map`` run needs of the map it continues while it runs.

    Attributes:
        relocaliser: places the run's submaps in the map (:mod:`slam.algorithm.merge.relocalise`).
        mesh_path: the map's mesh, shown beneath the run in its recording.
        localise_only: ``--localise``: poses in the map's frame only, no map and no merge.
    """

    relocaliser: Relocaliser
    mesh_path: Path
    localise_only: bool = False


def continued_map(previous: tuple, folder: Path, cfg, localise_only: bool) -> ContinuedMap:
    """The :class:`ContinuedMap` of the loaded map folder ``folder`` for the run config
    ``cfg``."""
    from slam.algorithm.merge.relocalise import Relocaliser
    from slam.assembly.threads import apply_thread_budget

    stored, stored_map = previous
    relocaliser = Relocaliser(stored, stored_map, localise=cfg.relocalise)
    if localise_only:  # every frame's registration then finds the surfaces ready
        # under the run's thread budget: torch's default pool spans every core, and on a busy
        # machine its threads wait for each other at every operation (the full-length street
        # map took 324 s at load 5 that way, 47 s on one thread); the odometry is idle yet, so
        # the surfaces are decoded on the threads of the whole-map mesh after a run
        threads = apply_thread_budget(cfg)
        relocaliser.decode_map(threads.mesh_threads)
    return ContinuedMap(relocaliser, folder / "mesh.ply", localise_only)


def check_config(neural_map, cfg, folder: Path, before_first_scan: bool) -> None:
    """One-line :class:`DatasetError` when the run's map settings differ from the stored map's,
    or when it would make no place descriptors (loop closure off) to be relocalised by."""
    if not cfg.loop_closure.enabled:
        raise DatasetError(
            f"--map {folder}: loop closure is off, so this run has no place descriptors to be "
            "relocalised in the map; run with loop_closure.enabled=true"
        )
    mapping = cfg.mapping
    scaled = cfg.source.lidar.scale_from_first_scan and (
        "voxel_size_m" not in mapping.model_fields_set
    )
    if not (before_first_scan and scaled) and mapping.voxel_size_m != neural_map.voxel_size_m:
        raise DatasetError(
            f"--map {folder}: voxel size {neural_map.voxel_size_m} m differs from this run's "
            f"{mapping.voxel_size_m} m; run with --set mapping.voxel_size_m="
            f"{neural_map.voxel_size_m}"
        )
    stored = neural_map.cfg
    if any(getattr(stored, key) != getattr(mapping, key) for key in LATENT_STORAGE_FIELDS):
        raise DatasetError(
            f"--map {folder}: latent storage ({', '.join(LATENT_STORAGE_FIELDS)}) differs from "
            "this run's; run with the map's mapping settings"
        )


def merge_into(previous: tuple, map_folder: Path, session_folder: Path, out: Path, viz: bool, cfg):
    """Relocalise and merge the finished run in ``session_folder`` (made with the run config
    ``cfg``) into the stored map; write the merged run into ``out``; returns its metrics."""
    from slam.algorithm.merge.merge import MergeError
    from slam.app.merge_cli import load_run, merge_runs

    start = time.perf_counter()
    current = load_run(session_folder, cfg.mapping)
    try:
        metrics: dict[str, Any] = merge_runs(
            [previous, current], [map_folder, session_folder], out, viz, start
        )
    except MergeError as exc:
        raise DatasetError(
            f"--map {map_folder}: this run could not be relocalised in it ({exc}); the run alone "
            f"is kept in {session_folder}"
        ) from None
    return metrics


def check_placed(metrics: dict[str, Any], map_folder: Path, folder: Path) -> None:
    """A ``--localise`` run that no submap placed in the map ends with one line (its poses are
    the odometry's, not in the map's frame)."""
    placed = metrics.get("relocalisation", {})
    if not placed.get("relocalised"):
        raise DatasetError(
            f"--map {map_folder}: this run was never placed in it ({placed.get('submaps_tried', 0)}"
            f" submaps tried; does it pass through the mapped place?); its odometry-only poses "
            f"are in {folder}"
        )
