"""Visualisation of SLAM runs in rerun, live (spawned or connected viewer) or recorded (.rrd).

- :mod:`~orbslam_hgcn.viz.records`: FrameLog and MapSnapshot, the plain arrays the pipeline
  fills (numpy only), and the entity paths.
- :mod:`~orbslam_hgcn.viz.rerun_logger`: RerunLogger, which logs them.
- :mod:`~orbslam_hgcn.viz.sinks`: the ``--rerun`` argument and the spawn/save/connect sinks
  (imports rerun only when a sink is opened).
- :mod:`~orbslam_hgcn.viz.live`: LiveViz, the ``System.observers`` entry that logs a running
  system (``orbslam-hgcn run ... --rerun spawn | save FILE.rrd | connect ADDR``).
- :mod:`~orbslam_hgcn.viz.blueprint`: the default viewer layout.
- :mod:`~orbslam_hgcn.viz.demo`: a synthetic run for checking the set-up.

Static trajectory and error plots live in :mod:`orbslam_hgcn.evaluation.plots`.
"""
