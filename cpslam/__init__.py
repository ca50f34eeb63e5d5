"""cpslam — collaborative neural point-based RGB-D SLAM."""

import os

# MKL (torch's CPU BLAS) picks code paths at run time that need not repeat bit for bit across
# runs: two 2-thread runs on an AVX2 CPU ended 1e-12 apart. Its conditional-numerical-
# reproducibility mode makes a run repeat itself; it is read at MKL's first call, so it is set
# on import, before any tensor maths. A value the user exported wins.
os.environ.setdefault("MKL_CBWR", "AUTO")

__version__ = "0.1.0"
