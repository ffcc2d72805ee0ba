"""TUM RGB-D sequences ("tum") and ICL-NUIM in its TUM-compatible release ("icl").

TUM layout (one folder per sequence)::

    rgb.txt, depth.txt          'timestamp rgb/<t>.png' lines
    associations.txt            optional, 'time path time path' (rgb and depth in either order)
    groundtruth.txt             optional, 't tx ty tz qx qy qz qw' (camera-to-world)
    rgb/*.png, depth/*.png      depth uint16 / 5000 = metres

Colour and depth are paired as TUM's ``associate.py`` pairs them (nearest within
``max_difference`` seconds, greedily unique) unless ``associations.txt`` exists; frames are then
paired with ground truth the same way. Every frame is fed to the pipeline whether or not it has
a ground-truth pose: frames without a pose within ``max_difference`` get ``T_W_S_gt = None`` (a
row of NaN in ``gt_poses``) and are left out of the scores only.

TUM intrinsics: the folder's ``intrinsics.txt`` (``fx fy cx cy width height depth_scale``, as
written by ``python -m frontends.generate``) when present, else the published calibration of the
camera named in the sequence (``freiburg1``/``fr1``, ``freiburg2``, ``freiburg3``), else TUM's
ROS default 525/525/319.5/239.5; an explicit ``intrinsics`` argument wins over all of them.

ICL-NUIM ("icl"): sequences ``lr-kt0..3`` (living room) and ``of-kt0..3`` (office), with a
trailing ``n`` for the noisy variant, are looked up as the folder names of the public releases
(``living_room_traj3n_frei_png``, ``traj0_frei_png``, ``lr_kt3n``, ...) or as a literal folder
name. The TUM-compatible folders hold ``rgb/``, ``depth/`` and ``associations.txt`` (depth first,
stamps are frame numbers) and the trajectory ``livingRoomN.gt.freiburg`` / ``trajN.gt.freiburg``
(or ``groundtruth.txt``), next to the images or in the root. A small layout with ``color/N.png``,
``depth/N.png`` and ``pose.txt`` (``tx ty tz qx qy qz qw`` a row, camera-to-world) is read too.

ICL-NUIM sign convention: the data was rendered by POV-Ray (left-handed), and the published
intrinsics are fx=481.2, fy=-480. Back-projecting with fy=-480 and applying the published poses
makes overlapping frames agree (checked on real frames, see tests/test_sources.py), i.e. the
published poses belong to camera coordinates with y pointing up. We normalise to the usual
right-handed camera (fy=+480, y down): points become ``F p`` with ``F = diag(1, -1, 1)`` and the
ground truth becomes ``F T F``. This is the same rigid geometry seen in a world frame mirrored in
y; the world is therefore the mirror image of ICL-NUIM's. Trajectories are written back in the
dataset's own frame (``IclSource.dataset_mirror``: ``F T F`` again), so evo compares them with
the release's ``*.gt.freiburg`` files directly; the mesh stays in the mirrored world (mirror it
with ``F`` to compare with the ICL-NUIM surface model).
"""

from __future__ import annotations

import dataclasses
import logging
import os
import re
from pathlib import Path

import numpy as np

from frontends.frame import Intrinsics
from frontends.sources._io import (
    DepthOptions,
    RgbdFrames,
    RgbdSource,
    associate,
    fail,
    frame_number,
    load_table,
    pose_from_translation_quaternion,
    read_stamped_paths,
    read_tum_trajectory,
    require_dir,
    require_file,
)

log = logging.getLogger(__name__)

TUM_INTRINSICS = Intrinsics(fx=525.0, fy=525.0, cx=319.5, cy=239.5, width=640, height=480)
"""TUM's recommended default intrinsics for the ROS-registered 640x480 images."""

