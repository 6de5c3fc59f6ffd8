"""The summary a run prints says what happened: a map made and then reset is not "never
initialised", and no statistic is printed from an empty sample."""

from __future__ import annotations

from orbslam_hgcn.app.ending import RunEnd
from orbslam_hgcn.runtime.results import summary_ms
from orbslam_hgcn.app.run import RunReport, format_report


def _report(events, tracking_ms, mapping_ms, tracked=0, resets=0) -> list[str]:
    stats = {
        "frames": {"frames": 19, "tracked": tracked, "lost": 1, "not_initialized": 4, "reset": 2, "dropped": 0},
        "keyframes": 0, "map_points": 0, "final_state": "not initialised", "map_resets": resets, "events": events,
        "timing_ms": {"tracking_per_frame": summary_ms(tracking_ms), "tracking_cpu_per_frame": summary_ms(tracking_ms),
                      "local_mapping_per_keyframe": summary_ms(mapping_ms)},
    }  # fmt: skip
    return format_report(RunReport({}, stats, {}, end=RunEnd()))


def test_summary_of_no_timings_is_empty_not_zero():
    assert summary_ms([]) == {"count": 0, "median": None, "p95": None, "mean": None, "max": None}
    assert summary_ms([2.0, 4.0])["median"] == 3.0


def test_a_map_made_then_reset_is_reported_as_such():
    """The TUM sample's case: initialised on frames 0 and 16, reset at frame 17."""
    events = [
        {"frame": 16, "t": 1.0, "event": "initialized", "map": 0, "keyframe_frames": [0, 16]},
        {"frame": 17, "t": 2.0, "event": "reset", "map": 1, "why": "tracking lost with only 2 keyframe(s) in the map"},
        {"frame": 17, "t": 2.0, "event": "lost", "map": 1},
    ]
    text = "\n".join(_report(events, [], [655.0], resets=1))
    assert "never initialised" not in text
    assert ("the map was initialised on frames 0 and 16, then reset at frame 17 (tracking lost with only 2 "
            "keyframe(s) in the map); it was not initialised again; the trajectory files are empty") in text
    assert "tracking ms/frame: no frames tracked, no timing" in text and "median 0.0" not in text
    assert "local mapping ms/keyframe: median 655, p95 655, mean 655" in text
    assert "the ATE below covers only the frames tracked" not in text  # there is no ATE at all


def test_a_map_never_made_and_no_keyframe_mapped():
    text = "\n".join(_report([], [], []))
    assert "WARNING: the map was never initialised (too little parallax or texture)" in text
    assert "local mapping ms/keyframe: no keyframes mapped, no timing" in text
