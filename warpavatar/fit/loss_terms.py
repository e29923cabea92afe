"""The training loss of a step: the core's terms, each extension's added by name, their weighted sum, and the
detached copies a step hands back for logging."""

from __future__ import annotations

import torch

from warpavatar.extensions import LossTerm, StepContext
from warpavatar.fit.config import FitConfig
from warpavatar.metrics import image_loss_terms

__all__ = ["core_loss_terms", "add_extension_loss_terms", "weighted_loss", "detached_loss_terms"]


def core_loss_terms(step: StepContext, *, config: FitConfig, gaussians, extent: float) -> dict[str, LossTerm]:
    """The photometric loss (L1 and D-SSIM) and the mask term of the step's render, and the scale term.

    Args:
        step: the step, rendered (``image`` [H,W,3], ``alpha`` [H,W], ``target`` [H,W,3], ``mask`` [H,W] or None).
        config: the fit configuration (``lambda_ssim``, ``lambda_mask``, ``lambda_scale``).
        gaussians: the canonical Gaussians (``scales`` [N,3], world units).
        extent: half the diagonal of the canonical box [world units]; scales past 5% of it are penalized.

    Returns:
        The terms by name, in the order they are summed.
    """
    image_terms = image_loss_terms(step.image, step.target, lambda_ssim=config.lambda_ssim, alpha=step.alpha,
                                   mask=step.mask, lambda_mask=config.lambda_mask)
    terms = {name: LossTerm(*term) for name, term in image_terms.items()}
    if config.lambda_scale > 0:
        terms["scale"] = LossTerm(config.lambda_scale, torch.relu(gaussians.scales - 0.05 * extent).mean())
    return terms


def add_extension_loss_terms(terms: dict[str, LossTerm], extensions, step: StepContext) -> None:
    """Add each extension's loss terms of ``step`` to ``terms``, in the registry's order.

    Raises:
        ValueError: an extension returns a term whose name another part has.
    """
    for extension in extensions:
        for name, term in extension.losses(step).items():
            if name in terms:
                raise ValueError(f"extension {extension.name!r} returns a loss term {name!r} another part has")
            terms[name] = term


def weighted_loss(terms: dict[str, LossTerm]) -> torch.Tensor:
    """The training loss: the sum of ``weight * value`` over ``terms``, in their order (0-dim tensor)."""
    return sum(term.weight * term.value for term in terms.values())


def detached_loss_terms(terms: dict[str, LossTerm], loss: torch.Tensor) -> dict[str, LossTerm]:
    """``terms`` with their values detached from the autograd graph, and ``loss`` (weight 1) added last."""
    detached = {name: LossTerm(term.weight, term.value.detach()) for name, term in terms.items()}
    detached["loss"] = LossTerm(1.0, loss.detach())
    return detached
