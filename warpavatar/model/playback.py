"""Playback of an avatar frame after frame: pose + shade + rasterize with no host synchronization, replayed from
a CUDA graph.

A :class:`Player` keeps every input of a frame in tensors of its own (the bone transforms, the camera matrices,
the parts' explicit inputs), which :meth:`Player.render` refills before drawing, and rasterizes with a fixed
intersection capacity (:func:`warpavatar.ops.rasterize_gaussians`), so a frame reads nothing from the device
and, on CUDA, is captured once as a graph (:mod:`warpavatar._src.graphs.capture`) and replayed per frame. The first
frame is drawn with exact buffers to learn how many (Gaussian, tile) pairs the avatar makes, and the capacity
is set to ``capacity_factor`` times that. After every frame the player reads the most pairs a frame needed
so far from a copy that travels to the host behind the frames' work
(:meth:`~warpavatar.model.capacity.IntersectionCapacity.poll`: no wait, unless ``check_every - 1`` frames came
after it) and, when a frame came near the capacity, grows it and captures again; a frame that needed more than the
capacity dropped the pairs of its farthest Gaussians, and the frame being drawn when that is read is drawn
again.

What depends only on the frozen avatar is computed once, before any capture, in buffers a captured frame reads:
the skinning grid, the activated Gaussians and their skinning weights at the stored centres
(:class:`~warpavatar.model.frozen.FrozenCanonical`: exact, the same functions), and what parts cache
(:meth:`~warpavatar.model.parts.AvatarPart.prepare_playback`: the pose correction's encoding of the canonical
centres, its parameter-only pieces and, with ``mlp_dtype="float16"``, its network in float16). Before each frame
the player compares the version counters of the avatar's tensors with those the caches were made from (host
values, no device read): a change (an optimizer step, ``load_state_dict``) refills the caches in place, and a
change of the storage a captured frame reads (the caches', the Gaussians') captures again.
"""

from __future__ import annotations

from typing import Any, Mapping

import torch

from warpavatar._src.graphs.capture import capture_or_fall_back, resolve_cuda_graph
from warpavatar._src.precision import check_matmul_precision, mlp_dtype, mlp_precision
from warpavatar.model.capacity import IntersectionCapacity
from warpavatar.model.frozen import FrozenCanonical, tensor_versions
from warpavatar.model.parts import AvatarPart

__all__ = ["Player"]

_MLP_DTYPES = {"float16": torch.float16, "float32": torch.float32}


class _Camera:
    """The player's camera: its matrices in tensors that keep their storage (a captured graph reads them)."""

    def __init__(self, camera, device):
        self.K = torch.as_tensor(camera.K, dtype=torch.float32, device=device).clone()
        self.world_to_camera = torch.as_tensor(camera.world_to_camera, dtype=torch.float32, device=device).clone()
        self.width, self.height = int(camera.width), int(camera.height)

    def load(self, camera) -> None:
        if (int(camera.width), int(camera.height)) != (self.width, self.height):
            raise ValueError(f"the player draws {self.width}x{self.height} images, the camera is "
                             f"{int(camera.width)}x{int(camera.height)} (make another Player)")
        self.K.copy_(torch.as_tensor(camera.K, dtype=torch.float32))
        self.world_to_camera.copy_(torch.as_tensor(camera.world_to_camera, dtype=torch.float32))


