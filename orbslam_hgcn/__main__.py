import sys

from orbslam_hgcn.cli import main

sys.exit(main())
