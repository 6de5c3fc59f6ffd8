"""Appearance-based loop-closure detection scored as confusion matrices.

Four detectors over visual words (the HGCN paper's comparison): TF-IDF bag-of-words
(:mod:`.bow_detector`) and FAB-MAP 2.0 (:mod:`.chow_liu`, :mod:`.fabmap`, :mod:`.sequence`),
each with the ORB-tree or the HGCN vocabulary. :mod:`.metrics` scores an (n, n) matrix of
match beliefs against a ground-truth loop matrix (:mod:`.data`); :mod:`.lcd` runs the whole
comparison (``orbslam-hgcn lcd``) and :mod:`.plots` draws it. The detectors work on word-id
arrays (:mod:`.words`), so any vocabulary with ``transform_words`` can feed them.
"""