class Player:
    """Draws an avatar in a sequence of poses through one camera size, reusing its buffers from frame to frame.

    Args:
        avatar: the :class:`~warpavatar.model.avatar.Avatar` (its skinning grid is cached, and evaluated again
            when the field's parameters change).
        camera: object with ``K`` [3,3], ``world_to_camera`` [4,4], ``width``, ``height`` [px]; later frames may
            bring other matrices, not another size.
        background: [3] RGB in 0..1 (default black).
        sh_degree: SH degree to render with (default: all the avatar has).
        cuda_graph: ``auto`` (a graph on CUDA), ``on`` (a graph, CUDA required) or ``off`` (eager). Avatars with
            parts that keep state over a sequence (they need the frame's index, a host number) always run eagerly.
        capacity_factor: intersection capacity as a multiple of the largest pair count seen (>= 1). The capacity
            grows once a frame needs over 90 % of it, which the player reads within ``check_every - 1`` frames;
            with the default 1.25, frames drop pairs only when their count grows by over a quarter within those
            frames (a cut to a closer view).
        check_every: a frame's pair count is read, at the latest, once ``check_every - 1`` more frames are drawn
            (its copy to the host is then waited for; otherwise it is read when it arrives, without a wait). 1
            reads it right after its frame, waiting for the device every frame.
        matmul_precision: ``tf32`` (the MLPs' float32 GEMMs on TF32 tensor cores, on CUDA) or ``fp32``
            (:mod:`warpavatar._src.precision`); default: the avatar's (``warpavatar-fit --matmul-precision``,
            kept in the avatar file). No effect on a CPU.
        mlp_dtype: ``float16`` or ``float32``: the dtype of the inputs, weights and activations of the parts'
            per-Gaussian MLPs (the pose correction's), sums kept in float32 (half the bytes their GEMMs and
            activations move; TF32 rounds GEMM inputs to the same 10-bit mantissa). A part keeps float32 where
            its values could leave float16's range (:meth:`AvatarPart.prepare_playback`). Default: ``float16`` on
            CUDA when ``matmul_precision`` is ``tf32``, else ``float32`` (on a CPU float16 is correct but slow).

    Raises:
        ValueError: bad options, or ``cuda_graph="on"`` without CUDA.
    """

    def __init__(self, avatar, camera, *, background: torch.Tensor | None = None, sh_degree: int | None = None,
                 cuda_graph: str = "auto", capacity_factor: float = 1.25, check_every: int = 3,
                 matmul_precision: str | None = None, mlp_dtype: str | None = None):
        if check_every < 1:
            raise ValueError(f"check_every must be >= 1, got {check_every}")
        self.matmul_precision = check_matmul_precision(matmul_precision or avatar.matmul_precision)
        self.avatar = avatar
        self.device = avatar.gaussians.means.device
        if mlp_dtype is None:
            mlp_dtype = "float16" if self.device.type == "cuda" and self.matmul_precision == "tf32" else "float32"
        if mlp_dtype not in _MLP_DTYPES:
            raise ValueError(f"mlp_dtype must be 'float16' or 'float32', got {mlp_dtype!r}")
        #: the dtype the parts' MLPs are asked to run in (``float16`` or ``float32``)
        self.mlp_dtype = mlp_dtype
        self.sh_degree = sh_degree
        self._capacity = IntersectionCapacity(self.device, factor=capacity_factor)
        self.check_every = int(check_every)
        #: whether parts keep state over a sequence (then frames need their index and run eagerly)
        self.stateful = any(type(part).prepare_sequence is not AvatarPart.prepare_sequence
                            for part in avatar.parts.values())
        self.use_graph = resolve_cuda_graph(cuda_graph, self.device) and not self.stateful
        self._cuda_graph_mode = cuda_graph
        self._camera = _Camera(camera, self.device)
        self._background = None if background is None else \
            torch.as_tensor(background, dtype=torch.float32, device=self.device).clone()
        self._bones = torch.zeros(avatar.joint_count, 4, 4, device=self.device)
        self._inputs: dict[str, torch.Tensor] = {}
        self._frame_index: int | None = None
        self._graph = None
        self._graph_outputs = None
        self._grid: torch.Tensor | None = None
        self._field_tensors: list[torch.Tensor] = []  # held: their identities are part of the field's key
        self._field_key: tuple = ()
        self._frozen = FrozenCanonical()  # the activated Gaussians and their weights at the stored centres
        self._cache_key: tuple | None = None  # what the captured graph reads of the caches
        self._refresh()

    @property
    def capacity(self) -> int | None:
        """The rasterizer's intersection capacity (None until the first frame has counted its pairs)."""
        return self._capacity.value

    @capacity.setter
    def capacity(self, value: int | None) -> None:
        self._capacity.value = value
        self._graph = self._graph_outputs = None  # its buffers have the old size

    @torch.no_grad()
    def _refresh(self) -> None:
        """Bring what the player caches of the avatar up to date (host checks only, unless something changed):
        the skinning grid when the field's parameters changed, the parts' playback caches; drop the captured
        graph when the storage it reads changed (the caches', the Gaussians', a replaced field or part), and
        count the pairs again when the number of Gaussians changed. Host work only: about 30 us a frame on a
        slow, shared CPU core."""
        avatar = self.avatar
        field = avatar.field
        tensors = list(field.parameters())
        field_key = (id(field), tensor_versions(tensors))
        if self._grid is None or field_key != self._field_key:
            with mlp_precision(self.matmul_precision):
                grid = field.grid_weights()
            if self._grid is not None and self._grid.shape == grid.shape:
                grid = self._grid.copy_(grid)  # in place: a captured frame reads this storage
            self._grid, self._field_tensors, self._field_key = grid, tensors, field_key
        gaussians = avatar.gaussians
        degree = gaussians.sh_degree if self.sh_degree is None else min(self.sh_degree, gaussians.sh_degree)
        frozen = self._frozen.refresh(gaussians, field, self._grid, sh_degree=degree)
        dtype = _MLP_DTYPES[self.mlp_dtype]
        key = (gaussians.count, self._grid.data_ptr(), tuple(t.data_ptr() for t in gaussians.parameters()), frozen,
               tuple((id(part), part.prepare_playback(gaussians.means, mlp_dtype=dtype))
                     for part in avatar.parts.values()))
        if key != self._cache_key:
            if self._cache_key is not None and key[0] != self._cache_key[0]:
                self._capacity.value = None  # other Gaussians: the next frame counts their pairs
            self._graph = self._graph_outputs = None
            self._cache_key = key

    def _draw(self):
        """One frame from the player's tensors: (image, alpha, depth); its rasterizer status is recorded."""
        with mlp_precision(self.matmul_precision), mlp_dtype(_MLP_DTYPES[self.mlp_dtype]):
            posed = self.avatar.pose(self._bones, sh_degree=self.sh_degree, grid=self._grid, inputs=self._inputs,
                                     frame_index=self._frame_index, frozen=self._frozen)
        image, alpha, depth, info = self.avatar.rasterize(posed, self._camera, background=self._background,
                                                          return_info=True, intersection_capacity=self.capacity)
        self._capacity.record(info["status"])
        return image, alpha, depth

    def _load(self, bone_transforms, inputs: Mapping[str, Any] | None, camera, frame_index) -> None:
        self._bones.copy_(torch.as_tensor(bone_transforms, dtype=torch.float32))
        inputs = dict(inputs or {})
        if self._inputs and set(inputs) != set(self._inputs):
            raise ValueError(f"the player was started with inputs for {sorted(self._inputs)}, got {sorted(inputs)}")
        for name, value in inputs.items():
            value = torch.as_tensor(value, device=self.device)
            if name in self._inputs:
                self._inputs[name].copy_(value)
            else:
                self._inputs[name] = value.clone()
        if camera is not None:
            self._camera.load(camera)
        self._frame_index = frame_index if self.stateful else None

    @torch.no_grad()
    def render(self, bone_transforms, *, camera=None, inputs: Mapping[str, Any] | None = None,
               frame_index: int | None = None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Draw one frame.

        Args:
            bone_transforms: [J,4,4] rest-to-posed transforms (torch or numpy).
            camera: the camera of this frame (same size as the player's), or None to keep the last one.
            inputs: explicit inputs of parts by part name (see :meth:`Avatar.pose`); the same names every frame.
            frame_index: the frame's index in the sequence prepared with :meth:`Avatar.prepare_sequence` (used
                by parts that keep state over time).

        Returns:
            ``(image [H,W,3], alpha [H,W], depth [H,W])``. With a CUDA graph these tensors are the graph's
            outputs, overwritten by the next frame: copy what you keep.
        """
        self._load(bone_transforms, inputs, camera, frame_index)
        self._refresh()
        if self.capacity is None:  # the first frame: exact buffers, to learn the pair count
            image, alpha, depth = self._draw()
            self._capacity.check()
            return image, alpha, depth
        if self.use_graph and self._graph is None:
            captured = capture_or_fall_back(self._draw, mode=self._cuda_graph_mode, what="playback",
                                            device=self.device)
            self.use_graph = captured is not None
            if captured is not None:
                self._graph, self._graph_outputs = captured
        if self.use_graph:
            self._graph.replay()
            image, alpha, depth = self._graph_outputs
        else:
            image, alpha, depth = self._draw()
        before = self.capacity
        overflow = self._capacity.poll(max_lag=self.check_every)  # no wait unless check_every frames went unread
        if self.capacity != before:
            self._graph = self._graph_outputs = None  # its buffers have the old size
        if overflow is not None:  # a frame since the last read dropped pairs: draw this one again
            return self.render(bone_transforms, camera=camera, inputs=inputs, frame_index=frame_index)
        return image, alpha, depth
