"""Fit configuration: the core options, the options of each enabled extension, and the ``warpavatar-fit`` flags.

A :class:`FitConfig` holds the core of a fit (data, schedule, Gaussians, skinning field, the core's losses,
optimizer, density control, book-keeping) as fields, and one options dataclass per enabled extension in
``extensions`` (:mod:`warpavatar.extensions`). Flags and presets speak one flat vocabulary: a core field's
name, an extension's switch (``pose_correction=True``) or an extension option's name (``frame_codes=False``);
:meth:`FitConfig.from_flat` sorts them out.
"""

from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass, field, fields
from typing import Mapping

from warpavatar._src.precision import MATMUL_PRECISIONS
from warpavatar.extensions import get_extension, registered

__all__ = ["FitConfig", "CORE_GROUPS", "RANGES", "range_text", "option_owners", "flat_options", "changed_options"]

CORE_GROUPS = ("data and schedule", "Gaussians", "skinning field", "colours", "losses", "optimizer",
               "density control", "book-keeping")
"""The groups of core options in ``--help``, in order (after the main options)."""


def _core(default, help_text: str, *, group: str, product: bool = False, choices: tuple | None = None):
    assert group in CORE_GROUPS, group
    return field(default=default, metadata={"help": help_text, "group": group, "product": product,
                                            "choices": choices})


def _check_choices(values) -> None:
    """Raise ValueError when a dataclass field declared with ``choices`` (core fields, extension options) holds
    another value."""
    for option in fields(values):
        choices = option.metadata.get("choices")
        if choices and getattr(values, option.name) not in choices:
            words = " or ".join([", ".join(repr(c) for c in choices[:-1]), repr(choices[-1])])
            raise ValueError(f"{option.name} must be {words}, got {getattr(values, option.name)!r}")


