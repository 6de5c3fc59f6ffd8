"""The default rerun layout of a SLAM recording.

Left: the 3D world (map points, keyframe frustums, covisibility and loop edges, trajectories,
current camera with its image). Right: the camera image with tracked (green) and untracked
(red) keypoints, time-series plots, and the event log (loop closures, tracking state).
"""

from __future__ import annotations

import rerun.blueprint as rrb

from orbslam_hgcn.viz import records as ent

FRAME_TIMELINE = "frame"
TIME_TIMELINE = "time"


def default_blueprint() -> rrb.Blueprint:
    """The layout sent with every recording (the viewer's "reset blueprint" restores it)."""
    plots = rrb.Grid(
        rrb.TimeSeriesView(origin=ent.PLOT_TRACKING, name="tracked points / keypoints"),
        rrb.TimeSeriesView(origin=ent.PLOT_FPS, name="fps"),
        rrb.TimeSeriesView(origin=ent.PLOT_KEYFRAMES, name="keyframes"),
        rrb.TimeSeriesView(origin=ent.PLOT_MAP_POINTS, name="map points"),
        rrb.TimeSeriesView(origin=ent.PLOT_ATE, name="ATE [m]"),
        rrb.TimeSeriesView(
            origin="plots",
            contents=[f"+ /{ent.PLOT_STATE}", f"+ /{ent.PLOT_LOOPS}"],
            name="tracking state / loops closed",
        ),
        grid_columns=2,
    )
    right = rrb.Vertical(
        rrb.Spatial2DView(origin=ent.IMAGE, name="camera"),
        plots,
        rrb.TextLogView(origin=ent.EVENTS, name="events"),
        row_shares=[3, 4, 1],
    )
    world = rrb.Spatial3DView(origin=ent.WORLD, name="world")
    return rrb.Blueprint(
        rrb.Horizontal(world, right, column_shares=[3, 2]),
        rrb.TimePanel(timeline=FRAME_TIMELINE),
        collapse_panels=False,
    )
