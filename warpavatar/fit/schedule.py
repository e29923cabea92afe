"""The core's optimization schedule: the Gaussians' optimizer with the configured learning rates, the decay of
the position learning rate and the spherical-harmonics degree that each step renders with."""

from __future__ import annotations

import math

from warpavatar.fit.config import FitConfig

__all__ = ["make_gaussian_optimizer", "position_learning_rate", "active_sh_degree"]


def make_gaussian_optimizer(gaussians, config: FitConfig, *, extent: float) -> None:
    """Give ``gaussians`` (a :class:`~warpavatar.model.gaussians.GaussianModel`) a new Adam optimizer with the
    config's learning rates, the position's scaled by ``extent``.

    Args:
        gaussians: the Gaussians to optimize; their ``optimizer`` is replaced.
        config: the fit configuration (``lr_position``, ``lr_scale``, ``lr_rotation``, ``lr_opacity``,
            ``lr_color``).
        extent: half the diagonal of the canonical box [world units].
    """
    gaussians.make_optimizer(lr_position=config.lr_position * extent, lr_scale=config.lr_scale,
                             lr_rotation=config.lr_rotation, lr_opacity=config.lr_opacity, lr_color=config.lr_color)


def position_learning_rate(config: FitConfig, step: int, *, extent: float) -> float:
    """The position learning rate of ``step``: log-linear from ``lr_position`` to ``lr_position_final`` over the
    fit's ``iterations``, then held.

    Args:
        config: the fit configuration.
        step: the step's number (0-based).
        extent: half the diagonal of the canonical box [world units]; both rates are multiples of it.

    Returns:
        The Adam step size of the means [world units].
    """
    fraction = min(1.0, step / max(1, config.iterations))
    start, end = config.lr_position * extent, config.lr_position_final * extent
    return math.exp(math.log(start) * (1 - fraction) + math.log(end) * fraction)


def active_sh_degree(config: FitConfig, step: int) -> int:
    """The spherical-harmonics degree ``step`` renders with: one more every ``sh_increase_every`` steps, up to
    ``sh_degree``."""
    return min(config.sh_degree, step // max(1, config.sh_increase_every))