@dataclass
class FitConfig:
    """Every knob of a fit. Iteration counts are optimizer steps (one training frame each)."""

    iterations: int = _core(8000, "total optimizer steps, one training frame each [steps]", group="data and schedule",
                            product=True)
    seed: int = _core(0, "random seed: on the CPU the fit is deterministic for a given seed; on CUDA the "
                         "gradients' atomic sums make two fits of one seed differ slightly",
                      group="data and schedule", product=True)
    image_scale: float = _core(1.0, "resize training frames by this factor, the intrinsics K with them [times the "
                               "frames' size]",
                               group="data and schedule", product=True)
    max_train_frames: int = _core(0, "use at most this many training frames, evenly spaced (0 = all) [frames]",
                                  group="data and schedule", product=True)
    matmul_precision: str = _core(
        "tf32", "precision of the float32 matrix products of the MLPs (skinning field, pose correction) on CUDA, "
        "in training steps (forward and backward) and in playback of the fitted avatar (warpavatar-render; kept in "
        "avatar.pt): 'tf32' (TensorFloat-32 tensor cores: faster products whose inputs are rounded to 10-bit "
        "mantissas, a relative error up to 2^-11 each, sums kept in float32; the rest of posing stays float32) or "
        "'fp32' (full float32 products: slower, as fits before this option); no effect on a CPU",
        group="data and schedule", product=True, choices=MATMUL_PRECISIONS)
    # Initialization (TAGA Sec. 3.1, no body template) and the Gaussians
    init_points_per_bone: int = _core(400, "Gaussians sampled around each bone's midpoint at start [Gaussians per "
                                      "bone]", group="Gaussians")
    init_carve: bool = _core(True, "also seed Gaussians by carving the canonical box with the training masks",
                             group="Gaussians")
    init_carve_candidates: int = _core(200000, "random canonical points tested against the masks when carving [points]",
                                       group="Gaussians")
    init_carve_points: int = _core(20000, "at most this many carved points are kept [points]", group="Gaussians")
    sh_degree: int = _core(3, "spherical-harmonics degree of the colours (0 = view-independent) [degree]",
                           group="Gaussians")
    sh_increase_every: int = _core(1000, "raise the active SH degree by one every this many steps [steps]",
                                   group="Gaussians")
    # Skinning field (TAGA Sec. 3.1, appendix C)
    grid_cells: int = _core(128, "voxel skinning grid cells along the longest canonical axis (TAGA: 64x64x16; "
                            "128 measured 0.3 dB better on novel views, BENCHMARKS.md) [cells]", group="skinning field")
    grid_min_cells: int = _core(16, "fewest voxel cells along any axis [cells]", group="skinning field")
    field_hidden: int = _core(128, "hidden width of the skinning-field MLP [features]", group="skinning field")
    field_layers: int = _core(4, "hidden layers of the skinning-field MLP [layers]", group="skinning field")
    field_frequencies: int = _core(6, "positional-encoding frequencies of the skinning-field MLP input [octaves]",
                                   group="skinning field")
    skinning_prior_temperature: float = _core(
        0.02, "temperature of the rigid bone-distance skinning prior that the field's warm-up distils and carving "
        "poses points with: small values give each point its nearest bone, larger ones blend neighbouring bones "
        "(loose garments) [fraction of the skeleton's size]",
        group="skinning field")
    field_warmup_steps: int = _core(600, "warm-up steps that distil a rigid bone-distance prior into the field, "
                                    "before the fit's first step [distillation steps]",
                                    group="skinning field")
    field_cells: str = _core(
        "active", "grid points at which a training step evaluates the skinning-field MLP: 'active' (those that "
        "the Gaussians and the bone samples read, one cell around, chosen anew every --field-cells-every steps "
        "and when the Gaussians are densified, kept by checkpoints; the others keep their values from then, "
        "which no step reads; the loss and its gradient are those of 'all') or 'all' (every grid point, every "
        "step)",
        group="skinning field", choices=("active", "all"))
    field_cells_every: int = _core(100, "steps between choices of the active grid points (--field-cells active) "
                                   "[steps]",
                                   group="skinning field")
    field_warmup_batch: int = _core(32768, "grid points per warm-up step, drawn at random (0 = every grid point) "
                                    "[grid points]",
                                    group="skinning field")
    gaussian_only_steps: int = _core(1500, "steps after warm-up where only the Gaussians train (field frozen) [steps]",
                                     group="skinning field")
    field_lr: float = _core(1e-3, "Adam learning rate of the skinning-field MLP (and of the networks that train "
                            "with it) [Adam step size]", group="skinning field")
    lambda_bone: float = _core(5.0, "weight of the bone regularization (one-hot weights at bone midpoints) "
                               "[loss weight]",
                               group="skinning field")
    # Colours
    shading: str = _core("world", "'world': colours follow how the body faces a fixed light rig (evaluated from "
                         "the training camera centre; right for a fixed camera and a turning subject); 'view': "
                         "view-dependent colours from the rendering camera (3DGS)", group="colours", product=True,
                         choices=("world", "view"))
    # Losses
    target: str = _core("auto", "what the render is compared with: 'frame' (the frame as it is), 'masked' (the "
                        "masked foreground over the background colour) or 'auto' ('frame' when meta.json declares "
                        "the flat background the frames were rendered over, so their anti-aliased edge pixels "
                        "stay; 'masked' otherwise)", group="losses", product=True,
                        choices=("auto", "frame", "masked"))
    lambda_ssim: float = _core(0.2, "weight of (1 - SSIM) in the photometric loss [fraction, 0-1]", group="losses")
    lambda_mask: float = _core(0.1, "weight of the L1 loss between rendered alpha and the foreground mask "
                               "[loss weight]",
                               group="losses")
    lambda_scale: float = _core(0.0, "weight of a penalty on Gaussian scales above 5 % of the canonical extent "
                                "(world units) [loss weight]", group="losses")
    # Optimizer (3DGS rates; positions scaled by the canonical extent)
    lr_position: float = _core(1.6e-4, "initial position learning rate [Adam step size, times the canonical extent]",
                               group="optimizer")
    lr_position_final: float = _core(1.6e-6, "final position learning rate [Adam step size, times the canonical "
                                     "extent]",
                                     group="optimizer")
    lr_scale: float = _core(5e-3, "learning rate of log-scales [Adam step size]", group="optimizer")
    lr_rotation: float = _core(1e-3, "learning rate of quaternions [Adam step size]", group="optimizer")
    lr_opacity: float = _core(2.5e-2, "learning rate of opacity logits [Adam step size]", group="optimizer")
    lr_color: float = _core(2.5e-3, "learning rate of SH DC coefficients, higher orders 1/20 of it [Adam step size]",
                            group="optimizer")
    # Adaptive density control
    densify_from: int = _core(500, "first step of densification (after the warm-up) [step]", group="density control")
    densify_until: int = _core(6000, "last step of densification [step]", group="density control")
    densify_every: int = _core(100, "steps between densification rounds [steps]", group="density control")
    densify_grad_threshold: float = _core(2e-4, "mean screen-space gradient above which a Gaussian is cloned or "
                                          "split [NDC units]", group="density control")
    densify_percent_dense: float = _core(0.01, "size separating clone from split [fraction of the canonical "
                                         "extent]", group="density control")
    max_gaussians: int = _core(200000, "the most Gaussians the fit holds, a hard cap: a densification round clones "
                               "and splits only as many as stay within it (those of the largest gradients), and an "
                               "initialization with more keeps a random subset [Gaussians]", group="density control")
    densify_slowdown: float = _core(0.0, "where density control slows down, as ToMiE's Gaussian budget (appendix "
                                    "A.4): past this share of --max-gaussians the clone/split threshold rises with "
                                    "the count, and from 1.5 times it no round densifies; 0 = never, the threshold "
                                    "holds up to the cap [fraction of --max-gaussians]", group="density control")
    prune_opacity: float = _core(0.005, "Gaussians whose opacity falls below this are pruned [opacity, 0-1]",
                                 group="density control")
    prune_max_scale: float = _core(0.1, "Gaussians larger than this are pruned [fraction of the canonical extent]",
                                   group="density control")
    opacity_reset_every: int = _core(2500, "steps between opacity resets (0 = never) [steps]", group="density control")
    # Book-keeping
    log_every: int = _core(50, "steps between training-log lines (JSON lines) [steps]", group="book-keeping")
    checkpoint_every: int = _core(1000, "steps between checkpoints (written atomically) [steps]", group="book-keeping")
    preview_frames: int = _core(3, "training frames rendered as previews at the end [frames]", group="book-keeping")
    #: the enabled extensions' options by extension name (see :mod:`warpavatar.extensions`)
    extensions: dict = field(default_factory=dict)

    def __post_init__(self):
        _check_ranges(self)
        _check_choices(self)
        if not self.skinning_prior_temperature > 0.0:
            raise ValueError(f"skinning_prior_temperature must be positive, got {self.skinning_prior_temperature}")
        # the registry's order, whatever order they were given in
        order = [cls.name for cls in registered()]
        for name in self.extensions:
            get_extension(name)  # unknown names fail here
        self.extensions = {name: self.extensions[name] for name in order if name in self.extensions}
        for name, options in self.extensions.items():
            cls = get_extension(name)
            if not isinstance(options, cls.options_type):
                raise TypeError(f"the options of {name!r} must be a {cls.options_type.__name__}, got {options!r}")
            _check_choices(options)
            for other, reason in cls.conflicts.items():
                if other in self.extensions:
                    raise ValueError(reason)
            for needed in cls.requires:
                if needed not in self.extensions:
                    raise ValueError(f"{_flag(cls.switch_name())} needs {_flag(get_extension(needed).switch_name())}")
            cls.check(options, self)

    # ------------------------------------------------------------------------------------------ the flat view
    @classmethod
    def from_flat(cls, values: Mapping) -> "FitConfig":
        """A config from one flat mapping of core fields, extension switches and extension options (unset ones
        keep their defaults; an extension is on when its switch says so, else by its own default).

        Raises:
            ValueError: a name that is none of these (the message lists them), or values that do not fit.
        """
        core = {f.name for f in fields(cls) if f.name != "extensions"}
        switches = {ext.switch_name(): ext for ext in registered()}
        owners = option_owners()
        unknown = sorted(set(values) - core - set(switches) - set(owners))
        if unknown:
            raise ValueError(f"unknown config fields: {unknown}")
        extensions = {}
        for ext in registered():
            switch = values.get(ext.switch_name(), ext.switch_default())
            if ext.switch_enables(switch):
                names = {f.name for f in fields(ext.options_type)}
                chosen = {k: v for k, v in values.items() if k in names}
                if ext.switch_modes:
                    chosen[ext.switch_name()] = switch
                extensions[ext.name] = ext.options_type(**chosen)
        return cls(**{k: v for k, v in values.items() if k in core}, extensions=extensions)

    def enabled(self, name: str) -> bool:
        """Whether the extension ``name`` is on."""
        return name in self.extensions

    # ---------------------------------------------------------------------------------------------- files
    def to_dict(self) -> dict:
        values = {f.name: getattr(self, f.name) for f in fields(self) if f.name != "extensions"}
        values["extensions"] = {name: dataclasses.asdict(options) for name, options in self.extensions.items()}
        return values

    @classmethod
    def from_dict(cls, values: dict) -> "FitConfig":
        """Read :meth:`to_dict`, or the flat layout of configs written before extensions had options of their
        own (every field at the top level)."""
        if "extensions" not in values:
            return cls.from_flat(values)
        values = dict(values)
        extensions = {name: get_extension(name).options_type(**options)
                      for name, options in values.pop("extensions").items()}
        known = {f.name for f in fields(cls)}
        unknown = set(values) - known
        if unknown:
            raise ValueError(f"unknown config fields: {sorted(unknown)}")
        return cls(**values, extensions=extensions)

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), indent=2)


