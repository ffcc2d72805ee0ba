"""Terminal lines shared by the end of a run (``slam.app.summary``) and ``python -m slam.eval``:
lengths in one format, and the mesh scores with the culling they were taken under."""

from __future__ import annotations

import math
from typing import Any

_CULLING = {
    "frustum": "over surfaces in view",
    "view": "over surfaces in view",
    "none": "over the whole ground truth",
}
_UNCULLED = {
    "frustum": "all ground truth in a camera's view, occluded surfaces too",
    "view": "all ground truth in a camera's view, occluded surfaces too",
    "none": "the whole ground truth",
}


def length(value: float | None) -> str:
    """``value`` metres as centimetres below 1 m, as metres above; ``n/a`` if missing."""
    if value is None or not math.isfinite(value):
        return "n/a"
    return f"{100 * value:.2f} cm" if abs(value) < 1.0 else f"{value:.2f} m"


def _ratio(value: float | None) -> str:
    return "n/a" if value is None or not math.isfinite(value) else f"{100 * value:.0f}%"


def mesh_lines(metrics: dict[str, Any]) -> list[str]:
    """The mesh scores of ``metrics`` (``mesh``, ``mesh_unculled``), or nothing without them."""
    mesh = metrics.get("mesh")
    if not mesh:
        return []
    culling = str(mesh.get("culling", ""))
    where = (
        "over observed surfaces"
        if culling.startswith("observed")
        else _CULLING.get(culling, f"culling {culling}")
    )
    lines = [
        f"mesh accuracy {length(mesh['accuracy_m'])}, completion {length(mesh['completion_m'])}, "
        f"completion ratio {_ratio(mesh['completion_ratio'])} "
        f"(< {length(mesh.get('threshold_m'))}) {where}"
    ]
    unculled = metrics.get("mesh_unculled")
    if unculled:
        culling = unculled.get("culling")
        lines.append(
            f"  unculled ({_UNCULLED.get(culling, culling)}): completion "
            f"{length(unculled['completion_m'])}, ratio {_ratio(unculled['completion_ratio'])}"
        )
    return lines
