"""warpavatar: animatable 3D Gaussian avatars from one video, with hand-written NVIDIA Warp kernels."""

__version__ = "0.1.0"

__all__ = ["__version__"]
