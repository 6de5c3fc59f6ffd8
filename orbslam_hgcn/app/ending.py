"""How a run ends: each way has its exit status (``orbslam-hgcn run``) and a one-line reason.

A light module (no SLAM imports) so that the command line can list the statuses in
``orbslam-hgcn run --help`` without loading the system.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

# How a run of ``orbslam-hgcn run`` can end, its exit status and what it means. Every ending
# but bad_input writes the results of the frames processed.
EXIT_STATUS = {
    "complete": 0,
    "internal_error": 1,
    "bad_input": 2,
    "bad_frame": 3,
    "stage_failed": 4,
    "interrupted": 130,
    "terminated": 143,
}
EXIT_MEANING = {
    "complete": "every frame processed (unreadable frames skipped and counted)",
    "internal_error": "a bug stopped the run: partial results, the traceback in OUT/traceback.txt",
    "bad_input": "bad arguments, config, dataset or output folder, found before the first frame: nothing run",
    "bad_frame": "an unreadable frame with --on-bad-frame stop: partial results",
    "stage_failed": "a worker thread or child process (bundle adjustment, extraction) failed: partial results",
    "interrupted": "Ctrl-C: partial results",
    "terminated": "SIGTERM: partial results",
}


@dataclass(frozen=True)
class RunEnd:
    """How a run ended: ``kind`` (a key of :data:`EXIT_STATUS`), a one-line reason, and the
    stage or the frame concerned, where one is."""

    kind: str = "complete"
    reason: str = "every frame processed"
    stage: str | None = None
    frame: int | None = None

    @property
    def complete(self) -> bool:
        return self.kind == "complete"

    @property
    def exit_status(self) -> int:
        return EXIT_STATUS[self.kind]

    def to_json(self) -> dict[str, Any]:
        d = {"kind": self.kind, "reason": self.reason, "exit_status": self.exit_status}
        if self.stage is not None:
            d["stage"] = self.stage
        if self.frame is not None:
            d["frame"] = self.frame
        return d


def exit_status_help() -> str:
    """The exit statuses of ``orbslam-hgcn run``, one per line (its --help epilog)."""
    return "exit status:\n" + "\n".join(f"  {EXIT_STATUS[k]:>3}  {EXIT_MEANING[k]}" for k in EXIT_STATUS)