TUM_CAMERA_INTRINSICS: dict[str, Intrinsics] = {
    "freiburg1": Intrinsics(fx=517.3, fy=516.5, cx=318.6, cy=255.3, width=640, height=480),
    "freiburg2": Intrinsics(fx=520.9, fy=521.0, cx=325.1, cy=249.7, width=640, height=480),
    "freiburg3": Intrinsics(fx=535.4, fy=539.2, cx=320.1, cy=247.6, width=640, height=480),
}
"""The published colour-camera calibrations of the TUM RGB-D benchmark (depth is registered to
colour), by the camera named in the sequence folder."""

_TUM_CAMERA = re.compile(r"(?:freiburg|fr)([123])(?![0-9])")


def tum_intrinsics_for(sequence: str) -> Intrinsics:
    """The published intrinsics of the TUM camera named in ``sequence`` (``freiburg2_xyz``,
    ``rgbd_dataset_freiburg3_office``, ``fr1_desk``), else TUM's ROS default 525/525."""
    match = _TUM_CAMERA.search(sequence.lower())
    return TUM_CAMERA_INTRINSICS[f"freiburg{match.group(1)}"] if match else TUM_INTRINSICS


ICL_INTRINSICS_RAW = Intrinsics(fx=481.2, fy=-480.0, cx=319.5, cy=239.5, width=640, height=480)
"""ICL-NUIM's published intrinsics (POV-Ray convention, negative fy)."""

FLIP_Y = np.diag([1.0, -1.0, 1.0, 1.0])


def _inside(folder: Path, list_file: Path, name: str, allow_outside: bool) -> Path:
    """``folder / name``, refused when a list file's entry leads out of the dataset folder
    (``../`` or an absolute path; links inside the folder are the user's choice) unless
    ``allow_outside``."""
    path = folder / name
    inside = os.path.normpath(path).startswith(os.path.normpath(folder) + os.sep)
    if allow_outside or inside:
        return path
    raise fail(
        list_file,
        f"entry '{name}' leaves the dataset folder {folder}",
        "fix the list, or set source.tum.allow_outside_paths: true if you trust it",
    )


def read_tum_pairs(folder: Path, max_difference: float, allow_outside: bool = False) -> RgbdFrames:
    """Colour/depth pairs of a TUM-layout folder (associations.txt, else rgb.txt + depth.txt,
    else rgb/ and depth/ images whose numeric names are their timestamps). Entries that leave
    ``folder`` are refused unless ``allow_outside``."""
    assoc = folder / "associations.txt"
    if assoc.is_file():
        return _read_associations(assoc, allow_outside)
    rgb_list, depth_list = folder / "rgb.txt", folder / "depth.txt"
    if rgb_list.is_file() or depth_list.is_file():
        rgb_stamps, rgb_names = read_stamped_paths(require_file(rgb_list, "TUM rgb.txt"))
        depth_stamps, depth_names = read_stamped_paths(require_file(depth_list, "TUM depth.txt"))
    else:
        rgb_stamps, rgb_names = _list_numbered(folder, "rgb")
        depth_stamps, depth_names = _list_numbered(folder, "depth")
    matches = associate(rgb_stamps, depth_stamps, max_difference)
    if not matches:
        raise fail(
            folder,
            f"no colour image has a depth image within {max_difference} s",
            "check rgb.txt/depth.txt or raise max_difference",
        )
    dropped = max(len(rgb_stamps), len(depth_stamps)) - len(matches)
    if dropped:
        log.warning(
            "%s: %d colour and %d depth images make %d pairs; %d frames dropped (no partner "
            "within %g s)",
            folder,
            len(rgb_stamps),
            len(depth_stamps),
            len(matches),
            dropped,
            max_difference,
        )
    return RgbdFrames(
        stamps=np.asarray([rgb_stamps[i] for i, _ in matches]),
        rgb=[_inside(folder, rgb_list, rgb_names[i], allow_outside) for i, _ in matches],
        depth=[_inside(folder, depth_list, depth_names[j], allow_outside) for _, j in matches],
    )


