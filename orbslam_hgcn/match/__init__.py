"""Matching ORB features: by projection, by BoW, for triangulation and for
initialisation (:mod:`.matching`, :mod:`.projection_search`), the Hamming distance kernels
(:mod:`.hamming`) and the grid of a frame's keypoints (:mod:`.grid`). Extraction itself
lives in :mod:`orbslam_hgcn.features`; matching imports it, never the reverse."""
