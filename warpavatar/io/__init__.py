"""Files in and out of an avatar: its Gaussians as 3DGS ``.ply`` and animated OpenUSD, and the motions that drive it.

The public names (docs/export.md documents each, with the conventions they share):

* :func:`write_gaussian_ply`, :func:`read_gaussian_ply` (:mod:`~warpavatar.io.ply`): one set of Gaussians as the
  ``.ply`` file the reference 3DGS code writes (raw parameters: logit opacities, log scales);
* :class:`GaussianUsdWriter`, :func:`read_gaussian_usd` (:mod:`~warpavatar.io.usd`): an animation as a
  time-sampled ``.usdc`` (OpenUSD's ``ParticleField3DGaussianSplat`` schema or a ``Points`` fallback, optionally
  with a UsdSkel rig), written frame by frame with bounded memory;
* :func:`load_motion`, :class:`Motion`, :class:`MotionError` (:mod:`~warpavatar.io.motion`): bone transforms of
  a skeleton from a video folder, a ``.npz`` or a ``.bvh``, checked;
* :func:`parse_bvh`, :class:`BvhMotion`, :func:`retarget_bvh`, :class:`BvhError` (:mod:`~warpavatar.io.bvh`): a
  BVH file's hierarchy and channels, and its motion retargeted to our skeleton;
* :class:`Exporter`, :func:`register_exporter`, :func:`exporter_for` (:mod:`~warpavatar.io.exporters`): the export
  formats, chosen by the output's suffix (``warpavatar-animate`` writes through them).

Each name is imported from its module on first use, so ``import warpavatar.io`` stays cheap: the USD writer
needs usd-core's ``pxr``, which takes seconds to import. ``warpavatar.io.animation`` (an avatar posed frame by
frame for the CLIs) and ``warpavatar.io.viewer`` (the web viewer) are imported by their own paths.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # what tools that read imports see; at run time __getattr__ imports each name when asked
    from warpavatar.io.bvh import BvhError, BvhMotion, parse_bvh, retarget_bvh
    from warpavatar.io.exporters import Exporter, exporter_for, register_exporter
    from warpavatar.io.motion import Motion, MotionError, load_motion
    from warpavatar.io.ply import read_gaussian_ply, write_gaussian_ply
    from warpavatar.io.usd import GaussianUsdWriter, read_gaussian_usd

__all__ = ["write_gaussian_ply", "read_gaussian_ply", "GaussianUsdWriter", "read_gaussian_usd", "load_motion",
           "Motion", "MotionError", "parse_bvh", "BvhMotion", "retarget_bvh", "BvhError", "Exporter",
           "register_exporter", "exporter_for"]

_MODULE_OF = {
    "write_gaussian_ply": "ply", "read_gaussian_ply": "ply",
    "GaussianUsdWriter": "usd", "read_gaussian_usd": "usd",
    "load_motion": "motion", "Motion": "motion", "MotionError": "motion",
    "parse_bvh": "bvh", "BvhMotion": "bvh", "retarget_bvh": "bvh", "BvhError": "bvh",
    "Exporter": "exporters", "register_exporter": "exporters", "exporter_for": "exporters",
}
"""Each public name -> the module of this package that defines it."""


def __getattr__(name: str):
    module = _MODULE_OF.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(f"{__name__}.{module}"), name)
    globals()[name] = value  # found directly from now on
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
