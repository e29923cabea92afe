"""The extension protocol: how an optional part of the avatar takes part in a fit.

An extension owns one optional feature from end to end: its options (a dataclass whose fields become
``warpavatar-fit`` flags), which other extensions it conflicts with or needs, the part it adds to the avatar
(:class:`~warpavatar.model.parts.AvatarPart`: what posing, rendering, exports and the avatar file see), and
how that part trains: its loss terms, its optimizers, its schedule and what it keeps in checkpoints. The
trainer knows none of them by name: it calls the hooks below on every enabled extension, in the registry's
order (:mod:`warpavatar.extensions`), and an extension never imports the trainer.

One training step calls, in this order::

    begin_step(step)            before the skinning grid is read: may change the model (grow joints)
    frame_input(step)           the explicit input of its avatar part for this step's render, or None
    step_input(step)            the same, computed as part of the step's device work (captured with it)
      ... the avatar is posed and rendered ...
    losses(step)                {name: LossTerm(weight, value)}; the trainer sums weight * value
    optimizers(step)            the optimizers that step now (zeroed before, stepped after the backward)
      ... backward ...
    after_backward(step)        gradients are there (pool them, make them sparse, ...)
      ... optimizers step ...
    after_step(step)            parameters may be projected onto constraints

Between densification events the shapes of a step stay fixed, so on CUDA the trainer captures the device work
from posing to ``after_step`` as a CUDA graph and replays it (``--cuda-graph``), refilling only the frame's
buffers (``step.frame``: the training frame's index on the device is one of them); ``begin_step``,
``frame_input`` and ``optimizers`` run every step on the host. An input that must be computed with gradients
every step (a window of simulated frames) comes from ``step_input``, which runs inside the captured work and
reads the frame from ``step.frame``; ``graph_key`` names what the captured work depends on beyond those
buffers' values (the shapes and storage of the tensors it reads and writes). An extension whose step
does host work (reads values back, follows a per-step schedule, swaps tensors) keeps the default
``step_capturable() -> False`` and the trainer runs those steps eagerly.

When density control clones, splits and prunes Gaussians, it calls ``before_densify(visible_count)`` while the
old Gaussians still exist, then ``on_gaussians_renumbered(source_index)``. At the end ``finish()`` runs before
the avatar is written and ``write_outputs(folder)`` after; ``state_dict``/``load_state_dict`` carry everything
a resumed fit needs.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, ClassVar, NamedTuple

import torch

from warpavatar.optim import Optimizer

__all__ = ["option", "NoOptions", "LossTerm", "FitContext", "StepContext", "Extension"]


def option(default, help_text: str, *, product: bool = False, choices: tuple | None = None):
    """A dataclass field that is also a ``warpavatar-fit`` flag (``--field-name``).

    Args:
        default: the value when neither the preset nor the command line sets one.
        help_text: what ``--help`` says, with the unit where there is one.
        product: a main option of the product (listed first by ``--help``) rather than a research knob.
        choices: the values the flag accepts, when they are few (a config with other values is refused).
    """
    if isinstance(default, (list, dict, set)):
        raise TypeError("options hold plain values")
    return field(default=default, metadata={"help": help_text, "product": product, "choices": choices})


@dataclass
class NoOptions:
    """The options of an extension that has none besides being on."""


class LossTerm(NamedTuple):
    """One term of the training loss: the trainer adds ``weight * value`` and logs ``value`` by name."""

    weight: float
    value: torch.Tensor


@dataclass
class FitContext:
    """What a fit gives its extensions; fixed for the whole fit.

    Attributes:
        avatar: the avatar being fitted (:class:`~warpavatar.model.avatar.Avatar`); its Gaussians are replaced
            as density control renumbers them, so read ``avatar.gaussians`` when needed.
        frames: the training frames (:class:`~warpavatar.fit.training_frames.TrainingFrames`): ``count``,
            ``bone_transforms`` [T,J,4,4], ``intervals`` [T] and ``seconds`` (seconds since the frame before),
            ``times`` [T] (seconds), ``skeleton``.
        config: the whole fit configuration (core fields and every enabled extension's options).
        extent: half the diagonal of the canonical box [world units]: the length scale of a fit.
        skinning: the skinning-field stage (:class:`~warpavatar.fit.skinning_field_stage.SkinningStage`): ``field``,
            ``grid(...)``, ``add_joints(parents)``.
        density: the density control (:class:`~warpavatar.fit.density.DensityControl`): ``visible_count`` [N],
            the steps each Gaussian was seen in since the last densification round.
        log: writes one record to the training log.
    """

    avatar: Any
    frames: Any
    config: Any
    extent: float
    skinning: Any
    density: Any
    log: Callable[[dict], None]

    @property
    def device(self) -> torch.device:
        return self.avatar.gaussians.means.device


@dataclass
class StepContext:
    """One training step as the extensions see it.

    Attributes:
        step: the step's number (0-based).
        index: the training frame it trains on (index into ``FitContext.frames``).
        frame: the same index as an int64 0-dim tensor on the training device, held in the step's buffers
            (refilled before every step, so a captured step reads the frame of the step it replays); set before
            :meth:`Extension.step_input` runs, None before.
        train_field: whether the skinning field (and the networks that train with it) train in this step.
        grid: the skinning grid of this step (:meth:`warpavatar.model.skinning_field.VoxelSkinningField.grid_weights`,
            with gradients when the field trains), read on first use: an extension that changes the field in
            :meth:`Extension.begin_step` does so before the grid is read.
        posed: the posed Gaussians (:class:`~warpavatar.model.avatar.PosedGaussians`), set after the render.
        image: [H,W,3] the render; ``alpha`` [H,W]; ``depth`` [H,W] the composited camera-space depth, not
            normalized by alpha [world units]; ``target`` [H,W,3] its ground truth; ``mask`` [H,W] or None.
    """

    step: int
    index: int
    train_field: bool
    read_grid: Callable[[], torch.Tensor] = field(repr=False, default=None)
    frame: torch.Tensor | None = None
    posed: Any = None
    image: torch.Tensor | None = None
    alpha: torch.Tensor | None = None
    depth: torch.Tensor | None = None
    target: torch.Tensor | None = None
    mask: torch.Tensor | None = None

    @property
    def grid(self) -> torch.Tensor:
        return self.read_grid()


class Extension:
    """Base of the fit's optional parts. Subclasses set the class attributes and override the hooks they need
    (every hook does nothing by default).

    Args:
        options: an instance of :attr:`options_type` (this extension's options).
        fit: the fit's :class:`FitContext`.
    """

    name: ClassVar[str] = ""
    """Name in the registry, the config, the checkpoint and (for its avatar part) the avatar."""
    switch: ClassVar[str] = ""
    """The option that turns it on (``--<switch>`` in kebab-case); its name when empty."""
    switch_modes: ClassVar[tuple[str, ...]] = ()
    """When set, the switch takes one of these words instead of on/off (e.g. ``auto``, ``on``, ``off``): ``off``
    turns the extension off, and its options receive the word in their field named like the switch."""
    default_mode: ClassVar[str] = ""
    """The switch's word when nothing sets it (with :attr:`switch_modes`)."""
    title: ClassVar[str] = ""
    """Title of its group of options in ``--help``."""
    summary: ClassVar[str] = ""
    """Help of the switch: what the extension does, in a sentence or two."""
    options_type: ClassVar[type] = NoOptions
    """The dataclass of its options (fields made with :func:`option`)."""
    enabled_by_default: ClassVar[bool] = False
    conflicts: ClassVar[dict[str, str]] = {}
    """Extensions it cannot be combined with, each with the reason told to the user."""
    requires: ClassVar[tuple[str, ...]] = ()
    """Extensions it needs."""
    presets: ClassVar[dict[str, dict]] = {}
    """Its values in named presets: ``{preset name: {its switch or option: value}}`` (e.g. a shorter schedule in
    ``quick``)."""

    def __init__(self, options, fit: FitContext):
        self.options = options
        self.fit = fit

    @classmethod
    def switch_name(cls) -> str:
        """The option that turns it on."""
        return cls.switch or cls.name

    @classmethod
    def switch_default(cls):
        """The switch's value when nothing sets it: a word of :attr:`switch_modes`, else on or off."""
        return cls.default_mode if cls.switch_modes else cls.enabled_by_default

    @classmethod
    def switch_enables(cls, value) -> bool:
        """Whether a value of the switch turns the extension on.

        Raises:
            ValueError: a word that is not one of :attr:`switch_modes`.
        """
        if not cls.switch_modes:
            return bool(value)
        if value not in cls.switch_modes:
            raise ValueError(f"--{cls.switch_name().replace('_', '-')} must be one of {', '.join(cls.switch_modes)}, "
                             f"got {value!r}")
        return value != "off"

    @classmethod
    def check(cls, options, config) -> None:
        """Raise ValueError where its options do not fit the rest of ``config`` (beyond conflicts/requires)."""

    # --------------------------------------------------------------------------------------------- hooks
    def attach(self) -> None:
        """Build what exists from the start of the fit (after the avatar and the skinning stage)."""

    def begin_step(self, step: StepContext) -> None:
        """Start of a step, before the skinning grid is read."""

    def frame_input(self, step: StepContext) -> Any | None:
        """The explicit input of this extension's avatar part for the step's render (None: the part decides)."""
        return None

    def step_input(self, step: StepContext) -> Any | None:
        """The explicit input of this extension's avatar part for the step's render, computed as part of the
        step's device work (captured and replayed with it when the step is capturable), or None. Read the frame
        from ``step.frame`` (a device tensor), never ``step.index``, and only tensors that keep their storage;
        write state back in place (``index_copy_``). Runs after :meth:`frame_input`, which may prepare it on the
        host (a refreshed cache, a flag that a part exists)."""
        return None

    def losses(self, step: StepContext) -> dict[str, LossTerm]:
        """This step's loss terms by name."""
        return {}

    def optimizers(self, step: StepContext) -> list[Optimizer | torch.optim.Optimizer]:
        """The optimizers that step in this step (:mod:`warpavatar.optim`'s, or torch's: anything with ``step``,
        ``zero_grad``, ``param_groups`` and ``state``)."""
        return []

    def after_backward(self, step: StepContext) -> None:
        """The gradients of this step exist; the optimizers have not stepped yet."""

    def after_step(self, step: StepContext) -> None:
        """The optimizers have stepped (project parameters onto constraints here)."""

    def step_capturable(self, step: StepContext) -> bool:
        """Whether the device work of this step (posing through :meth:`losses`, the backward,
        :meth:`after_backward`, the optimizers and :meth:`after_step`) may be captured once as a CUDA graph and
        replayed for the following steps of the same shapes (``--cuda-graph``). Return True only when those hooks
        read nothing from the device, make no decision on host values that change between such steps (the step
        number, a frame index, a counter) and change tensors only in place; :meth:`begin_step` and
        :meth:`frame_input` run every step, outside the graph. The default, False, runs every step eagerly."""
        return False

    def graph_key(self, step: StepContext) -> tuple:
        """What this extension's captured work depends on beyond the values of the tensors it reads: shapes, the
        storage (``data_ptr``) of tensors it reads or writes in place, Python numbers baked into the work. The
        trainer captures the step again when any extension's key changes. Default: nothing."""
        return ()

    def before_densify(self, visible_count: torch.Tensor) -> None:
        """Density control is about to renumber the Gaussians; ``visible_count`` [N]: steps each was seen in
        since the last round."""

    def on_gaussians_renumbered(self, source_index: torch.Tensor) -> None:
        """The Gaussians were cloned, split or pruned: new Gaussian ``i`` is (or comes from) old
        ``source_index[i]``."""

    def log_values(self) -> dict[str, float]:
        """Values for the training log beyond the loss terms (read only on logging steps)."""
        return {}

    def finish(self) -> None:
        """The fit is over; runs before the avatar is written."""

    def write_outputs(self, folder: Path) -> None:
        """Write this extension's own files into the fit's output folder (after the avatar)."""

    def summary_lines(self) -> list[str]:
        """What ``warpavatar-fit`` prints about this extension at the end."""
        return []

    def state_dict(self) -> dict:
        """Everything a resumed fit needs (its part, optimizers, caches)."""
        return {}

    def load_state_dict(self, state: dict) -> None:
        """Restore :meth:`state_dict` (after :meth:`attach`)."""