def _read_associations(path: Path, allow_outside: bool = False) -> RgbdFrames:
    stamps: list[float] = []
    rgb: list[Path] = []
    depth: list[Path] = []
    for line_no, line in enumerate(path.read_text().splitlines(), 1):
        text = line.split("#", 1)[0].strip()
        if not text:
            continue
        tokens = text.split()
        try:
            t1, p1, t2, p2 = float(tokens[0]), tokens[1], float(tokens[2]), tokens[3]
        except (ValueError, IndexError):
            raise fail(
                path, f"line {line_no} is not 'time path time path'", "regenerate associations.txt"
            ) from None
        if "depth" in p1 and "depth" not in p2:  # ICL-NUIM writes depth first
            t1, p1, t2, p2 = t2, p2, t1, p1
        stamps.append(t1)
        rgb.append(_inside(path.parent, path, p1, allow_outside))
        depth.append(_inside(path.parent, path, p2, allow_outside))
    if not stamps:
        raise fail(path, "associations file is empty", "regenerate associations.txt")
    return RgbdFrames(np.asarray(stamps), rgb, depth)


def _list_numbered(folder: Path, sub: str) -> tuple[np.ndarray, list[str]]:
    image_dir = require_dir(folder / sub, f"{sub}/ images (or {sub}.txt / associations.txt)")
    files = sorted(
        image_dir.glob("*.png"), key=lambda p: float(p.stem) if _is_number(p.stem) else 0
    )
    files = [p for p in files if _is_number(p.stem)]
    if not files:
        raise fail(image_dir, "no numbered .png images", "add rgb.txt and depth.txt")
    return np.asarray([float(p.stem) for p in files]), [f"{sub}/{p.name}" for p in files]


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def gt_for_pairs(
    name: str,
    pairs: RgbdFrames,
    gt_file: Path | None,
    max_difference: float,
    gt_transform: np.ndarray | None = None,
) -> np.ndarray | None:
    """Ground truth of the frames by timestamp, (N, 4, 4) (None without ``gt_file``): every
    frame is kept, frames without a pose within ``max_difference`` get a row of NaN."""
    if gt_file is None:
        return None
    gt_stamps, gt_poses = read_tum_trajectory(gt_file)
    if gt_transform is not None:
        gt_poses = gt_transform @ gt_poses @ gt_transform
    matches = associate(pairs.stamps, gt_stamps, max_difference)
    if not matches:
        raise fail(
            gt_file,
            f"no frame has a ground-truth pose within {max_difference} s",
            "use the ground truth of this sequence",
        )
    missing = len(pairs.stamps) - len(matches)
    if missing:
        log.warning(
            "%s: %d of %d frames have no ground-truth pose within %g; they are processed but "
            "not scored",
            name,
            missing,
            len(pairs.stamps),
            max_difference,
        )
    poses = np.full((len(pairs.stamps), 4, 4), np.nan)
    for i, j in matches:
        poses[i] = gt_poses[j]
    return poses


class _PairedSource(RgbdSource):
    """An RGB-D source over listed colour/depth pairs (each checked to exist)."""

    def _set_pairs(self, pairs: RgbdFrames, gt: np.ndarray | None) -> None:
        for path in (*pairs.depth, *pairs.rgb):
            if not path.is_file():
                raise fail(path, "listed image not found", "restore it or regenerate the lists")
        self._set_frames(pairs, gt)


def _find_sequence_folder(root: Path, candidates: list[str], what: str) -> Path:
    require_dir(root, f"the dataset root holding {what}")
    for name in candidates:
        folder = root / name
        if folder.is_dir():
            return folder
    raise fail(
        root,
        f"no sequence folder among {', '.join(dict.fromkeys(candidates))}",
        f"pass the root that holds {what}",
    )


def _folder_intrinsics(folder: Path) -> tuple[Intrinsics, float] | None:
    """``intrinsics.txt`` beside the images (intrinsics, depth scale), or None."""
    from frontends.generate.writers import INTRINSICS_FILE, read_intrinsics

    path = folder / INTRINSICS_FILE
    return read_intrinsics(path) if path.is_file() else None


