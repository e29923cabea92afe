"""Adaptive density control (3DGS) under a hard cap on the Gaussian count, slowed past a soft budget (ToMiE
appendix A.4), as its own strategy."""

from __future__ import annotations

import math

import torch

__all__ = ["DensityControl", "strongest"]


def strongest(grad_norm: torch.Tensor, *, threshold: float, count: int) -> torch.Tensor:
    """``grad_norm`` [N] with only its ``count`` largest values at or above ``threshold`` (> 0) kept there: the
    other values at or above it become 0, so that at most ``count`` Gaussians pass the threshold (ties go to the
    lower index). When no more than ``count`` pass it, ``grad_norm`` itself (not a copy) is returned; a ``count``
    of at least N returns it without reading the device."""
    if count >= grad_norm.shape[0]:
        return grad_norm
    selected = grad_norm >= threshold
    if int(selected.sum()) <= count:
        return grad_norm
    ranked = torch.where(selected, grad_norm, torch.full_like(grad_norm, -math.inf))
    order = torch.sort(ranked, descending=True, stable=True).indices[:max(count, 0)]
    kept = torch.zeros_like(selected)
    kept[order] = True
    return torch.where(kept | ~selected, grad_norm, torch.zeros_like(grad_norm))


class DensityControl:
    """Clones and splits the Gaussians whose screen-space gradient stays large, prunes the faint and the huge,
    resets opacities, and tells the fit's extensions when the Gaussians are renumbered.

    ``max_gaussians`` is a hard cap: a round clones and splits at most as many Gaussians as keep the count at or
    below it (those of the largest gradients; a split adds one Gaussian, as a clone does). Past the budget,
    ``densify_slowdown`` times the cap (when set), the clone/split threshold rises with the count, and from 1.5
    times the budget no round densifies (ToMiE A.4).

    Args:
        config: the fit configuration (``densify_*``, ``max_gaussians``, ``prune_*``, ``opacity_reset_every``).
        extent: the canonical box's half-diagonal [world units] (sizes are relative to it).
        generator: the fit's random generator (the samples of split Gaussians).

    Attributes:
        grad_accum: [N,2] summed absolute screen-space position gradients since the last round [NDC units].
        visible_count: [N] steps each Gaussian was visible in since the last round.
    """

    def __init__(self, config, *, extent: float, generator: torch.Generator):
        self.config = config
        self.extent = extent
        self.generator = generator
        self.grad_accum = self.visible_count = None
        self._pixel_to_ndc: dict[tuple[int, int], torch.Tensor] = {}

    def reset(self, count: int, device) -> None:
        """Start a new round's statistics for ``count`` Gaussians."""
        self.grad_accum = torch.zeros(count, 2, device=device)
        self.visible_count = torch.zeros(count, device=device)

    @torch.no_grad()
    def accumulate(self, grad_out: torch.Tensor, radii: torch.Tensor, camera) -> None:
        """Add one step's screen gradients [N,2] (pixels) and visibility (``radii`` [N,2] > 0 somewhere)."""
        # absolute screen gradient in NDC units (pixels -> [-1, 1]) as 3DGS thresholds it
        size = (camera.width, camera.height)
        if size not in self._pixel_to_ndc:  # made once per size: no host-to-device copy in a step
            self._pixel_to_ndc[size] = torch.tensor([size[0] * 0.5, size[1] * 0.5], device=grad_out.device)
        self.grad_accum += grad_out * self._pixel_to_ndc[size]
        self.visible_count += (radii > 0).any(dim=-1).float()

    @torch.no_grad()
    def after_step(self, step: int, gaussians, extensions) -> None:
        """Run a round when one is due after step ``step`` (then ``before_densify`` and
        ``on_gaussians_renumbered`` of each extension), and the opacity reset."""
        config = self.config
        in_window = config.densify_from <= step <= config.densify_until
        if in_window and step > 0 and step % config.densify_every == 0:
            count = gaussians.count
            threshold = config.densify_grad_threshold
            budget = config.densify_slowdown * config.max_gaussians  # ToMiE A.4's budget (0: none)
            if budget and count > budget:  # ToMiE A.4: raise the threshold as the count passes the budget
                threshold *= 2.0 + (count - budget) / (budget / 6.0)
            grad_norm = (self.grad_accum / self.visible_count.clamp_min(1)[:, None]).norm(dim=-1)
            for extension in extensions:
                extension.before_densify(self.visible_count)
            source = torch.arange(count, device=self.grad_accum.device)
            room = config.max_gaussians - count
            if room > 0 and not (budget and count >= 1.5 * budget):
                source = gaussians.densify(strongest(grad_norm, threshold=threshold, count=room),
                                           threshold=threshold, size_split=config.densify_percent_dense * self.extent,
                                           generator=self.generator)
            max_scale = gaussians.scales.detach().max(dim=1).values
            keep = (gaussians.opacities.detach() > config.prune_opacity) & (
                max_scale < config.prune_max_scale * self.extent)
            if not bool(keep.all()):
                gaussians.prune(keep)
                source = source[keep]
            self.reset(gaussians.count, source.device)
            for extension in extensions:
                extension.on_gaussians_renumbered(source)
        if config.opacity_reset_every and step > 0 and step % config.opacity_reset_every == 0 \
                and step <= config.densify_until:
            gaussians.reset_opacity()

    def state_dict(self) -> dict:
        return {"grad_accum": self.grad_accum.cpu(), "visible_count": self.visible_count.cpu()}

    def load_state_dict(self, state: dict, *, device) -> None:
        self.grad_accum = state["grad_accum"].to(device)
        self.visible_count = state["visible_count"].to(device)
