"""Optional parts of the avatar and how each is fitted, chosen by name from the config.

Each extension (:class:`~warpavatar.extensions.base.Extension`) owns one feature end to end: its options, its
avatar part (:class:`~warpavatar.model.parts.AvatarPart`), its losses, optimizers, schedule and checkpoint
state. The registry holds them in the order their hooks run; :func:`register` adds one (see
``docs/architecture.md`` for a worked example). Installed packages add theirs through the entry-point group
``warpavatar.extensions`` (each entry an :class:`Extension` subclass), loaded when this package is imported.

Built in, in hook order:

- ``pose_refinement`` (``--refine-poses auto|on|off``): per-training-frame corrections of the given poses.
- ``joint_growth`` (``--grow-joints``): ToMiE's skeleton growth.
- ``backward_mapping`` (``--backward-mapping``): TAGA's backward mapping and cycle losses.
- ``pose_correction`` (``--pose-correction``): a pose-conditioned correction of the canonical Gaussians.
- ``secondary_motion`` (``--secondary-motion``): per-training-frame displacements on SMAD's graph.
- ``dynamics`` (``--dynamics``): SMAD's learned secondary dynamics.
- ``garment`` (``--garment auto|off``): loose garments detected and simulated as cloth.
- ``lighting`` (``--lighting``): a global world-frame irradiance.
"""

from warpavatar.extensions.backward_mapping import BackwardMappingExtension
from warpavatar.extensions.base import Extension, FitContext, LossTerm, NoOptions, StepContext, option
from warpavatar.extensions.dynamics import DynamicsExtension
from warpavatar.extensions.garment import GarmentExtension
from warpavatar.extensions.joint_growth import JointGrowthExtension
from warpavatar.extensions.lighting import LightingExtension
from warpavatar.extensions.pose_correction import PoseCorrectionExtension
from warpavatar.extensions.pose_refinement import PoseRefinementExtension
from warpavatar.extensions.registry import get_extension, load_entry_points, register, registered, unregister
from warpavatar.extensions.secondary_motion import SecondaryMotionExtension

__all__ = ["Extension", "FitContext", "StepContext", "LossTerm", "NoOptions", "option", "register", "unregister",
           "registered", "get_extension", "load_entry_points"]

for _extension in (PoseRefinementExtension, JointGrowthExtension, BackwardMappingExtension, PoseCorrectionExtension,
                   SecondaryMotionExtension, DynamicsExtension, GarmentExtension, LightingExtension):
    register(_extension)
load_entry_points()
