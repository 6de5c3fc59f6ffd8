"""orbslam_hgcn: monocular ORB-SLAM-style visual SLAM with an HGCN visual vocabulary.

The Python API is :class:`Slam` (:mod:`orbslam_hgcn.app.slam`; docs/API.md)::

    from orbslam_hgcn import Slam

    with Slam(camera="tum_fr3") as slam:
        for t, image in frames:
            result = slam.track(image, t)
"""

from typing import Any

from orbslam_hgcn.errors import OrbslamError

__all__ = ["MapData", "OrbslamError", "Slam", "Tracked", "__version__"]
__version__ = "0.1.0"

_API = ("Slam", "Tracked", "MapData")


def __getattr__(name: str) -> Any:
    # Imported on first use: the command line starts without loading the SLAM system.
    if name in _API:
        from orbslam_hgcn.app import slam

        return getattr(slam, name)
    raise AttributeError(f"module 'orbslam_hgcn' has no attribute {name!r}")
