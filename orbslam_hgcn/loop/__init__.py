"""Loop closing: detection over the keyframe database, Sim(3) verification, loop correction
with a Sim(3) pose graph and global BA (ORB-SLAM, Mur-Artal, Montiel & Tardos, T-RO 2015,
Sec. VII). :class:`~orbslam_hgcn.loop.closer.LoopCloser` is the stage's entry."""