class TumSource(_PairedSource):
    """A TUM RGB-D sequence.

    Args:
        root: folder holding the sequence folders.
        sequence: folder name, e.g. ``rgbd_dataset_freiburg1_desk`` or ``freiburg1_desk``.
        frames: optional slice of frames.
        intrinsics: camera intrinsics. Default: the folder's ``intrinsics.txt`` when present (as
            written by ``python -m frontends.generate``), else the published freiburg1/2/3
            calibration named by ``sequence``, else TUM's 525/525/319.5/239.5.
        depth_scale: depth PNG units per metre (None: ``intrinsics.txt``'s, else TUM's 5000).
        max_difference: association window in seconds (TUM's associate.py default 0.02).
        depth_options: how depth is lifted to points.
    """

    def __init__(
        self,
        root: str | Path,
        sequence: str,
        frames: slice | None = None,
        *,
        intrinsics: Intrinsics | dict | None = None,
        depth_scale: float | None = None,
        max_difference: float = 0.02,
        depth_options: DepthOptions | dict | None = None,
        allow_outside_paths: bool = False,
    ) -> None:
        root = Path(root).expanduser()
        folder = _find_sequence_folder(
            root, [sequence, f"rgbd_dataset_{sequence}"], "TUM sequence folders (rgb.txt, depth/)"
        )
        stored = _folder_intrinsics(folder)
        if depth_scale is None:
            depth_scale = stored[1] if stored is not None else 5000.0
        if not depth_scale > 0:
            where = folder / "intrinsics.txt" if stored is not None else folder
            raise fail(where, f"depth scale {depth_scale} is not positive", "pass units per metre")
        if intrinsics is None and stored is None and not _TUM_CAMERA.search(folder.name.lower()):
            log.warning(
                "%s: no intrinsics.txt and the folder name names no TUM camera (freiburg1/2/3); "
                "assuming TUM's 640x480 default fx=fy=525: add intrinsics.txt ('fx fy cx cy "
                "width height depth_scale') or set source.tum.intrinsics",
                folder,
            )
        if intrinsics is None:
            intrinsics = stored[0] if stored is not None else tum_intrinsics_for(folder.name)
        elif isinstance(intrinsics, dict):
            intrinsics = Intrinsics(**intrinsics)
        if intrinsics.fy <= 0 or intrinsics.fx <= 0:
            raise fail(folder, "intrinsics fx and fy must be positive", "pass fx, fy > 0")
        self.intrinsics = intrinsics
        self.depth_scale = depth_scale
        super().__init__(f"tum-{sequence}", frames, depth_options)
        self.folder = folder
        gt_file = folder / "groundtruth.txt"
        pairs = read_tum_pairs(folder, max_difference, allow_outside_paths)
        gt_file = gt_file if gt_file.is_file() else None
        self._set_pairs(pairs, gt_for_pairs(self.name, pairs, gt_file, max_difference))


_ICL_NAME = re.compile(r"(lr|of)[-_]?kt([0-3])(n?)")


def icl_folder_candidates(sequence: str) -> list[str]:
    """Folder names under which ICL-NUIM sequence ``sequence`` (e.g. ``lr-kt3n``) is published."""
    match = _ICL_NAME.fullmatch(sequence.lower())
    if match is None:
        return [sequence]
    room, k, noisy = match.groups()
    names = [f"{room}-kt{k}{noisy}", f"{room}_kt{k}{noisy}", f"{room}kt{k}{noisy}"]
    if room == "lr":
        names += [f"living_room_traj{k}{noisy}_frei_png", f"living_room_traj{k}{noisy}"]
    else:
        names += [
            f"traj{k}{noisy}_frei_png",
            f"office_room_traj{k}{noisy}_frei_png",
            f"office_room_traj{k}{noisy}",
        ]
    return [sequence, *names]


