"""Training vocabularies: image sources and descriptor extraction with a resumable cache
(:mod:`.train`, the ``orbslam-hgcn vocab train`` entry), feature tracks across training
images (:mod:`.tracks`), the level-by-level k-medians tree of the ORB vocabulary
(:mod:`.tree_build`), and the hyperbolic GCN in torch (:mod:`.hgcn`, :mod:`.hyperbolic`).
Run time never needs this package (nor torch): a trained vocabulary is a file read by
:func:`orbslam_hgcn.vocabulary.load_vocabulary`."""
