"""The avatar model: canonical Gaussians, the voxel skinning field, the avatar that poses and renders them, and
the protocol of its optional parts."""

from warpavatar.model.avatar import AVATAR_FORMAT, Avatar, PosedGaussians
from warpavatar.model.gaussians import GaussianModel
from warpavatar.model.parts import AvatarPart, CanonicalGaussians, PoseFrame, frame_intervals
from warpavatar.model.skinning_field import VoxelSkinningField

__all__ = ["Avatar", "AVATAR_FORMAT", "PosedGaussians", "GaussianModel", "VoxelSkinningField", "AvatarPart",
           "CanonicalGaussians", "PoseFrame", "frame_intervals"]
