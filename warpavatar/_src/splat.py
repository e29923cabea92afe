"""Differentiable Gaussian-splatting rasterizer: torch autograd bridge to the Warp kernels of ``kernels/splat.py``.

One forward pass makes four Warp kernel launches (projection, key emission, tile ranges, compositing) plus three
calls of Warp's native sort and scan (the depth sort of the Gaussians, the prefix sum of their tile counts in depth
order, the sort of the (Gaussian, tile) pairs by tile: two radix sorts over 4-byte keys that give the order of one
over 8-byte (tile, depth) keys, see ``kernels/splat.py``), one small torch fill (the prefix sum's buffer with the
pair count and the flags; the key emission clears the tile ranges), a copy of the sorted ids when a backward may
follow (it keeps 4 bytes a pair, not the sort's double buffer; a pass whose inputs need no gradient skips it), and
one host wait for the pair count (in the speculative mode a copy into pinned host memory after the prefix sum,
which the host polls while the compositing runs); in the speculative mode a call whose buffers' addresses repeat
replays all of that but the ids' copy from one CUDA graph. One backward pass makes two Warp launches (compositing
backward, projection adjoint), one torch fill and no synchronization.

The sort buffers must hold every (Gaussian, tile) pair, a number known only on the device once the projection
has run (an upper bound would cost far more memory, as any Gaussian may cover the whole image). Four modes:

* **Speculative** (CUDA, the default once a call of the same image size and Gaussian count has been seen): the
  buffers get a capacity of :data:`SPECULATIVE_HEADROOM` times the most pairs of the last
  :data:`SPECULATIVE_HISTORY` such calls (more where their counts rise), every buffer is allocated first, and
  the whole pass is queued without waiting; the pair count and the non-finite-input flag are copied into pinned
  host memory as soon as the prefix sum has them and read there once the whole pass is queued
  (:mod:`warpavatar._src.graphs.status_mailbox`: the host waits for the front half of the pass, not for the
  compositing), and only then are the pairs' ids copied out of the sort's double buffer (queued behind the
  compositing). When the pairs did not fit, the tile binning and compositing run again with exact buffers, so
  the result is always exact. The host thus queues every kernel while the GPU works, instead of waiting for the
  projection half-way, and does its work after the read (the ids' copy, autograd's) while the GPU composites.
  Where a call's buffers come back at the addresses of a recent call's (torch's caching allocator hands out the
  same blocks to the same sequence of allocations: a render loop, a training step), its launches are replayed
  from a CUDA graph keyed by those addresses (:mod:`warpavatar._src.graphs.address_graphs`): one graph launch instead
  of some twenty launches from Python, and no memory held between calls.
* **Exact** (CPU, and the first call of a size on CUDA): the pair count is read after the depth sort and its
  prefix sum, and the buffers get exactly that size.
* **Fixed** (``intersection_capacity``): the buffers have that size, the key kernel gives unused slots a padding
  key that sorts last and drops pairs past the capacity, and nothing is read from the device, so the pass can be
  captured in a CUDA graph; the pair count and the input flags stay on the device (``info["status"]``) for
  the caller to check when it reads other values anyway (:func:`rasterizer_status`).

* **Replayed with its own buffers** (CUDA, opt-in: :func:`rasterizer_replays`,
  :mod:`warpavatar._src.graphs.splat_replay`): once a few consecutive speculative calls of one shape (image size,
  Gaussian count, SH layout) have fitted their guess, that shape's fixed-capacity pass is captured into a CUDA graph
  with its own inputs, outputs and sort buffers, and later calls replay it: their inputs copied in by one concatenation,
  the graph replayed, its outputs copied out (three copies) and the status read. It serves a call wherever its tensors
  are, but the graph holds about as much memory again as the pass between calls. A pass that outgrew the graph is passed
  again with exact buffers.

In every mode non-finite inputs raise a ``ValueError`` (fixed mode: when the caller checks the status).

Host work per call is kept small: kernel arguments are Warp launch descriptors
(:func:`~warpavatar._src.warp_utils.warp_descriptor`), not ``wp.array`` objects, the launches reuse recorded
commands (:mod:`warpavatar.kernels.launch`), and the sort and scan get the tensors' pointers
(``warp_utils.radix_sort_pairs`` and ``inclusive_scan``). Before a replayed pass's graph launch (the host's work
the GPU waits for) a call only checks its inputs, skips conversions they do not need, allocates ten buffers
(the per-Gaussian records in one) and builds the graph's key; the views the launches would need are made only
where launches are queued. Autograd gets three outputs (the info tensors travel beside them) and packs only the
inputs; the pass's own intermediates are kept on its context (:class:`SavedPass`). Memory a pass holds, per
Gaussian / pair / pixel, is listed in ``docs/rasterizer_memory.md``.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Mapping
from typing import NamedTuple

import torch
import warp as wp

from warpavatar._src.graphs import address_graphs, splat_replay
from warpavatar._src.graphs.address_graphs import AddressKeyedGraphs
from warpavatar._src.graphs.splat_replay import ReplayCache
from warpavatar._src.graphs.status_mailbox import status_mailbox
from warpavatar._src.warp_utils import (check_tensor, inclusive_scan, radix_sort_pairs, torch_stream_scope,
                                        warp_descriptor, write_only_descriptor)
from warpavatar.kernels import splat as splat_kernels

__all__ = ["rasterize_gaussians", "RasterInfo", "rasterizer_replays", "rasterizer_status", "run_pass",
           "allocate_pass_buffers", "PassBuffers", "SavedPass", "SPECULATIVE_HEADROOM", "SPECULATIVE_HISTORY"]

SPECULATIVE_HEADROOM = 1.03
"""Speculative capacity as a multiple of the most pairs of recent calls of the same size, or of the last call's
pairs plus the largest rise between consecutive recent calls where that is more (:func:`_speculative_capacity`)."""

SPECULATIVE_HISTORY = 8
"""How many recent calls of one (device, image size, Gaussian count) the speculative capacity looks back on."""

_SPECULATIVE_MINIMUM = 1024  # slots; the capacity never goes below it
_SPECULATE_ON_CPU = False  # CPU kernels run synchronously: the exact mode costs no wait there (tests set this)

# Pair counts of recent calls, per (device, width, height, Gaussian count).
_RECENT_PAIRS: dict[tuple, _PairHistory] = {}
_RECENT_PAIRS_KEPT = 256  # distinct keys kept before the table starts over

_BAD_INPUT_NAMES = (
    (splat_kernels.BAD_MEANS, "means"),
    (splat_kernels.BAD_QUATS, "quats"),
    (splat_kernels.BAD_SCALES, "scales"),
    (splat_kernels.BAD_OPACITIES, "opacities"),
    (splat_kernels.BAD_COLORS, "colors"),
    (splat_kernels.BAD_CAMERA, "K / world_to_camera"),
)


_BLACK_BACKGROUNDS: dict[torch.device, torch.Tensor] = {}


def _black_background(device: torch.device) -> torch.Tensor:
    """A black background [3] on ``device``, made once per device (no allocation and fill a call): the kernels
    only read it and it needs no gradient. Inside a CUDA graph capture a fresh one, captured with its fill (a
    tensor made during a capture holds its zeros only once the graph replays)."""
    if device.type == "cuda" and torch.cuda.is_current_stream_capturing():
        return torch.zeros(3, device=device, dtype=torch.float32)
    background = _BLACK_BACKGROUNDS.get(device)
    if background is None:
        background = _BLACK_BACKGROUNDS[device] = torch.zeros(3, device=device, dtype=torch.float32)
    return background


def _tile_grid(width: int, height: int) -> tuple[int, int]:
    tile = int(splat_kernels.TILE_SIZE)
    return (width + tile - 1) // tile, (height + tile - 1) // tile


def _raise_on_bad_inputs(flags: int) -> None:
    if flags:
        bad = [name for bit, name in _BAD_INPUT_NAMES if flags & bit]
        raise ValueError(f"rasterize_gaussians: non-finite values in {', '.join(bad)}")


class _PairHistory(deque):
    """The pair counts of recent calls of one key, and the capacity they give the next call (computed when a count
    is added, which happens after a pass has been queued: off the next call's path to its launches)."""

    def __init__(self):
        super().__init__(maxlen=SPECULATIVE_HISTORY)
        self.capacity = None

    def add(self, count: int) -> None:
        self.append(count)
        # Calls that repeat one count (a scene rendered again, a training step's small moves) get a few per cent
        # above the most; calls whose counts grow get the largest recent rise on top of the last. Rounded up to
        # 1/64 of the capacity's power of two, so that slightly different histories give the same capacity (and
        # the same buffers: address_graphs).
        counts = list(self)
        rise = max((later - earlier for earlier, later in zip(counts, counts[1:])), default=0)
        guess = max(max(counts), counts[-1] + rise)
        capacity = max(_SPECULATIVE_MINIMUM, math.ceil(SPECULATIVE_HEADROOM * guess))
        step = 1 << max(capacity.bit_length() - 7, 0)
        self.capacity = -(-capacity // step) * step


def _speculative_capacity(key: tuple) -> int | None:
    """The speculative capacity for a call of ``key`` (see the module doc), or None: no call of it seen yet, or
    speculation is off on this device."""
    device = key[0]
    if device.type == "cuda":
        if torch.cuda.is_current_stream_capturing():
            return None  # a capture cannot read the device; callers give a fixed capacity there
    elif not _SPECULATE_ON_CPU:
        return None
    recent = _RECENT_PAIRS.get(key)
    return None if recent is None else recent.capacity


def _remember_pairs(key: tuple, count: int) -> None:
    recent = _RECENT_PAIRS.get(key)
    if recent is None:
        if len(_RECENT_PAIRS) >= _RECENT_PAIRS_KEPT:
            _RECENT_PAIRS.clear()
        recent = _RECENT_PAIRS[key] = _PairHistory()
    recent.add(int(count))


def _front_buffers(gaussian_count: int, device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
    """The front half's buffers, as :func:`_front_views` reads them: the depth sort's double buffers in one
    allocation (24 bytes a Gaussian, released with the pass) and, in another (as ``info["status"]``, a view of it,
    may outlive the pass), int32 [N + 2] for a zero, the inclusive prefix sum of the tile counts in depth order and
    the non-finite-input flag, zeroed by the pass.

    Returns:
        ``(depth_sort_buffers, tile_ends_and_flag)``.
    """
    return (torch.empty(6 * gaussian_count, device=device, dtype=torch.int32),
            torch.empty(gaussian_count + 2, device=device, dtype=torch.int32))


def _front_views(front: tuple[torch.Tensor, torch.Tensor]) -> tuple[tuple, torch.Tensor]:
    """Views of :func:`_front_buffers`: the depth sort's buffers ((Gaussian, tile count) records as int32
    [2 N, 2], first, 8-byte aligned; float32 keys [2 N]) and the prefix sum ``tile_ends`` [N]. The projection fills
    the sort's first halves. Made only where launches are queued (a replayed pass needs none of them).

    Returns:
        ``((depth_keys, depth_order), tile_ends)``.
    """
    depth_buffers, tile_ends_and_flag = front
    n = tile_ends_and_flag.shape[0] - 2
    return ((depth_buffers[4 * n:].view(torch.float32), depth_buffers[: 4 * n].view(-1, 2)),
            tile_ends_and_flag[1: n + 1])


def _sort_by_depth(depth_sort, tile_ends) -> None:
    """Sort the Gaussians by depth and write ``tile_ends`` [N], the inclusive prefix sum of their tile counts in
    that order. ``depth_sort`` holds :func:`_front_views`' sort buffers as the projection filled them."""
    gaussian_count = tile_ends.shape[0]
    if not gaussian_count:
        return
    depth_keys, depth_order = depth_sort
    # Stable: equal depths keep the index order. The scan reads the counts in place, from the sorted records.
    radix_sort_pairs(depth_keys, depth_order, gaussian_count, begin_bit=0, end_bit=splat_kernels.DEPTH_SORT_BITS)
    inclusive_scan(depth_order[:, 1], tile_ends, stride=2)


def _tile_sort_buffers(slots: int, device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
    """The tile sort's double buffers for ``slots`` pairs: int32 keys [2 slots] and Gaussian ids [2 slots]."""
    return (torch.empty(2 * slots, device=device, dtype=torch.int32),
            torch.empty(2 * slots, device=device, dtype=torch.int32))


def _queue_binning(slots, sort_keys, sorted_ids, buffers, depth_sort, tile_ends, *, width, height,
                   padded: bool) -> None:
    """Queue the binning of the (Gaussian, tile) pairs into ``slots`` slots of :func:`_tile_sort_buffers`: the
    key emission (which clears ``buffers.tile_ranges``), the tile sort and the tile ranges. ``depth_sort`` and
    ``tile_ends`` [N] are as :func:`_sort_by_depth` left them. ``padded``: the slots are a capacity, whose unused
    slots hold a padding key that sorts last and belongs to no tile, and pairs past it are dropped; else
    ``slots`` is the exact pair count. Reads nothing from the device."""
    tiles_x, tiles_y = _tile_grid(width, height)
    gaussian_count = tile_ends.shape[0]
    tile_ranges = buffers.tile_ranges
    if not (slots and gaussian_count):
        tile_ranges.zero_()  # no pair: every tile's range is empty (the emission clears them otherwise)
        return
    splat_kernels.launch_emit_tile_keys(
        warp_descriptor(buffers.xy_opacity, wp.vec3), warp_descriptor(buffers.conics, wp.vec3),
        warp_descriptor(buffers.radii, wp.vec2i), warp_descriptor(depth_sort[1][:gaussian_count], wp.vec2i),
        warp_descriptor(tile_ends), width=width, height=height, keys=warp_descriptor(sort_keys[:slots]),
        gaussian_ids=warp_descriptor(sorted_ids[:slots]), tile_ranges=warp_descriptor(tile_ranges))
    radix_sort_pairs(sort_keys, sorted_ids, slots, begin_bit=0,
                     end_bit=splat_kernels.tile_key_bits(tiles_x * tiles_y))
    if padded:
        splat_kernels.launch_tile_ranges_padded(warp_descriptor(sort_keys), slots, warp_descriptor(tile_ranges))
    else:
        splat_kernels.launch_tile_ranges(warp_descriptor(sort_keys), slots, warp_descriptor(tile_ranges))


def _kept_ids(sorted_ids, count: int, *, ids_out=None, compact=True):
    """The first ``count`` sorted ids as the backward keeps them. The sort's second halves were its scratch: the
    backward keeps only the ids (4 bytes a pair, not the 8 of the double buffer), copied once the caller has
    released the keys' 8 bytes a pair. ``ids_out``: a buffer that receives them, returned instead of a fresh copy
    (a fixed capacity's pass). ``compact=False`` (nothing reads the ids after the pass: no backward) returns them
    in place, a view of the sort's double buffer, without the copy. Without Gaussians no tile has a range, and
    the ids are never read."""
    if ids_out is not None:
        ids_out.copy_(sorted_ids[:count])
        return ids_out
    return sorted_ids[:count].clone() if compact else sorted_ids[:count]


class PassBuffers(NamedTuple):
    """What one forward pass writes that outlives it (the outputs, and what the backward reads).

    Shapes (N Gaussians, H x W pixels, T tiles): ``image`` [H, W, 3], ``alpha`` and ``depth`` [H, W] float32;
    ``radii`` [N, 2] int32; ``xy_opacity`` and ``conics`` [N, 3], ``color_depth`` [N, 4] float32;
    ``tile_ranges`` [T, 2] int32; ``final_transmittance`` [H, W] float32 and ``last_index`` [H, W] int32;
    ``sorted_ids`` [slots] int32 (one per pair, or per slot of a capacity; None until binned when the exact
    count sizes it); ``status`` [2] int32, the pair count and the non-finite-input flags.
    """

    image: torch.Tensor
    alpha: torch.Tensor
    depth: torch.Tensor
    radii: torch.Tensor
    xy_opacity: torch.Tensor
    color_depth: torch.Tensor
    status: torch.Tensor | None
    conics: torch.Tensor
    tile_ranges: torch.Tensor
    final_transmittance: torch.Tensor
    last_index: torch.Tensor
    sorted_ids: torch.Tensor | None


def allocate_pass_buffers(gaussian_count: int, width: int, height: int, device: torch.device) -> PassBuffers:
    """The buffers of one eager pass (no ``status`` or ``sorted_ids`` yet: the pass makes them), in six
    allocations: the image, alpha and depth each their own (the caller may keep one alone); the per-Gaussian
    records (radii, projected means and opacities, conics, colours and depths: 48 bytes a Gaussian, laid end to
    end) in one, as the backward keeps them all; what the backward reads per pixel (the final transmittance and
    the last index) in one; the tile ranges."""
    tiles_x, tiles_y = _tile_grid(width, height)
    n = gaussian_count
    records = torch.empty(12 * n, device=device, dtype=torch.int32)
    floats = records.view(torch.float32)
    pixel_state = torch.empty(2, height, width, device=device, dtype=torch.int32)
    return PassBuffers(
        image=torch.empty(height, width, 3, device=device, dtype=torch.float32),
        alpha=torch.empty(height, width, device=device, dtype=torch.float32),
        depth=torch.empty(height, width, device=device, dtype=torch.float32),
        radii=records.as_strided((n, 2), (2, 1), 0), xy_opacity=floats.as_strided((n, 3), (3, 1), 2 * n),
        conics=floats.as_strided((n, 3), (3, 1), 5 * n), color_depth=floats.as_strided((n, 4), (4, 1), 8 * n),
        status=None, tile_ranges=torch.empty(tiles_x * tiles_y, 2, device=device, dtype=torch.int32),
        final_transmittance=pixel_state[0].view(torch.float32), last_index=pixel_state[1], sorted_ids=None)


def run_pass(means, quats, scales, opacities, coefficients, background, K, world_to_camera, *, width: int,
             height: int, sh_degree: int, capacity: int | None, speculative: bool,
             buffers: PassBuffers, compact_ids: bool = True, pixel_state: bool = True,
             graphs: AddressKeyedGraphs | None = None) -> tuple[PassBuffers, int | None]:
    """Queue one forward pass into ``buffers`` (see the module doc for the three modes).

    Args:
        capacity: None for the exact mode; else the sort buffers' size, a guess when ``speculative``.
        speculative: read the pair count as soon as the device has it (a status mailbox, while the compositing
            runs on) and bin and composite again with exact buffers when the guess was short (raising on
            non-finite inputs); False with a ``capacity``: nothing is read.
        buffers: from :func:`allocate_pass_buffers`; a fixed capacity's pass may bring ``status`` [2] and
            ``sorted_ids`` [capacity] to be filled in place (a captured pass keeps them).
        compact_ids: False when no backward will read the pass (no gradient asked for): the sorted ids then
            stay in the sort's buffer (8 bytes a pair, released with the pass) instead of a 4-byte copy.
        pixel_state: False when no backward will run: ``final_transmittance`` and ``last_index`` are then not
            written (their buffers hold garbage).
        graphs: in the speculative mode, where the pass's launches are replayed from when its buffers' addresses
            repeat (:mod:`warpavatar._src.graphs.address_graphs`); None: launched one by one.

    Returns:
        ``(buffers, pair_count)``: the buffers with ``status`` and ``sorted_ids`` set, and the pair count where
        it was read (exact and speculative modes), else None.
    """
    device = means.device
    gaussian_count = means.shape[0]
    used_coefficients = 1 if sh_degree < 0 else (sh_degree + 1) ** 2
    # The depth sort's buffers and the prefix sum of the tile counts, whose last two values are the pair count and
    # the flag (one read fetches both; 0 pairs without Gaussians).
    front = _front_buffers(gaussian_count, device)
    tile_ends_and_flag = front[1]
    status = tile_ends_and_flag[gaussian_count:]
    out = buffers

    def queue_front(mailbox=None):
        """Clear the prefix sum's buffer, project, sort by depth and sum the tile counts (then post the pair
        count and the flag to ``mailbox``)."""
        depth_sort, tile_ends = _front_views(front)
        tile_ends_and_flag.zero_()
        splat_kernels.launch_project(
            warp_descriptor(means, wp.vec3), warp_descriptor(quats, wp.vec4), warp_descriptor(scales, wp.vec3),
            warp_descriptor(opacities), warp_descriptor(coefficients, wp.vec3),
            warp_descriptor(K.view(1, 3, 3), wp.mat33), warp_descriptor(world_to_camera.view(1, 4, 4), wp.mat44),
            width=width, height=height, sh_degree=sh_degree, used_coefficients=used_coefficients,
            xy_opacity=warp_descriptor(out.xy_opacity, wp.vec3), conics=warp_descriptor(out.conics, wp.vec3),
            color_depth=warp_descriptor(out.color_depth, wp.vec4), radii=warp_descriptor(out.radii, wp.vec2i),
            depth_keys=warp_descriptor(depth_sort[0][:gaussian_count]),
            depth_order=warp_descriptor(depth_sort[1][:gaussian_count], wp.vec2i),
            bad_input_flags=warp_descriptor(tile_ends_and_flag[gaussian_count + 1:]),
        )
        _sort_by_depth(depth_sort, tile_ends)
        if mailbox is not None:
            mailbox.post(status)

    def queue_composite(sorted_ids):
        splat_kernels.launch_composite_forward(
            warp_descriptor(out.tile_ranges), warp_descriptor(sorted_ids), warp_descriptor(out.xy_opacity, wp.vec3),
            warp_descriptor(out.conics, wp.vec3), warp_descriptor(out.color_depth, wp.vec4),
            warp_descriptor(background.view(1, 3), wp.vec3), width=width, height=height, pixel_state=pixel_state,
            image=warp_descriptor(out.image.view(-1, 3), wp.vec3), alpha=warp_descriptor(out.alpha.view(-1)),
            depth=warp_descriptor(out.depth.view(-1)),
            final_transmittance=warp_descriptor(out.final_transmittance.reshape(-1)),
            last_index=warp_descriptor(out.last_index.reshape(-1)))

    def queue_binned_composite(slots, sort_keys, slot_ids, *, padded):
        depth_sort, tile_ends = _front_views(front)
        _queue_binning(slots, sort_keys, slot_ids, out, depth_sort, tile_ends, width=width, height=height,
                       padded=padded)
        queue_composite(slot_ids[:slots])

    def bin_and_composite(slots, *, padded, ids_out=None):
        """Bin into fresh buffers of ``slots`` slots and composite; returns the kept ids (keys released first)."""
        sort_keys, slot_ids = _tile_sort_buffers(slots, device)
        with torch_stream_scope(device):
            queue_binned_composite(slots, sort_keys, slot_ids, padded=padded)
        del sort_keys
        return _kept_ids(slot_ids, slots, ids_out=ids_out, compact=compact_ids)

    if capacity is None:  # exact: the pair count read half-way (the one host sync)
        with torch_stream_scope(device):
            queue_front()
        count, flags = status.tolist()
        _raise_on_bad_inputs(flags)
        sorted_ids = bin_and_composite(count, padded=False)
    elif not speculative:  # fixed: nothing read
        with torch_stream_scope(device):
            queue_front()
        count = None
        sorted_ids = bin_and_composite(capacity, padded=True, ids_out=out.sorted_ids)
        if out.status is not None:
            out.status.copy_(status)
            status = out.status
    else:  # speculative: every buffer allocated first, the whole pass queued (or replayed), the status read early
        sort_keys, slot_ids = _tile_sort_buffers(capacity, device)
        mailbox = status_mailbox(device)

        def queue_pass():
            with torch_stream_scope(device):
                queue_front(mailbox)
                queue_binned_composite(capacity, sort_keys, slot_ids, padded=True)

        mailbox.arm()
        if graphs is None:
            queue_pass()
        else:
            # Everything the launches take: the addresses, and the sizes and scalars that fix the rest.
            key = (device, width, height, sh_degree, capacity, pixel_state, coefficients.shape[1], gaussian_count,
                   mailbox.address, means.data_ptr(), quats.data_ptr(), scales.data_ptr(), opacities.data_ptr(),
                   coefficients.data_ptr(), background.data_ptr(), K.data_ptr(), world_to_camera.data_ptr(),
                   front[0].data_ptr(), tile_ends_and_flag.data_ptr(), sort_keys.data_ptr(), slot_ids.data_ptr(),
                   out.radii.data_ptr(), out.tile_ranges.data_ptr(), out.image.data_ptr(), out.alpha.data_ptr(),
                   out.depth.data_ptr(), out.last_index.data_ptr())
            graphs.run(key, queue_pass, device=device)
        # The one host wait: until the front half has posted the count (the binning and compositing go on).
        count, flags = mailbox.read()
        _raise_on_bad_inputs(flags)
        del sort_keys
        if count > capacity:  # the guess was short: again with exact buffers (the emission clears ranges)
            del slot_ids
            sorted_ids = bin_and_composite(count, padded=True)
        else:  # only the pairs' ids are kept (the padding slots sort last and belong to no tile)
            sorted_ids = _kept_ids(slot_ids, count, compact=compact_ids)
    return out._replace(status=status, sorted_ids=sorted_ids), count


_REPLAYS = ReplayCache(run_pass=run_pass, buffer_type=PassBuffers, tile_grid=_tile_grid,
                       raise_on_bad_inputs=_raise_on_bad_inputs)
"""The graphs of recently repeated call shapes (:mod:`warpavatar._src.graphs.splat_replay`)."""

_PASS_GRAPHS = AddressKeyedGraphs()
"""The speculative passes' launches, replayed where their buffers' addresses repeat
(:mod:`warpavatar._src.graphs.address_graphs`)."""


class SavedPass(NamedTuple):
    """What a forward pass keeps for its backward besides its inputs (``grad_fn.saved_pass`` of its image):
    the per-Gaussian records, the tile ranges, the sorted ids and the per-pixel state (see :class:`PassBuffers`).
    Kept as an attribute of the autograd context rather than with ``save_for_backward``: these are the pass's
    own intermediates (never outputs, never changed in place), which spares autograd packing eight tensors a
    call."""

    xy_opacity: torch.Tensor
    conics: torch.Tensor
    color_depth: torch.Tensor
    radii: torch.Tensor
    tile_ranges: torch.Tensor
    sorted_ids: torch.Tensor
    final_transmittance: torch.Tensor
    last_index: torch.Tensor


class _RasterizeGaussians(torch.autograd.Function):
    """Autograd wrapper; inputs are already validated, float32 and contiguous (see :func:`rasterize_gaussians`).
    Its outputs are the image, alpha and depth; the info tensors (radii, the per-Gaussian records, the status),
    which carry no gradient, are appended to the ``info_out`` list instead of being outputs (less of autograd's
    work a call)."""

    @staticmethod
    def forward(ctx, means, quats, scales, opacities, coefficients, background, K, world_to_camera, width, height,
                sh_degree, densify_grad_out, intersection_capacity, info_out):
        device = means.device
        gaussian_count = means.shape[0]
        inputs = (means, quats, scales, opacities, coefficients, background, K, world_to_camera)
        sizes = dict(width=width, height=height, sh_degree=sh_degree)
        passed = count = None
        capacity, speculative = intersection_capacity, False
        if intersection_capacity is None:
            speculation_key = (device, width, height, gaussian_count)
            capacity = _speculative_capacity(speculation_key)
            speculative = capacity is not None
            if speculative:
                # A pass replayed from a CUDA graph once calls of this shape repeat (splat_replay), else queued.
                passed, count = _REPLAYS.run(inputs, capacity=capacity, **sizes)
                if passed is None and count is not None:
                    capacity = count  # the replay's graph was outgrown: this many slots fit, nothing is binned twice
        if passed is None:
            needs = ctx.needs_input_grad
            passed, count = run_pass(*inputs, **sizes, capacity=capacity, speculative=speculative,
                                     buffers=allocate_pass_buffers(gaussian_count, width, height, device),
                                     compact_ids=any(needs[:5]), pixel_state=any(needs[:6]),
                                     graphs=_PASS_GRAPHS if speculative else None)
        if intersection_capacity is None:
            _remember_pairs(speculation_key, count)
            if speculative and count <= capacity:
                _REPLAYS.note_fitting_call(inputs, capacity=capacity, **sizes)

        ctx.save_for_backward(means, quats, scales, coefficients, background, K, world_to_camera)
        ctx.saved_pass = SavedPass(passed.xy_opacity, passed.conics, passed.color_depth, passed.radii,
                                   passed.tile_ranges, passed.sorted_ids, passed.final_transmittance,
                                   passed.last_index)
        ctx.width, ctx.height, ctx.sh_degree = width, height, sh_degree
        ctx.densify_grad_out = densify_grad_out
        # The per-Gaussian buffers as-is for the info dict (built only when asked for), with the [pair count,
        # bad-input flags] on the device, for a caller that checks them off the hot path.
        info_out.extend((passed.radii, passed.xy_opacity, passed.color_depth, passed.status))
        return passed.image, passed.alpha, passed.depth

    @staticmethod
    def backward(ctx, grad_image, grad_alpha, grad_depth):
        means, quats, scales, coefficients, background, K, world_to_camera = ctx.saved_tensors
        (xy_opacity, conics, color_depth, radii, tile_ranges, sorted_ids, final_transmittance,
         last_index) = ctx.saved_pass
        device = means.device
        gaussian_count = means.shape[0]
        width, height, sh_degree = ctx.width, ctx.height, ctx.sh_degree
        densify_grad_out = ctx.densify_grad_out

        def as_grad(grad, shape):
            if grad is None:
                return torch.zeros(shape, device=device, dtype=torch.float32)
            return _float32(grad)

        grad_image = as_grad(grad_image, (height, width, 3))
        grad_alpha = as_grad(grad_alpha, (height, width))
        grad_depth = as_grad(grad_depth, (height, width))

        n = gaussian_count
        # One zeroed allocation (one fill) for the screen-space gradients (the |d mean2d| sums only when asked
        # for) and the parameters' gradients, which the kernels add into.
        screen_floats = splat_kernels.screen_grad_floats(densify_grad_out is not None)
        coefficient_count = coefficients.shape[1]
        gradients = torch.zeros((screen_floats + 10 + 3 * coefficient_count) * n, device=device, dtype=torch.float32)
        screen_grads = gradients[: screen_floats * n]
        param_grads = gradients[screen_floats * n:]
        grad_means = param_grads[: 3 * n].view(n, 3)
        grad_quats = param_grads[3 * n: 7 * n].view(n, 4)
        grad_scales = param_grads[7 * n: 10 * n].view(n, 3)
        grad_coefficients = param_grads[10 * n:].view(n, coefficient_count, 3)
        with torch_stream_scope(device):
            splat_kernels.launch_composite_backward(
                warp_descriptor(tile_ranges), warp_descriptor(sorted_ids), warp_descriptor(xy_opacity, wp.vec3),
                warp_descriptor(conics, wp.vec3), warp_descriptor(color_depth, wp.vec4),
                warp_descriptor(background.view(1, 3), wp.vec3), width=width, height=height,
                final_transmittance=warp_descriptor(final_transmittance.view(-1)),
                last_index=warp_descriptor(last_index.view(-1)),
                grad_image=warp_descriptor(grad_image.view(-1, 3), wp.vec3),
                grad_alpha=warp_descriptor(grad_alpha.view(-1)), grad_depth=warp_descriptor(grad_depth.view(-1)),
                with_abs=densify_grad_out is not None, grads=warp_descriptor(screen_grads),
            )
            if any(ctx.needs_input_grad[i] for i in (0, 1, 2, 4)):
                # The adjoint launch replays the projection's outputs, which nothing reads: they all land on one
                # vec3 (write_only_descriptor) instead of a buffer of 9 floats a Gaussian.
                sink = torch.empty(3, device=device, dtype=torch.float32)
                splat_kernels.launch_project_backward(
                    warp_descriptor(means, wp.vec3), warp_descriptor(quats, wp.vec4), warp_descriptor(scales, wp.vec3),
                    warp_descriptor(coefficients, wp.vec3), warp_descriptor(K.view(1, 3, 3), wp.mat33),
                    warp_descriptor(world_to_camera.view(1, 4, 4), wp.mat44), warp_descriptor(radii, wp.vec2i),
                    width=width, height=height, sh_degree=sh_degree,
                    scratch_mean2d=write_only_descriptor(sink, n, wp.vec2),
                    scratch_conic=write_only_descriptor(sink, n, wp.vec3),
                    scratch_depth=write_only_descriptor(sink, n, wp.float32),
                    scratch_color=write_only_descriptor(sink, n, wp.vec3),
                    grad_mean2d=warp_descriptor(screen_grads[: 2 * n].view(n, 2), wp.vec2),
                    grad_conic=warp_descriptor(screen_grads[2 * n: 5 * n].view(n, 3), wp.vec3),
                    grad_depth=warp_descriptor(screen_grads[9 * n: 10 * n]),
                    grad_color=warp_descriptor(screen_grads[6 * n: 9 * n].view(n, 3), wp.vec3),
                    grad_means=warp_descriptor(grad_means, wp.vec3), grad_quats=warp_descriptor(grad_quats, wp.vec4),
                    grad_scales=warp_descriptor(grad_scales, wp.vec3),
                    grad_coefficients=warp_descriptor(grad_coefficients, wp.vec3),
                )
        if densify_grad_out is not None:
            densify_grad_out.add_(screen_grads[10 * n:].view(n, 2))
        grad_opacities = screen_grads[5 * n: 6 * n]
        grad_background = None
        if ctx.needs_input_grad[5]:
            grad_background = (grad_image * final_transmittance[..., None]).sum(dim=(0, 1))
        return (grad_means, grad_quats, grad_scales, grad_opacities, grad_coefficients, grad_background,
                None, None, None, None, None, None, None, None)


def rasterize_gaussians(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    colors: torch.Tensor,
    K: torch.Tensor,
    world_to_camera: torch.Tensor,
    width: int,
    height: int,
    *,
    background: torch.Tensor | None = None,
    sh_degree: int | None = None,
    densify_grad_out: torch.Tensor | None = None,
    return_info: bool = False,
    intersection_capacity: int | None = None,
):
    """Render 3D Gaussians into one camera with tile-based EWA splatting (3DGS / gsplat 1.5.3 conventions).

    Differentiable with respect to ``means``, ``quats``, ``scales``, ``opacities``, ``colors`` and
    ``background``; ``K`` and ``world_to_camera`` are constants. All work is float32 on the inputs' device.
    Conventions (camera, pixel centres, quaternions, SH) are in ``docs/conventions.md``.

    Args:
        means: Gaussian centres in world units, shape [N, 3].
        quats: rotations as (w, x, y, z) quaternions, shape [N, 4]; normalized inside (need not be unit).
        scales: standard deviations along the rotated axes in world units (linear, > 0), shape [N, 3].
        opacities: peak opacities in [0, 1], shape [N].
        colors: RGB in [0, 1], shape [N, 3]; or, when ``sh_degree`` is given, spherical-harmonics coefficients
            of shape [N, C, 3] with C >= (sh_degree + 1) ** 2 (the first (sh_degree + 1) ** 2 are used, so a
            trainer may keep 16 and raise the degree over time; the others get zero gradient).
        K: pinhole intrinsics [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] in pixels, shape [3, 3], with the centre of
            pixel (column i, row j) at image coordinates (i, j).
        world_to_camera: OpenCV-convention (x right, y down, z forward) rigid transform, shape [4, 4].
        width: image width [px], >= 1.
        height: image height [px], >= 1.
        background: RGB composited behind the Gaussians with the final transmittance, shape [3]; None = black.
        sh_degree: None for RGB ``colors``; 0..3 for SH coefficients (colour = max(SH(dir) + 0.5, 0) with dir the
            unit vector from the camera centre to the Gaussian).
        densify_grad_out: optional float32 tensor [N, 2] on the same device; the backward pass adds to it, per
            Gaussian, the sum over pixels of |d loss / d mean2d| per image axis [loss units per pixel].
        return_info: also return a dict of per-Gaussian projection results.
        intersection_capacity: None: size the sort buffers to the exact number of (Gaussian, tile) pairs, read
            from the device (one host synchronization; non-finite inputs raise); on CUDA, calls of a shape seen
            before guess the size and check it at the end, and repeated calls of one shape are replayed from a
            CUDA graph (the same results; the module doc says what it holds). An int: sort in buffers of
            this many pairs without any host read (capturable in a CUDA graph); pairs past it are dropped, so
            the image is then wrong, and non-finite inputs do not raise: both show in ``info["status"]``, which
            the caller checks off the hot path (:func:`rasterizer_status`).

    Returns:
        ``(image, alpha, depth)``: float32 tensors of shapes [H, W, 3] (RGB), [H, W] (1 - final transmittance)
        and [H, W] (sum over composited Gaussians of weight times camera-space z, not normalized by alpha).
        With ``return_info`` a fourth item, a read-only mapping (:class:`RasterInfo`): ``{"radii": [N, 2] int32
        per-axis radius in pixels (0 = culled), "means2d": [N, 2] float32 projected centres in pixels (pixel
        centres at integers; 0 where culled), "depths": [N] float32 camera-space z, "status": [2] int32 on the
        device: the number of (Gaussian, tile) pairs the image needs and the non-finite-input flags (0 =
        none)}`` (not differentiable).

    Raises:
        TypeError: a tensor argument is not a floating-point tensor, or a size is not an int.
        ValueError: wrong shapes, mixed devices, bad sizes or degree, or non-finite values in the inputs.
    """
    check_tensor("means", means, (None, 3))
    device = means.device
    gaussian_count = means.shape[0]
    check_tensor("quats", quats, (gaussian_count, 4), device=device)
    check_tensor("scales", scales, (gaussian_count, 3), device=device)
    check_tensor("opacities", opacities, (gaussian_count,), device=device)
    check_tensor("K", K, (3, 3), device=device)
    check_tensor("world_to_camera", world_to_camera, (4, 4), device=device)
    for name, size in (("width", width), ("height", height)):
        if isinstance(size, bool) or not isinstance(size, int):
            raise TypeError(f"{name} must be an int, got {type(size).__name__}")
        if size < 1:
            raise ValueError(f"{name} must be >= 1, got {size}")
    if sh_degree is None:
        check_tensor("colors", colors, (gaussian_count, 3), device=device)
        coefficients = colors.reshape(gaussian_count, 1, 3)
        kernel_degree = -1
    else:
        if isinstance(sh_degree, bool) or not isinstance(sh_degree, int) or not 0 <= sh_degree <= 3:
            raise ValueError(f"sh_degree must be None or an int in 0..3, got {sh_degree!r}")
        check_tensor("colors", colors, (gaussian_count, None, 3), device=device)
        if colors.shape[1] < (sh_degree + 1) ** 2:
            raise ValueError(
                f"colors has {colors.shape[1]} SH coefficients per Gaussian, sh_degree={sh_degree} needs "
                f"at least {(sh_degree + 1) ** 2}"
            )
        coefficients = colors
        kernel_degree = sh_degree
    if background is None:
        background = _black_background(device)
    else:
        check_tensor("background", background, (3,), device=device)
    if densify_grad_out is not None:
        check_tensor("densify_grad_out", densify_grad_out, (gaussian_count, 2), device=device)
        if densify_grad_out.dtype != torch.float32:
            raise TypeError(f"densify_grad_out must be float32, got {densify_grad_out.dtype}")

    if intersection_capacity is not None and (isinstance(intersection_capacity, bool) or not isinstance(
            intersection_capacity, int) or intersection_capacity < 1):
        raise ValueError(f"intersection_capacity must be None or an int >= 1, got {intersection_capacity!r}")

    info: list = []
    image, alpha, depth = _RasterizeGaussians.apply(
        _float32(means), _float32(quats), _float32(scales), _float32(opacities), _float32(coefficients),
        _float32(background), _float32(_constant(K)), _float32(_constant(world_to_camera)), width, height,
        kernel_degree, densify_grad_out, intersection_capacity, info,
    )
    if return_info:
        radii, xy_opacity, color_depth, status = info
        return image, alpha, depth, RasterInfo(radii, xy_opacity, color_depth, status)
    return image, alpha, depth


def _float32(tensor: torch.Tensor) -> torch.Tensor:
    """``tensor`` as contiguous float32: itself when it is already (no call into torch)."""
    if tensor.dtype is torch.float32 and tensor.is_contiguous():
        return tensor
    return tensor.to(torch.float32).contiguous()


def _constant(tensor: torch.Tensor) -> torch.Tensor:
    """``tensor`` without gradient (the camera is a constant of the pass)."""
    return tensor.detach() if tensor.requires_grad else tensor


class RasterInfo(Mapping):
    """The info of :func:`rasterize_gaussians` (a read-only mapping): ``radii`` and ``status`` as the pass wrote
    them, ``means2d`` and ``depths`` made from its per-Gaussian records when first read (six small kernels on
    CUDA, which a training step or a playback frame, reading only the first two, no longer runs)."""

    __slots__ = ("_values", "_records")

    def __init__(self, radii: torch.Tensor, xy_opacity: torch.Tensor, color_depth: torch.Tensor,
                 status: torch.Tensor):
        self._values = {"radii": radii, "status": status}
        self._records = (xy_opacity, color_depth)

    def __getitem__(self, name: str) -> torch.Tensor:
        if name not in self._values:
            xy_opacity, color_depth = self._records
            if name == "means2d":
                kept = self._values["radii"].detach().bool().any(dim=1, keepdim=True)
                self._values[name] = torch.where(kept, xy_opacity[:, :2] - 0.5, 0.0)  # integer pixel centres
            elif name == "depths":
                self._values[name] = color_depth[:, 3].clone()
            else:
                raise KeyError(name)
        return self._values[name]

    def __iter__(self):
        return iter(("radii", "means2d", "depths", "status"))

    def __len__(self) -> int:
        return 4


def rasterizer_replays(*, mode: str = "address", after: int = 3, max_bytes: int = 128 << 20) -> int:
    """Set how repeated forward calls skip their host work, and release what cached graphs hold.

    An eager forward pass queues about twenty launches from Python, more host time than the GPU needs for an
    avatar's frame. Three modes:

    * ``"address"`` (the default): a call whose buffers have the addresses of a recent call's (as torch's
      caching allocator gives them to a loop that allocates the same way every time) replays that call's
      launches from a CUDA graph (:mod:`warpavatar._src.graphs.address_graphs`); nothing is held between calls but
      the graphs' sort scratch space, and calls whose buffers move run eagerly.
    * ``"owned"``: a shape called ``after`` times in a row (each fitting its guessed capacity) is captured with
      its own inputs, outputs and sort buffers and replayed whatever the call's addresses
      (:mod:`warpavatar._src.graphs.splat_replay`): the fewest host steps, but the graph holds about as much memory
      again as the pass between calls (21 MiB for an 89k-Gaussian avatar at 384x384; 93 / 244 / 432 MiB at
      100k / 500k / 1M Gaussians at 1080p), and no shape that would hold over ``max_bytes`` is captured.
    * ``"off"``: every launch from Python.

    Args:
        mode: ``"address"``, ``"owned"`` or ``"off"``.
        after: with ``"owned"``, the calls in a row after which a shape is captured (>= 1).
        max_bytes: with ``"owned"``, shapes whose graph would hold more than this many bytes stay eager (> 0;
            default 128 MiB).

    Returns:
        The bytes the owned graphs held, now released.

    Raises:
        ValueError: an unknown mode, ``after`` below 1, ``max_bytes`` not positive.
    """
    if mode not in ("address", "owned", "off"):
        raise ValueError(f"mode must be address, owned or off, got {mode!r}")
    if int(after) != after or after < 1:
        raise ValueError(f"after must be an integer >= 1, got {after!r}")
    if not max_bytes > 0:
        raise ValueError(f"max_bytes must be > 0, got {max_bytes!r}")
    held = _REPLAYS.held_bytes()
    _REPLAYS.clear()
    _PASS_GRAPHS.clear()
    splat_replay.REPLAY_AFTER = int(after) if mode == "owned" else None
    splat_replay.REPLAY_MAX_BYTES = int(max_bytes)
    address_graphs.CAPTURE_AFTER = address_graphs.DEFAULT_CAPTURE_AFTER if mode == "address" else None
    return held


def rasterizer_status(info: Mapping) -> int:
    """Check a rasterization's device-side status (one host read): the number of (Gaussian, tile) pairs it
    needed.

    Args:
        info: the info dict of :func:`rasterize_gaussians` (``return_info=True``).

    Returns:
        The pair count; an ``intersection_capacity`` below it means the image dropped pairs (grow the capacity).

    Raises:
        ValueError: the inputs held non-finite values.
    """
    pair_count, flags = info["status"].tolist()
    _raise_on_bad_inputs(flags)
    return int(pair_count)
