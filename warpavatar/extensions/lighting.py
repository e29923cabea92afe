"""A global world-frame lighting term: colour = SH colour x irradiance(world normal).

Scenes are lit by lights fixed in the world. A subject that turns in front of a fixed camera shows each part
of its body only while that part faces the camera, so how a surface looks when it faces *away* from the
training camera (what a camera behind the subject sees) is never observed. A per-Gaussian colour cannot
extrapolate that; a low-order irradiance shared by all Gaussians can: ``E(n) = max(0, a + B n)`` per RGB
channel (first-order spherical harmonics of the irradiance, 12 numbers), with ``n`` each Gaussian's world
normal.

A Gaussian's normal is the axis of its smallest scale (splats on a surface flatten along it), signed to
point away from the nearest bone (outwards from the body) in the canonical pose, then carried by the
Gaussian's posed rotation.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from warpavatar.extensions.base import Extension, option
from warpavatar.geometry import quat_rotate
from warpavatar.model.parts import AvatarPart
from warpavatar.model.skinning_field import closest_on_segments
from warpavatar.optim import Adam, Optimizer

__all__ = ["WorldLighting", "outward_normals", "LightingOptions", "LightingExtension"]


def _closest_on_bones(points: torch.Tensor, heads: torch.Tensor, tails: torch.Tensor) -> torch.Tensor:
    """Closest point [N,3] on the nearest bone segment to each point [N,3] (in chunks: [n,J,3] at a time)."""
    closest = []
    for chunk in torch.split(points, 32768):
        candidates = closest_on_segments(chunk, heads, tails)  # [n,J,3]
        nearest = (chunk[:, None, :] - candidates).square().sum(-1).argmin(dim=1)
        closest.append(candidates[torch.arange(chunk.shape[0], device=points.device), nearest])
    return torch.cat(closest)


def outward_normals(canonical_means: torch.Tensor, canonical_quats: torch.Tensor, posed_quats: torch.Tensor,
                    scales: torch.Tensor, heads: torch.Tensor, tails: torch.Tensor) -> torch.Tensor:
    """World normals [N,3] of posed Gaussians: smallest-scale axis, signed away from the nearest bone.

    Args:
        canonical_means: [N,3] rest-pose centres; canonical_quats: [N,4] rest-pose orientations (w,x,y,z).
        posed_quats: [N,4] posed orientations; scales: [N,3] linear scales.
        heads, tails: [J,3] rest-pose bone segments.
    """
    axis_index = scales.detach().argmin(dim=1)
    local = torch.nn.functional.one_hot(axis_index, 3).to(canonical_means.dtype)
    with torch.no_grad():
        canonical_normal = quat_rotate(canonical_quats.detach(), local)
        outward = canonical_means.detach() - _closest_on_bones(canonical_means.detach(), heads, tails)
        sign = torch.where((canonical_normal * outward).sum(-1, keepdim=True) < 0, -1.0, 1.0)
    return quat_rotate(posed_quats, local) * sign


class WorldLighting(AvatarPart):
    """``E(n) = max(0, ambient + directional @ n)`` per RGB channel; starts as the identity (E = 1).

    Args:
        heads: [J,3] rest-pose bone heads; tails: [J,3] bone tails (to orient normals outwards).
    """

    name = "lighting"

    def __init__(self, heads: torch.Tensor, tails: torch.Tensor):
        super().__init__()
        self.register_buffer("heads", torch.as_tensor(heads, dtype=torch.float32).clone())
        self.register_buffer("tails", torch.as_tensor(tails, dtype=torch.float32).clone())
        self.ambient = torch.nn.Parameter(torch.ones(3))
        self.directional = torch.nn.Parameter(torch.zeros(3, 3))  # [rgb, xyz]

    def shade(self, colors: torch.Tensor, posed, frame=None) -> torch.Tensor:
        """Lit colours [N,3] from SH colours [N,3] and the posed Gaussians (``canonical_means``, ``quats``,
        ``canonical_quats``, ``scales``)."""
        normals = outward_normals(posed["canonical_means"], posed["canonical_quats"], posed["quats"],
                                  posed["scales"], self.heads, self.tails)
        irradiance = (self.ambient + normals @ self.directional.T).clamp_min(0.0)
        return colors * irradiance

    @classmethod
    def from_file_state(cls, state: dict, *, device="cpu") -> "WorldLighting":
        weights = state["state_dict"]
        part = cls(weights["heads"], weights["tails"])
        part.load_state_dict(weights)
        return part.to(device)


@dataclass
class LightingOptions:
    lr_lighting: float = option(1e-3, "Adam learning rate of the global lighting's 12 numbers")


class LightingExtension(Extension):
    """Fits :class:`WorldLighting`'s 12 numbers with the Gaussians, from the first step."""

    name = "lighting"
    title = "world lighting (--lighting)"
    summary = ("multiply colours by a global first-order irradiance of each Gaussian's world normal (lights fixed "
               "in the world; extrapolates to sides never facing the camera)")
    options_type = LightingOptions

    def attach(self) -> None:
        skeleton = self.fit.frames.skeleton
        self.part = self.fit.avatar.add_part(WorldLighting(torch.as_tensor(skeleton.heads),
                                                           torch.as_tensor(skeleton.tails)).to(self.fit.device))
        self.optimizer = Adam(self.part.parameters(), lr=self.options.lr_lighting)

    def optimizers(self, step) -> list[Optimizer | torch.optim.Optimizer]:
        return [self.optimizer]

    def state_dict(self) -> dict:
        return {"part": self.part.state_dict(), "optimizer": self.optimizer.state_dict()}

    def load_state_dict(self, state: dict) -> None:
        self.part.load_state_dict(state["part"])
        self.optimizer.load_state_dict(state["optimizer"])
