"""cpslam — collaborative neural point-based RGB-D SLAM."""

__version__ = "0.1.0"