def icl_gt_candidates(sequence: str) -> list[str]:
    """Ground-truth file names of an ICL-NUIM sequence (the noisy variant shares the clean one)."""
    match = _ICL_NAME.fullmatch(sequence.lower())
    names = ["groundtruth.txt"]
    if match is not None:
        room, k, _ = match.groups()
        names.append(f"livingRoom{k}.gt.freiburg" if room == "lr" else f"traj{k}.gt.freiburg")
    return names


class IclSource(_PairedSource):
    """An ICL-NUIM sequence (TUM-compatible release, or the small color/depth/pose.txt layout).

    Args:
        root: folder holding the sequence folders (and optionally the ``*.gt.freiburg`` files).
        sequence: ``lr-kt0``..``lr-kt3``, ``of-kt0``..``of-kt3`` (+ ``n`` for noisy), or a folder
            name.
        frames: optional slice of frames.
        max_difference: association window in (file) timestamp units.
        depth_options: how depth is lifted to points.

    Timestamps are the release's (frame numbers), not seconds; ground truth follows the sign
    normalisation described in the module docstring.
    """

    depth_scale = 5000.0
    dataset_mirror = FLIP_Y
    intrinsics = dataclasses.replace(ICL_INTRINSICS_RAW, fy=-ICL_INTRINSICS_RAW.fy)

    def __init__(
        self,
        root: str | Path,
        sequence: str,
        frames: slice | None = None,
        *,
        max_difference: float = 0.02,
        depth_options: DepthOptions | dict | None = None,
    ) -> None:
        root = Path(root).expanduser()
        folder = _find_sequence_folder(
            root, icl_folder_candidates(sequence), "ICL-NUIM sequence folders"
        )
        super().__init__(f"icl-{sequence}", frames, depth_options)
        self.folder = folder
        if (folder / "pose.txt").is_file() and (folder / "color").is_dir():
            self._set_pairs(*_read_small_icl(folder))
            return
        gt_file = _find_icl_gt(root, folder, sequence)
        pairs = read_tum_pairs(folder, max_difference)
        self._set_pairs(pairs, gt_for_pairs(self.name, pairs, gt_file, max_difference, FLIP_Y))


def _find_icl_gt(root: Path, folder: Path, sequence: str) -> Path | None:
    for name in icl_gt_candidates(sequence):
        for place in (folder, root):
            if (place / name).is_file():
                return place / name
    found = sorted(folder.glob("*.gt.freiburg"))
    return found[0] if len(found) == 1 else None


def _read_small_icl(folder: Path) -> tuple[RgbdFrames, np.ndarray]:
    """color/N.png, depth/N.png and pose.txt rows (image order) -> pairs and F T F poses."""
    color_dir = require_dir(folder / "color", "color/N.png images")
    depth_dir = require_dir(folder / "depth", "depth/N.png images")
    depth = sorted(depth_dir.glob("*.png"), key=lambda p: frame_number(p, r"(\d+)\.png"))
    if not depth:
        raise fail(depth_dir, "no depth/N.png images", "check the folder")
    color = [require_file(color_dir / p.name, "a colour image per depth image") for p in depth]
    color_count = len(list(color_dir.glob("*.png")))
    if color_count != len(depth):
        raise fail(
            color_dir, f"{color_count} colour images for {len(depth)} depth images", "pair them up"
        )
    pose_file = folder / "pose.txt"
    table = load_table(pose_file, 7, "rows 'tx ty tz qx qy qz qw', camera-to-world")
    if len(table) != len(depth):
        raise fail(
            pose_file,
            f"{len(table)} poses for {len(depth)} depth images",
            "give one pose per image, in image order",
        )
    stamps = np.asarray([float(frame_number(p, r"(\d+)\.png")) for p in depth])
    poses = FLIP_Y @ pose_from_translation_quaternion(table) @ FLIP_Y
    return RgbdFrames(stamps, color, depth), poses
