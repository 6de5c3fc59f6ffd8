"""Training vocabularies: image sources and descriptor extraction with a resumable cache
(:mod:`.train`, the ``orbslam-hgcn vocab train`` entry), feature tracks across training
images (:mod:`.tracks`), the level-by-level k-medians tree of the ORB vocabulary
(:mod:`.tree_build`), and the hyperbolic GCN in torch (:mod:`.hgcn`, :mod:`.hyperbolic`).
The vocabularies' own ``train_*`` functions call into it; a trained vocabulary is a file read
by :func:`orbslam_hgcn.vocabulary.load_vocabulary`, and loading or using one never imports
torch (:mod:`.hgcn` is imported only when an HGCN vocabulary is trained)."""
