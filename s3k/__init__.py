"""s3k: semantic 3D keypoints from a calibrated multi-camera rig (after S3K, Vecerik et al. 2020)."""

__version__ = "0.1.0"