def _flag(name: str) -> str:
    return "--" + name.replace("_", "-")


_UNBOUNDED = float("inf")
RANGES: dict[str, tuple[float, float, bool]] = {
    # name: (low, high, low excluded); sizes above ``high`` would exhaust memory or time long before a result
    "iterations": (1, 10_000_000, False),
    "seed": (0, 2**63 - 1, False),  # torch's generators take seeds up to 2**64 - 1; int64 keeps them portable
    "image_scale": (0.0, 4.0, True),
    "max_train_frames": (0, _UNBOUNDED, False),
    "init_points_per_bone": (1, 100_000, False),
    "init_carve_candidates": (0, 100_000_000, False),
    "init_carve_points": (0, 10_000_000, False),
    "sh_degree": (0, 3, False),
    "sh_increase_every": (1, _UNBOUNDED, False),
    "grid_cells": (2, 512, False),
    "grid_min_cells": (2, 512, False),
    "field_hidden": (1, 4096, False),
    "field_layers": (1, 64, False),
    "field_frequencies": (0, 32, False),
    "field_warmup_steps": (0, 10_000_000, False),
    "gaussian_only_steps": (0, _UNBOUNDED, False),
    "field_cells_every": (1, _UNBOUNDED, False),
    "field_warmup_batch": (0, _UNBOUNDED, False),
    "field_lr": (0.0, 1.0, True),
    "lambda_bone": (0.0, _UNBOUNDED, False),
    "lambda_ssim": (0.0, 1.0, False),
    "lambda_mask": (0.0, _UNBOUNDED, False),
    "lambda_scale": (0.0, _UNBOUNDED, False),
    "lr_position": (0.0, 1.0, True),
    "lr_position_final": (0.0, 1.0, True),
    "lr_scale": (0.0, 1.0, True),
    "lr_rotation": (0.0, 1.0, True),
    "lr_opacity": (0.0, 1.0, True),
    "lr_color": (0.0, 1.0, True),
    "densify_from": (0, _UNBOUNDED, False),
    "densify_until": (0, _UNBOUNDED, False),
    "densify_every": (1, _UNBOUNDED, False),
    "densify_grad_threshold": (0.0, _UNBOUNDED, True),
    "densify_percent_dense": (0.0, 1.0, True),
    "max_gaussians": (1, 100_000_000, False),
    "densify_slowdown": (0.0, 1.0, False),
    "prune_opacity": (0.0, 1.0, False),
    "prune_max_scale": (0.0, _UNBOUNDED, True),
    "opacity_reset_every": (0, _UNBOUNDED, False),
    "log_every": (1, _UNBOUNDED, False),
    "checkpoint_every": (1, _UNBOUNDED, False),
    "preview_frames": (0, 1000, False),
}
"""The accepted range of each numeric core option: ``(low, high, low excluded)``, both ends in the option's
unit; :class:`FitConfig` rejects values outside it (and non-finite ones) naming the option's flag."""


