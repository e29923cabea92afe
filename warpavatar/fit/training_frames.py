"""The frames a fit trains on: the video folder read at the fit's training resolution, then held on the training
device."""

from __future__ import annotations

import os
from types import SimpleNamespace

import numpy as np
import torch

from warpavatar.data import VideoFolder, load_video_folder
from warpavatar.geometry import camera_centre
from warpavatar.model.parts import frame_intervals

__all__ = ["load_training_video", "evenly_spaced", "TrainingFrames"]


def load_training_video(folder: str | os.PathLike, config) -> VideoFolder:
    """Read the video folder a fit trains on at the fit's training resolution.

    This is the one place a fit's ``image_scale`` is applied: images, masks and intrinsics are resized as the
    frames are read (:func:`~warpavatar.data.load_video_folder` with ``scale=config.image_scale``), so a caller
    hands over the folder and never scales anything itself. Every frame is read; ``max_train_frames`` picks
    among them later (:class:`TrainingFrames`).

    Args:
        folder: the training video folder (``docs/data.md``).
        config: the fit's :class:`~warpavatar.fit.config.FitConfig` (its ``image_scale``, a fraction).

    Returns:
        The folder's contents, ``round(W * image_scale) x round(H * image_scale)`` pixels a frame.

    Raises:
        VideoFolderError: a missing or invalid file (the message names it).
    """
    return load_video_folder(folder, scale=config.image_scale)


def evenly_spaced(total: int, count: int) -> np.ndarray:
    """At most ``count`` distinct indices spread evenly over ``0..total-1`` (first and last included)."""
    return np.unique(np.linspace(0, total - 1, min(count, total)).round().astype(int))


class TrainingFrames:
    """The training frames of a video folder (all, or ``max_train_frames`` evenly spaced), on the device.

    Args:
        video: the training :class:`~warpavatar.data.VideoFolder` at the training resolution
            (:func:`load_training_video`).
        max_frames: use at most this many frames, evenly spaced (0: all).
        target: what a render is compared with (:attr:`warpavatar.fit.config.FitConfig.target`).
        device: the training device.

    Attributes:
        indices: [T] the frames' rows in the video folder; ``frame_ids`` [T] their frame numbers.
        images: [T,H,W,3] uint8; ``masks``: [T,H,W] uint8 or None.
        bone_transforms: [T,J,4,4] float32 rest-to-posed transforms.
        intervals: [T] seconds from each frame to the one before (:func:`~warpavatar.model.parts.frame_intervals`),
            and ``seconds``, the same as host numbers.
        times: [T] the frames' times [s].
        cameras: the frames' cameras, their matrices on the device (``K``, ``world_to_camera``, ``width``,
            ``height``).
        background: [3] the folder's background colour in 0..1.
        composite_target: whether targets are the masked foreground over the background (else the frame).
        skeleton: the folder's :class:`~warpavatar.data.Skeleton`.
    """

    def __init__(self, video, *, max_frames: int = 0, target: str = "auto", device="cpu"):
        device = torch.device(device)
        self.video = video
        self._step_buffers: dict[tuple[int, int], SimpleNamespace] = {}  # see step_buffers
        self.indices = np.arange(video.frame_count)
        if max_frames and max_frames < video.frame_count:
            self.indices = evenly_spaced(video.frame_count, max_frames)
        self.images = torch.as_tensor(video.images[self.indices], device=device)
        self.masks = torch.as_tensor(video.masks[self.indices], device=device) if video.masks is not None else None
        self.bone_transforms = torch.as_tensor(video.bone_transforms[self.indices], dtype=torch.float32,
                                               device=device)
        frame_ids = video.frame_ids[self.indices]
        self.frame_ids = frame_ids
        self.intervals = frame_intervals(frame_ids, video.fps).to(device)
        self.seconds = self.intervals.tolist()  # the same on the host: no device read per step
        self.times = torch.as_tensor(frame_ids, dtype=torch.float32, device=device) / float(video.fps)
        # cameras with their matrices already on the device (no host-to-device copy per step)
        self.cameras = [
            SimpleNamespace(K=torch.as_tensor(c.K, dtype=torch.float32, device=device),
                            world_to_camera=torch.as_tensor(c.world_to_camera, dtype=torch.float32, device=device),
                            width=c.width, height=c.height)
            for c in (video.cameras[i] for i in self.indices)]
        self.background = torch.as_tensor(video.background, dtype=torch.float32, device=device)
        # frames rendered over a declared flat background are their own target (their edge pixels mix the
        # subject with that colour, as a render does); otherwise the mask cuts the foreground out
        self.composite_target = self.masks is not None and (
            target == "masked" or (target == "auto" and not video.declares_background))
        self.skeleton = video.skeleton

    @property
    def count(self) -> int:
        """Number of training frames T."""
        return len(self.indices)

    def frame_id(self, index: int) -> int:
        """The frame number of training frame ``index``."""
        return int(self.video.frame_ids[self.indices[index]])

    def spread(self, count: int) -> np.ndarray:
        """At most ``count`` training-frame indices spread evenly over the sequence."""
        return evenly_spaced(self.count, count)

    def camera_centre(self) -> torch.Tensor:
        """Mean world position [3] of the training cameras' centres."""
        return torch.stack([camera_centre(c.world_to_camera) for c in self.cameras]).mean(0)

    def target(self, index: int) -> tuple[torch.Tensor, torch.Tensor | None]:
        """Ground truth [H,W,3] in 0..1 of training frame ``index`` and its mask [H,W] (None without masks).

        The image is the frame itself, or (``composite_target``) its masked foreground over the background.
        """
        return self.target_of(self.images[index], None if self.masks is None else self.masks[index])

    def target_of(self, image: torch.Tensor, mask: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor | None]:
        """:meth:`target` of a frame's uint8 image [H,W,3] and mask [H,W] (or None), wherever they are held
        (a training step's buffers, refilled every step, as a CUDA graph needs)."""
        image = image.float() / 255.0
        if mask is None:
            return image, None
        mask = mask.float() / 255.0
        if not self.composite_target:
            return image, mask
        return image * mask[..., None] + self.background * (1 - mask[..., None]), mask

    def step_buffers(self, index: int) -> SimpleNamespace:
        """Training frame ``index`` in tensors that keep their storage from call to call (one set per image size),
        refilled by device-to-device copies, so that one captured training step serves every frame of a size:
        ``index`` (the frame's index, int64 0-dim), ``bones`` [J,4,4], ``image`` [H,W,3] uint8, ``mask`` [H,W]
        uint8 or None, ``camera`` (``K``, ``world_to_camera``, ``width``, ``height``)."""
        camera = self.cameras[index]
        size = (camera.width, camera.height)
        buffers = self._step_buffers.get(size)
        if buffers is None:
            buffers = self._step_buffers[size] = SimpleNamespace(
                index=torch.tensor(int(index), dtype=torch.int64, device=self.images.device),
                bones=self.bone_transforms[index].clone(), image=self.images[index].clone(),
                mask=None if self.masks is None else self.masks[index].clone(),
                camera=SimpleNamespace(K=camera.K.clone(), world_to_camera=camera.world_to_camera.clone(),
                                       width=camera.width, height=camera.height))
            return buffers
        buffers.index.fill_(int(index))  # (a fill kernel: no host-to-device copy, no sync)
        buffers.bones.copy_(self.bone_transforms[index])
        buffers.image.copy_(self.images[index])
        if buffers.mask is not None:
            buffers.mask.copy_(self.masks[index])
        buffers.camera.K.copy_(camera.K)
        buffers.camera.world_to_camera.copy_(camera.world_to_camera)
        return buffers
