"""What the commands do: ``run`` on a dataset (:mod:`.run`, with how a run ends, :mod:`.ending`,
and saved maps, :mod:`.mapfile`), ``compare`` vocabularies (:mod:`.compare`), ``sweep``
parameters over sequences (:mod:`.sweep`) and the ``demo`` (:mod:`.demo`). They build on
:mod:`orbslam_hgcn.runtime`; the command line (:mod:`orbslam_hgcn.cli`) calls them."""
