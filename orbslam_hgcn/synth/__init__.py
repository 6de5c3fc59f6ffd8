"""The synthetic sequence renderer: scenes, textures, camera paths, lighting, camera
effects and image degradations, written in the TUM or KITTI layout with exact ground truth
(``orbslam-hgcn synth``; :func:`orbslam_hgcn.synth.sequence.render_sequence`).

Renders are inputs to the system, not part of it: the readers in
:mod:`orbslam_hgcn.datasets` read them as they read any dataset.
"""
