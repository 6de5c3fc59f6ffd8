"""orbslam_hgcn: monocular ORB-SLAM-style visual SLAM with an HGCN visual vocabulary."""

from orbslam_hgcn.errors import OrbslamError

__all__ = ["OrbslamError", "__version__"]
__version__ = "0.1.0"