def _number(value: float) -> str:
    return str(int(value)) if float(value).is_integer() else f"{value:g}"


def range_text(name: str) -> str:
    """The accepted range of the core option ``name`` in words ("at least 1 and at most 10000000")."""
    low, high, low_excluded = RANGES[name]
    low_text = f"{'above' if low_excluded else 'at least'} {_number(low)}"
    return low_text + ("" if high == _UNBOUNDED else f" and at most {_number(high)}")


def _check_ranges(config: FitConfig) -> None:
    for name, (low, high, low_excluded) in RANGES.items():
        value = getattr(config, name)
        integer = config.__dataclass_fields__[name].type in ("int", int)
        if isinstance(value, bool) or not isinstance(value, (int, float)) or (integer and value != int(value)):
            kind = "an integer" if integer else "a number"
            raise ValueError(f"{_flag(name)} must be {kind}, got {value!r}")
        below = value <= low if low_excluded else value < low
        if not math.isfinite(value) or below or value > high:
            raise ValueError(f"{_flag(name)} must be {range_text(name)}, got {value!r}")
    if config.grid_min_cells > config.grid_cells:
        raise ValueError(f"--grid-min-cells ({config.grid_min_cells}) must not exceed --grid-cells "
                         f"({config.grid_cells})")


def flat_options(config: FitConfig) -> dict:
    """The options of ``config`` by name, in the flags' flat vocabulary: the core fields, and each enabled
    extension's switch (its word, or "on") and options."""
    values = config.to_dict()
    flat = {name: value for name, value in values.items() if name != "extensions"}
    for name, options in values["extensions"].items():
        switch = get_extension(name).switch_name()
        flat[switch] = options.pop(switch, "on")
        flat.update(options)
    return flat


def changed_options(first: FitConfig, second: FitConfig) -> list[tuple[str, object, object]]:
    """``(name, value in first, value in second)`` of every option (:func:`flat_options`) whose values differ,
    in name order; an option of an extension that is off in one of them has the value None there."""
    a, b = flat_options(first), flat_options(second)
    return [(name, a.get(name), b.get(name)) for name in sorted(a.keys() | b.keys()) if a.get(name) != b.get(name)]


def option_owners() -> dict[str, list]:
    """Each extension option's name -> the extensions that have it (two for a shared option); an extension's
    field that holds its switch's word is the switch, not an option."""
    owners: dict[str, list] = {}
    for ext in registered():
        for f in fields(ext.options_type):
            if not (ext.switch_modes and f.name == ext.switch_name()):
                owners.setdefault(f.name, []).append(ext)
    return owners
