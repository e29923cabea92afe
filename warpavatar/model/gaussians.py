"""Canonical 3D Gaussians: parameters, activations, their optimizer, and adaptive density control.

Stored (raw, optimized) parameters follow 3DGS: positions [N,3] in world units of the rest pose, log-scales
[N,3], quaternions [N,4] (w, x, y, z; normalized when used), opacity logits [N], SH coefficients split in
DC [N,1,3] and higher orders [N,(d+1)^2-1,3].
"""

from __future__ import annotations

import math

import torch

from warpavatar.geometry import SH_C0, quat_to_matrix
from warpavatar.optim import Adam

__all__ = ["rgb_to_sh_dc", "sh_dc_to_rgb", "GaussianModel"]

_PARAMETER_NAMES = ("means", "log_scales", "quats", "opacity_logits", "sh_dc", "sh_rest")


def rgb_to_sh_dc(rgb: torch.Tensor) -> torch.Tensor:
    """SH DC coefficient giving colour ``rgb`` (in 0..1) for every view direction."""
    return (rgb - 0.5) / SH_C0


def sh_dc_to_rgb(dc: torch.Tensor) -> torch.Tensor:
    """Inverse of :func:`rgb_to_sh_dc`."""
    return dc * SH_C0 + 0.5


class GaussianModel(torch.nn.Module):
    """A set of canonical Gaussians and the Adam optimizer that trains them.

    Args:
        means: [N,3] canonical positions (world units).
        rgb: [N,3] initial colours in 0..1.
        scales: [N,3] initial scales (world units, > 0).
        sh_degree: maximum SH degree of the colours (0..3).
        opacity: initial opacity of every Gaussian, in (0, 1).
    """

    def __init__(self, means: torch.Tensor, rgb: torch.Tensor, scales: torch.Tensor, *, sh_degree: int = 3,
                 opacity: float = 0.1):
        super().__init__()
        if not 0 <= sh_degree <= 3:
            raise ValueError(f"sh_degree must be in 0..3, got {sh_degree}")
        count = means.shape[0]
        self.sh_degree = sh_degree
        quats = torch.zeros(count, 4, dtype=torch.float32, device=means.device)
        quats[:, 0] = 1.0
        rest = torch.zeros(count, (sh_degree + 1) ** 2 - 1, 3, dtype=torch.float32, device=means.device)
        logit = math.log(opacity / (1.0 - opacity))
        self.means = torch.nn.Parameter(means.float().clone())
        self.log_scales = torch.nn.Parameter(scales.float().clamp_min(1e-7).log())
        self.quats = torch.nn.Parameter(quats)
        self.opacity_logits = torch.nn.Parameter(torch.full((count,), logit, device=means.device))
        self.sh_dc = torch.nn.Parameter(rgb_to_sh_dc(rgb.float()).reshape(count, 1, 3).clone())
        self.sh_rest = torch.nn.Parameter(rest)
        self.optimizer: Adam | None = None

    # ----------------------------------------------------------------------------------------------- access
    @property
    def count(self) -> int:
        """Number of Gaussians."""
        return self.means.shape[0]

    @property
    def scales(self) -> torch.Tensor:
        return self.log_scales.exp()

    @property
    def opacities(self) -> torch.Tensor:
        return torch.sigmoid(self.opacity_logits)

    @property
    def normalized_quats(self) -> torch.Tensor:
        return self.quats / self.quats.norm(dim=-1, keepdim=True).clamp_min(1e-12)

    def sh_coefficients(self, degree: int | None = None) -> torch.Tensor:
        """SH coefficients [N,(degree+1)^2,3] up to ``degree`` (default: the model's)."""
        degree = self.sh_degree if degree is None else degree
        coefficients = torch.cat([self.sh_dc, self.sh_rest], dim=1)
        return coefficients[:, : (degree + 1) ** 2]

    # --------------------------------------------------------------------------------------------- optimizer
    def make_optimizer(self, *, lr_position: float, lr_scale: float, lr_rotation: float, lr_opacity: float,
                       lr_color: float) -> Adam:
        """Create the Adam optimizer with one group per parameter (3DGS settings, eps 1e-15)."""
        if self.means.is_cuda:  # a tensor, so that a captured step reads the rate of the step it replays
            lr_position = torch.tensor(float(lr_position), device=self.means.device)
        groups = [
            {"params": [self.means], "lr": lr_position, "name": "means"},
            {"params": [self.log_scales], "lr": lr_scale, "name": "log_scales"},
            {"params": [self.quats], "lr": lr_rotation, "name": "quats"},
            {"params": [self.opacity_logits], "lr": lr_opacity, "name": "opacity_logits"},
            {"params": [self.sh_dc], "lr": lr_color, "name": "sh_dc"},
            {"params": [self.sh_rest], "lr": lr_color / 20.0, "name": "sh_rest"},
        ]
        self.optimizer = Adam(groups, lr=0.0, eps=1e-15)
        return self.optimizer

    def set_position_lr(self, lr: float) -> None:
        for group in self.optimizer.param_groups:
            if group["name"] == "means":
                if isinstance(group["lr"], torch.Tensor):
                    group["lr"].fill_(lr)  # in place: a captured optimizer step reads this tensor
                elif self.means.is_cuda:  # a float again (a loaded state dict)
                    group["lr"] = torch.tensor(float(lr), device=self.means.device)
                else:
                    group["lr"] = lr

    def _replace_parameters(self, build, build_moment=None) -> None:
        """Swap every parameter for ``build(name, old_tensor)`` and its Adam moments for
        ``build_moment(name, old_moment)`` (default: ``build``), keeping the optimizer pointing at them."""
        build_moment = build if build_moment is None else build_moment
        for name in _PARAMETER_NAMES:
            old = getattr(self, name)
            new = torch.nn.Parameter(build(name, old.detach()))
            if self.optimizer is not None:
                group = next(g for g in self.optimizer.param_groups if g["name"] == name)
                state = self.optimizer.state.pop(old, None)
                if state:
                    for key in ("exp_avg", "exp_avg_sq"):
                        state[key] = build_moment(name, state[key])
                    self.optimizer.state[new] = state
                group["params"] = [new]
            setattr(self, name, new)

    # ------------------------------------------------------------------------------- adaptive density control
    def prune(self, keep: torch.Tensor) -> None:
        """Keep the Gaussians where the boolean mask ``keep`` [N] is true."""
        self._replace_parameters(lambda name, tensor: tensor[keep])

    def append(self, values: dict[str, torch.Tensor]) -> None:
        """Add Gaussians given raw parameter values (same names as the parameters); their Adam moments start at 0."""
        self._replace_parameters(lambda name, tensor: torch.cat([tensor, values[name]], dim=0),
                                 lambda name, moment: torch.cat([moment, torch.zeros_like(values[name])], dim=0))

    def raw_parameters(self, index: torch.Tensor) -> dict[str, torch.Tensor]:
        """Detached copies of the raw parameters of the Gaussians ``index``."""
        return {name: getattr(self, name).detach()[index].clone() for name in _PARAMETER_NAMES}

    def densify(self, grad_norm: torch.Tensor, *, threshold: float, size_split: float, generator: torch.Generator
                ) -> torch.Tensor:
        """Clone small and split large Gaussians whose mean screen-space gradient exceeds ``threshold``.

        Args:
            grad_norm: [N] mean screen-space gradient magnitude of each Gaussian (NDC units).
            threshold: gradient above which a Gaussian is densified.
            size_split: Gaussians whose largest scale is above this (world units) are split in two
                (sampled from the Gaussian itself, scales divided by 1.6); smaller ones are cloned.
            generator: random generator for the split samples (keeps fits deterministic).

        Returns:
            [N'] for each Gaussian afterwards, the index (before) of the one it is, or was cloned or split from.
        """
        selected = grad_norm >= threshold
        max_scale = self.scales.detach().max(dim=1).values
        clone_index = torch.nonzero(selected & (max_scale <= size_split)).squeeze(1)
        split_index = torch.nonzero(selected & (max_scale > size_split)).squeeze(1)

        new_values = [self.raw_parameters(clone_index)]
        if split_index.numel():
            split = self.raw_parameters(split_index)
            samples = []
            stds = split["log_scales"].exp()
            quats = split["quats"]
            rotations = quat_to_matrix(quats / quats.norm(dim=-1, keepdim=True))
            for _ in range(2):
                noise = torch.randn(stds.shape, generator=generator, device="cpu").to(stds.device) * stds
                samples.append(split["means"] + torch.einsum("nij,nj->ni", rotations, noise))
            two = {name: torch.cat([value, value], dim=0) for name, value in split.items()}
            two["means"] = torch.cat(samples, dim=0)
            two["log_scales"] = two["log_scales"] - math.log(1.6)
            new_values.append(two)
        merged = {name: torch.cat([values[name] for values in new_values], dim=0) for name in _PARAMETER_NAMES}
        source = torch.cat([torch.arange(self.count, device=self.means.device), clone_index, split_index,
                            split_index])
        self.append(merged)
        if split_index.numel():
            keep = torch.ones(self.count, dtype=torch.bool, device=self.means.device)
            keep[split_index] = False
            self.prune(keep)
            source = source[keep]
        return source

    def reset_opacity(self, value: float = 0.01) -> None:
        """Clamp every opacity to at most ``value`` and clear the opacity moments (3DGS opacity reset)."""
        with torch.no_grad():
            limit = math.log(value / (1.0 - value))
            self.opacity_logits.clamp_(max=limit)
        if self.optimizer is not None:
            state = self.optimizer.state.get(self.opacity_logits)
            if state:
                state["exp_avg"].zero_()
                state["exp_avg_sq"].zero_()

    # --------------------------------------------------------------------------------------------- storage
    def state_for_checkpoint(self) -> dict:
        return {"sh_degree": self.sh_degree, **{name: getattr(self, name).detach().clone()
                                                 for name in _PARAMETER_NAMES}}

    @classmethod
    def from_checkpoint(cls, state: dict, *, device="cpu") -> "GaussianModel":
        count = state["means"].shape[0]
        model = cls(torch.zeros(count, 3), torch.full((count, 3), 0.5), torch.ones(count, 3),
                    sh_degree=state["sh_degree"])
        for name in _PARAMETER_NAMES:
            setattr(model, name, torch.nn.Parameter(state[name].to(device).float().clone()))
        return model
