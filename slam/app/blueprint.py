"""The default Rerun viewer layout of a run.

A 3D view of ``world`` on the left; on the right the colour and depth images (RGB-D runs only)
above tabs of time series, one per metric group (``metrics/timing``, ``metrics/error``,
``metrics/counts``).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import rerun.blueprint as rrb

WORLD_ENTITY = "world"
CAMERA_ENTITY = "world/sensor/camera"
DEPTH_ENTITY = "world/sensor/depth_camera"
METRIC_GROUPS = ("timing", "error", "counts")


def default_blueprint(with_camera: bool = False) -> rrb.Blueprint:
    """The viewer layout; ``with_camera`` adds a 2D view of the RGB and depth images."""
    import rerun.blueprint as rrb

    series = rrb.Tabs(
        *(
            rrb.TimeSeriesView(origin=f"metrics/{group}", name=group.capitalize())
            for group in METRIC_GROUPS
        ),
        name="Metrics",
    )
    right: rrb.Container | rrb.View = series
    if with_camera:
        images = rrb.Horizontal(
            rrb.Spatial2DView(origin=CAMERA_ENTITY, name="Colour"),
            rrb.Spatial2DView(origin=DEPTH_ENTITY, name="Depth"),
        )
        right = rrb.Vertical(images, series, row_shares=[1, 1])
    world = rrb.Spatial3DView(origin=WORLD_ENTITY, name="World")
    return rrb.Blueprint(
        rrb.Horizontal(world, right, column_shares=[3, 2]),
        rrb.TimePanel(timeline="frame"),
        collapse_panels=False,
    )
