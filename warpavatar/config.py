"""Fitting configuration: one dataclass whose field docstrings are the ``--help`` of ``warpavatar-fit``.

Presets are named configurations (:data:`PRESETS`); command-line flags override single fields.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from dataclasses import dataclass, field, fields

__all__ = ["FitConfig", "PRESETS", "preset", "add_config_arguments", "config_from_arguments"]


def _opt(default, help_text: str):
    return field(default=default, metadata={"help": help_text})


@dataclass
class FitConfig:
    """Every knob of a fit. Iteration counts are optimizer steps (one training frame each)."""

    iterations: int = _opt(8000, "total optimizer steps (one training frame per step)")
    seed: int = _opt(0, "random seed: the fit is deterministic for a given seed on a given device")
    image_scale: float = _opt(1.0, "resize training frames by this factor (K is scaled to match)")
    max_train_frames: int = _opt(0, "use at most this many training frames, evenly spaced (0 = all)")
    # Initialization (TAGA Sec. 3.1, no body template)
    init_points_per_bone: int = _opt(400, "Gaussians sampled around each bone's midpoint at start")
    init_carve: bool = _opt(True, "also seed Gaussians by carving the canonical box with the training masks")
    init_carve_candidates: int = _opt(200000, "random canonical points tested against the masks when carving")
    init_carve_points: int = _opt(20000, "at most this many carved points are kept")
    sh_degree: int = _opt(3, "spherical-harmonics degree of the colours (0 = view-independent)")
    sh_increase_every: int = _opt(1000, "raise the active SH degree by one every this many steps")
    # Skinning field (TAGA Sec. 3.1, appendix C)
    grid_cells: int = _opt(128, "voxel skinning grid cells along the longest canonical axis (TAGA: 64x64x16; "
                           "128 measured 0.3 dB better on novel views, BENCHMARKS.md)")
    grid_min_cells: int = _opt(16, "fewest voxel cells along any axis")
    field_hidden: int = _opt(128, "hidden width of the skinning-field MLP")
    field_layers: int = _opt(4, "hidden layers of the skinning-field MLP")
    field_frequencies: int = _opt(6, "positional-encoding frequencies of the skinning-field MLP input")
    skinning_prior_temperature: float = _opt(0.02, "temperature of the rigid bone-distance skinning prior that the "
                                             "field's warm-up distils and carving poses points with, as a fraction "
                                             "of the skeleton's size: small values give each point its nearest "
                                             "bone, larger ones blend neighbouring bones (loose garments)")
    field_warmup_steps: int = _opt(600, "warm-up steps that distil a rigid bone-distance prior into the field")
    gaussian_only_steps: int = _opt(1500, "steps after warm-up where only the Gaussians train (field frozen)")
    field_lr: float = _opt(1e-3, "Adam learning rate of the skinning-field MLP")
    lambda_bone: float = _opt(5.0, "weight of the bone regularization (one-hot weights at bone midpoints)")
    pose_correction: bool = _opt(True, "learn a pose-conditioned correction of canonical Gaussians (garments)")
    frame_codes: bool = _opt(True, "give each training frame a learned code in the pose correction (cloth "
                             "dynamics of the training instants; other poses use the pose-only correction)")
    pose_correction_hidden: int = _opt(128, "hidden width of the pose-correction MLP")
    lambda_pose_correction: float = _opt(0.01, "weight of the pose correction's size regularizer")
    # TAGA's backward mapping (paper 004 Sec. 3.2-3.4)
    backward_mapping: bool = _opt(False, "detect Gaussians whose skinning disagrees with a bone GMM (ambiguous), "
                                  "correct them from their nearest normal neighbours and pull the canonical "
                                  "model and skinning field towards the correction (TAGA's cycle losses)")
    backward_from: int = _opt(3000, "first step of the backward-mapping phase")
    backward_until: int = _opt(6500, "last step of the backward-mapping phase")
    backward_every: int = _opt(150, "steps between refreshes of the detected and corrected Gaussians")
    backward_threshold: float = _opt(0.5, "Gaussians whose confidence 1 - JSD(GMM weights, weights) is at most "
                                     "this are ambiguous")
    backward_neighbours: int = _opt(8, "nearest normal Gaussians an ambiguous one may take its weights from")
    backward_max_move: float = _opt(0.05, "corrections moving a canonical centre farther than this fraction of "
                                    "the canonical extent are dropped (distant parts touching in the frame)")
    lambda_geo: float = _opt(1000.0, "weight of the geometry cycle loss (mean L1 distance, world units)")
    lambda_skin: float = _opt(10.0, "weight of the skinning cycle loss (mean squared weight difference)")
    # Secondary motion on SMAD's graph (paper 000 Sec. 3.1-3.3): per-frame displacements or learned dynamics
    secondary_motion: bool = _opt(False, "learn per-training-frame displacements of a voxel-downsampled Gaussian "
                                  "graph (cloth that swings; novel views of training instants and replays use them)")
    secondary_from: int = _opt(2000, "step at which the graph is built from the canonical Gaussians and starts to "
                               "train")
    secondary_voxel: float = _opt(0.03, "graph voxel edge as a fraction of the canonical box's longest side")
    lr_secondary: float = _opt(1e-4, "Adam learning rate of the node displacements, times the canonical extent")
    dynamics: bool = _opt(False, "learn SMAD's secondary dynamics on the graph (the alternative to "
                          "--secondary-motion): a message-passing network predicts forces from the body's motion and "
                          "a mass-spring-damper step with learned stiffness and damping moves the nodes, so any "
                          "motion can be rolled out (novel poses, exports); starts at --secondary-from")
    dynamics_hidden: int = _opt(64, "width of the dynamics network's node features and messages")
    dynamics_window: int = _opt(4, "frames each step rolls forward with gradients, from a cached state (truncated "
                                "backpropagation through time)")
    dynamics_refresh_every: int = _opt(100, "steps between full no-gradient rollouts of the training sequence that "
                                       "refresh the cached states")
    dynamics_substeps: int = _opt(2, "semi-implicit Euler steps per frame")
    dynamics_velocity_history: int = _opt(11, "past skinned velocities in each node's encoding (SMAD: 11)")
    dynamics_pose_window: int = _opt(4, "frames of bone rotations in the pose-window embedding")
    lr_dynamics: float = _opt(1e-3, "Adam learning rate of the dynamics network")
    lr_dynamics_springs: float = _opt(1e-2, "Adam learning rate of the dynamics' stiffness, anchor and damping "
                                      "(logits of their bounded ranges)")
    lambda_isometry: float = _opt(0.1, "weight of SMAD's isometry loss on the posed graph (per voxel^2)")
    lambda_damping: float = _opt(0.01, "weight of SMAD's damping loss on node velocities (voxels per frame)")
    lambda_displacement: float = _opt(1e-3, "weight of the mean squared node displacement (per voxel^2)")
    # ToMiE's skeleton growth (paper 003 Sec. 4)
    grow_joints: bool = _opt(False, "grow extra joints on the skeleton where garments or held objects do not follow "
                             "the body (ToMiE): at --grow-at, joints whose Gaussians carry the largest position "
                             "gradients (assigned by skinning weights and motion kernels) each grow a child whose "
                             "per-frame rotation is learned; novel views of training instants replay it, other "
                             "poses keep it at rest unless animated explicitly")
    grow_at: int = _opt(1500, "step at which joints grow (the position gradients of every step before it are "
                        "pooled); growing when the field starts to train (as here) measured better than at step "
                        "3000 on cesium_skirt with named parents")
    grow_threshold: float = _opt(1.1, "a joint grows a child when its gradient is at least this many times the "
                                 "median joint's (ToMiE thresholds an absolute value, which depends on the loss "
                                 "scale)")
    grow_max_joints: int = _opt(4, "at most this many located joints grow a child")
    grow_criterion: str = _opt("gradient", "what locates the parent joints: 'gradient' (ToMiE: each joint's "
                               "assigned Gaussians' mean position-gradient norm) or 'history' (their RMS offset, "
                               "over the training frames, that the pose correction's per-frame codes add to its "
                               "pose-only correction: shape no function of the pose explains, as cloth that "
                               "lags; needs --pose-correction and --frame-codes, and --grow-at after "
                               "--gaussian-only-steps so that the correction has trained)")
    grow_parents: str = _opt("", "comma-separated skeleton joint names that grow a child at --grow-at instead of "
                             "those the gradients locate (e.g. the hips a skirt hangs from; a name given twice "
                             "grows two children); the gradients are still logged")
    grow_motion_mix: float = _opt(0.4, "share of the motion kernel in the assignment of Gaussians to joints "
                                  "(ToMiE's lambda)")
    grow_kernel_frames: int = _opt(64, "training frames (evenly spaced) the motion kernels are computed over")
    lr_extra_joints: float = _opt(1e-3, "Adam learning rate of the grown joints' position and rotation MLPs")
    # Colours
    lighting: bool = _opt(False, "multiply colours by a global first-order irradiance of each Gaussian's world "
                          "normal (lights fixed in the world; extrapolates to sides never facing the camera)")
    lr_lighting: float = _opt(1e-3, "Adam learning rate of the global lighting's 12 numbers")
    shading: str = _opt("world", "'world': colours follow how the body faces a fixed light rig (evaluated from "
                        "the training camera centre; right for a fixed camera and a turning subject); 'view': "
                        "view-dependent colours from the rendering camera (3DGS)")
    # Losses
    target: str = _opt("auto", "what the render is compared with: 'frame' (the frame as it is), 'masked' (the "
                       "masked foreground over the background colour) or 'auto' ('frame' when meta.json declares "
                       "the flat background the frames were rendered over, so their anti-aliased edge pixels "
                       "stay; 'masked' otherwise)")
    lambda_ssim: float = _opt(0.2, "weight of (1 - SSIM) in the photometric loss")
    lambda_mask: float = _opt(0.1, "weight of the L1 loss between rendered alpha and the foreground mask")
    lambda_scale: float = _opt(0.0, "weight of a penalty on Gaussian scales above scale_limit")
    # Optimizer (3DGS rates; positions scaled by the canonical extent)
    lr_position: float = _opt(1.6e-4, "initial position learning rate, times the canonical extent")
    lr_position_final: float = _opt(1.6e-6, "final position learning rate, times the canonical extent")
    lr_scale: float = _opt(5e-3, "learning rate of log-scales")
    lr_rotation: float = _opt(1e-3, "learning rate of quaternions")
    lr_opacity: float = _opt(2.5e-2, "learning rate of opacity logits")
    lr_color: float = _opt(2.5e-3, "learning rate of SH DC coefficients (higher orders use 1/20 of it)")
    # Adaptive density control
    densify_from: int = _opt(500, "first step of densification (after the warm-up)")
    densify_until: int = _opt(6000, "last step of densification")
    densify_every: int = _opt(100, "steps between densification rounds")
    densify_grad_threshold: float = _opt(2e-4, "mean screen-space gradient (NDC) above which a Gaussian is cloned or split")
    densify_percent_dense: float = _opt(0.01, "relative size (of the canonical extent) separating clone from split")
    max_gaussians: int = _opt(200000, "Gaussian budget: the densification threshold rises as the count nears it")
    prune_opacity: float = _opt(0.005, "Gaussians whose opacity falls below this are pruned")
    prune_max_scale: float = _opt(0.1, "Gaussians larger than this fraction of the canonical extent are pruned")
    opacity_reset_every: int = _opt(2500, "steps between opacity resets (0 = never)")
    # Book-keeping
    log_every: int = _opt(50, "steps between training-log lines (JSON lines)")
    checkpoint_every: int = _opt(1000, "steps between checkpoints (written atomically)")
    preview_frames: int = _opt(3, "training frames rendered as previews at the end")

    def __post_init__(self):
        if self.shading not in ("world", "view"):
            raise ValueError(f"shading must be 'world' or 'view', got {self.shading!r}")
        if self.target not in ("auto", "frame", "masked"):
            raise ValueError(f"target must be 'auto', 'frame' or 'masked', got {self.target!r}")
        if not 0.0 < self.backward_threshold < 1.0:
            raise ValueError(f"backward_threshold must lie in (0, 1), got {self.backward_threshold}")
        if not self.skinning_prior_temperature > 0.0:
            raise ValueError(f"skinning_prior_temperature must be positive, got {self.skinning_prior_temperature}")
        if self.backward_every < 1:
            raise ValueError(f"backward_every must be at least 1, got {self.backward_every}")
        if self.dynamics and self.secondary_motion:
            raise ValueError("choose one secondary-motion model: --secondary-motion (per-frame displacements) or "
                             "--dynamics (learned dynamics), not both")
        if self.grow_joints and (self.dynamics or self.backward_mapping):
            raise ValueError("--grow-joints cannot yet be combined with --dynamics or --backward-mapping (both read "
                             "the skeleton's bones only); use --secondary-motion for per-frame cloth displacements")
        if self.grow_criterion not in ("gradient", "history"):
            raise ValueError(f"grow_criterion must be 'gradient' or 'history', got {self.grow_criterion!r}")
        if self.grow_joints and self.grow_criterion == "history" and not (
                self.pose_correction and self.frame_codes and self.grow_at > self.gaussian_only_steps):
            raise ValueError("--grow-criterion history reads the pose correction's per-frame codes: it needs "
                             "--pose-correction, --frame-codes and --grow-at later than --gaussian-only-steps")
        if self.grow_parents and not self.grow_joints:
            raise ValueError("--grow-parents names the joints that grow: it needs --grow-joints")
        if self.grow_threshold <= 0 or not 0.0 <= self.grow_motion_mix <= 1.0:
            raise ValueError(f"grow_threshold must be positive and grow_motion_mix lie in [0, 1], got "
                             f"{self.grow_threshold} and {self.grow_motion_mix}")
        if self.grow_kernel_frames < 2 or self.grow_max_joints < 1:
            raise ValueError(f"grow_kernel_frames must be at least 2 and grow_max_joints at least 1, got "
                             f"{self.grow_kernel_frames} and {self.grow_max_joints}")
        for name in ("dynamics_hidden", "dynamics_window", "dynamics_refresh_every", "dynamics_substeps",
                     "dynamics_velocity_history", "dynamics_pose_window"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be at least 1, got {getattr(self, name)}")

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, values: dict) -> "FitConfig":
        known = {f.name for f in fields(cls)}
        unknown = set(values) - known
        if unknown:
            raise ValueError(f"unknown config fields: {sorted(unknown)}")
        return cls(**values)

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), indent=2)


PRESETS: dict[str, dict] = {
    # Quality preset, for a GPU.
    "default": {},
    # Small and fast: CPU fits in minutes, and the test suite.
    "quick": dict(
        iterations=2000,
        image_scale=0.5,
        init_points_per_bone=150,
        init_carve_candidates=60000,
        init_carve_points=6000,
        sh_degree=1,
        sh_increase_every=800,
        grid_cells=32,
        grid_min_cells=8,
        field_hidden=64,
        field_layers=3,
        field_warmup_steps=300,
        gaussian_only_steps=600,
        densify_from=200,
        densify_until=1400,
        densify_every=100,
        max_gaussians=10000,
        pose_correction=False,
        secondary_from=800,
        grow_at=600,
        backward_from=1000,
        backward_until=1700,
        opacity_reset_every=0,
        checkpoint_every=500,
    ),
}


def preset(name: str, **overrides) -> FitConfig:
    """The named preset (``"default"`` or ``"quick"``) with some fields overridden."""
    if name not in PRESETS:
        raise ValueError(f"unknown preset {name!r}; choose one of {sorted(PRESETS)}")
    return FitConfig(**{**PRESETS[name], **overrides})


def add_config_arguments(parser: argparse.ArgumentParser) -> None:
    """Add one kebab-case flag per config field (``--lambda-ssim``), defaulting to "take the preset's"."""
    group = parser.add_argument_group("fit configuration (each overrides the preset's value)")
    for f in fields(FitConfig):
        flag = "--" + f.name.replace("_", "-")
        help_text = f"{f.metadata['help']} (default preset: {f.default})"
        if f.type in ("bool", bool):
            group.add_argument(flag, dest=f.name, default=None, action=argparse.BooleanOptionalAction, help=help_text)
        else:
            kind = {"int": int, "float": float}.get(f.type if isinstance(f.type, str) else f.type.__name__, str)
            group.add_argument(flag, dest=f.name, type=kind, default=None, metavar=kind.__name__.upper(),
                               help=help_text)


def config_from_arguments(args: argparse.Namespace, preset_name: str) -> FitConfig:
    """The preset with every flag the user gave applied."""
    overrides = {f.name: getattr(args, f.name) for f in fields(FitConfig) if getattr(args, f.name, None) is not None}
    return preset(preset_name, **overrides)
