"""What posing a frozen avatar computes from its parameters alone, kept once for playback.

Every frame of :meth:`~warpavatar.model.avatar.Avatar.pose` activates the stored Gaussian parameters (the
exponential of the log-scales, the sigmoid of the opacity logits, the normalized quaternions, the SH
coefficients joined into one tensor) and reads the skinning grid at the canonical centres. For a frozen avatar
none of that depends on the frame. :class:`FrozenCanonical` keeps those tensors, computed by the very same
functions (so equal to the per-frame values, bit for bit), refilled in place when the parameters or the grid
change (their version counters, read on the host), so that a captured playback frame reads them from storage
that stays put. Training never uses it: a fit's step needs the gradients of the activations.
"""

from __future__ import annotations

import torch

__all__ = ["FrozenCanonical", "tensor_versions"]

_CACHED = ("quats", "scales", "opacities", "colors", "weights")


def tensor_versions(tensors) -> tuple:
    """What a cache made from ``tensors`` depends on beyond their values: each one's storage, version counter
    (bumped by every in-place change: optimizer steps, ``load_state_dict``) and shape. Host values only; the
    caller holds the tensors themselves where their identity matters (a freed tensor's storage may be reused)."""
    return tuple((t.data_ptr(), t._version, tuple(t.shape)) for t in tensors)


class FrozenCanonical:
    """The activated canonical Gaussians of a frozen avatar and their skinning weights at the stored centres.

    Empty until :meth:`refresh`; then:

    Attributes:
        quats: [N,4] unit orientations (w, x, y, z) (:attr:`GaussianModel.normalized_quats`).
        scales: [N,3] scales [world units].
        opacities: [N] opacities in (0, 1).
        colors: [N,(sh_degree+1)^2,3] SH coefficients up to :attr:`sh_degree`, contiguous.
        weights: [N,J+E] skinning weights at the stored canonical centres, read from the grid given to
            :meth:`refresh` (what :meth:`VoxelSkinningField.weights` gives there).
        sh_degree: SH degree of :attr:`colors` (None until the first refresh).
    """

    def __init__(self):
        self.quats = self.scales = self.opacities = self.colors = self.weights = None
        self.sh_degree: int | None = None
        self._key: tuple | None = None
        self._held: tuple = ()  # the tensors of the key, held so that no other tensor takes their storage

    @torch.no_grad()
    def refresh(self, gaussians, field, grid: torch.Tensor, *, sh_degree: int) -> tuple:
        """Compute the tensors again when what they are made of changed since the last call (a Gaussian
        parameter, the grid, the degree: their storage, shape or version counter; host values only), in place
        while their shapes hold.

        Args:
            gaussians: the avatar's :class:`~warpavatar.model.gaussians.GaussianModel`.
            field: its :class:`~warpavatar.model.skinning_field.VoxelSkinningField`.
            grid: [D,H,W,J+E] the skinning grid posing reads (:meth:`VoxelSkinningField.grid_weights`).
            sh_degree: SH degree to keep the colours up to (at most the Gaussians').

        Returns:
            The storage of the kept tensors (data pointers): a captured frame that reads them must be captured
            again when it changes.
        """
        tensors = (*gaussians.parameters(), grid)
        key = (int(sh_degree), tensor_versions(tensors))
        if key != self._key:
            values = {"quats": gaussians.normalized_quats, "scales": gaussians.scales,
                      "opacities": gaussians.opacities, "colors": gaussians.sh_coefficients(sh_degree).contiguous(),
                      "weights": field.weights(gaussians.means, grid)}
            for name, value in values.items():
                kept = getattr(self, name)
                if kept is not None and kept.shape == value.shape and kept.device == value.device:
                    value = kept.copy_(value)
                setattr(self, name, value)
            self.sh_degree = int(sh_degree)
            self._key, self._held = key, tensors
        return tuple(getattr(self, name).data_ptr() for name in _CACHED)
