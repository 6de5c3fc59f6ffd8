"""Trajectory evaluation: ATE/RPE through evo (``ate``), plots (``plots``), reports (``report``)."""
