"""Correction kernels: a pose-dependent correction's network outputs applied to canonical Gaussians in one pass.

The pose correction (:class:`warpavatar.extensions.pose_correction.PoseCorrection`) turns 9 network outputs per
Gaussian into a corrected centre, orientation and scale: ``mean + offset_scale * o[0:3]``, the unit quaternion
``(1, o[3:6]) / |(1, o[3:6])|`` applied before the stored orientation (Hamilton product, (w, x, y, z)), and
``scale * exp(clamp(o[6:9], -3, 3))``. In torch that is some twenty element-wise kernels over the Gaussians; a
frame of playback runs this one instead (no gradients: playback only; a fit keeps the torch code, which the
tests hold this kernel to). The outputs may be float32 or float16 (the float16 network of playback), read as
float32. The frame code a pose gets (the code of the training frame whose pose it is, else zeros: what
:meth:`~warpavatar.extensions.pose_correction.PoseCorrection.frame_code` computes in seven torch kernels) takes
two: the largest entry difference from each training pose, then the closest pose's code. The network's
first-layer bias of a frame (the pose feature through the pose encoder, joined by the code, through the first
layer's pose columns: some ten small torch kernels) takes two more. Launchers take Warp arrays, check their
sizes and skip empty work; the torch bridge is :mod:`warpavatar._src.correction`.
"""

from __future__ import annotations

from typing import Any

import warp as wp

from warpavatar.kernels.launch import launch
from warpavatar.kernels.quaternion import quat_multiply

__all__ = ["LOG_SCALE_LIMIT", "apply_correction", "match_frame_code", "frame_bias"]

LOG_SCALE_LIMIT = 3.0
"""Largest magnitude of the log-scale change (outputs 6..8 are clamped to +-this)."""

_LOG_SCALE_LIMIT = wp.constant(LOG_SCALE_LIMIT)


REDUCE_LANES = 64
"""Threads of a block of :data:`pose_difference_kernel`, :data:`pose_feature_kernel`, :data:`first_bias_kernel` and
:data:`closest_code_kernel` on CUDA: a block makes one output, its threads taking every 64th term, then one
block reduction (a thread's terms are a short chain, not the whole row: one output per thread was a chain of
~150 dependent loads)."""


def _reduce_lanes(device) -> int:
    return REDUCE_LANES if wp.get_device(device).is_cuda else 1


@wp.kernel(enable_backward=False)
def apply_correction_kernel(outputs: wp.array2d(dtype=Any), means: wp.array(dtype=wp.vec3),
                            quats: wp.array(dtype=wp.vec4), scales: wp.array(dtype=wp.vec3),
                            offset_scale: wp.array(dtype=wp.float32), means_out: wp.array(dtype=wp.vec3),
                            quats_out: wp.array(dtype=wp.vec4), scales_out: wp.array(dtype=wp.vec3)):
    i = wp.tid()
    o = wp.vector(length=9, dtype=wp.float32)
    for k in range(9):
        o[k] = wp.float32(outputs[i, k])
    s = offset_scale[0]
    means_out[i] = means[i] + wp.vec3(o[0] * s, o[1] * s, o[2] * s)
    rotation = wp.vec4(1.0, o[3], o[4], o[5])
    rotation = rotation / wp.sqrt(1.0 + o[3] * o[3] + o[4] * o[4] + o[5] * o[5])
    quats_out[i] = quat_multiply(rotation, quats[i])
    scale = scales[i]
    scales_out[i] = wp.vec3(
        scale[0] * wp.exp(wp.clamp(o[6], -_LOG_SCALE_LIMIT, _LOG_SCALE_LIMIT)),
        scale[1] * wp.exp(wp.clamp(o[7], -_LOG_SCALE_LIMIT, _LOG_SCALE_LIMIT)),
        scale[2] * wp.exp(wp.clamp(o[8], -_LOG_SCALE_LIMIT, _LOG_SCALE_LIMIT)),
    )


def apply_correction(outputs: wp.array, means: wp.array, quats: wp.array, scales: wp.array, offset_scale: wp.array,
                     means_out: wp.array, quats_out: wp.array, scales_out: wp.array) -> None:
    """Write the corrected Gaussians (launcher of :func:`apply_correction_kernel`).

    Args:
        outputs: [N,C>=9] float32 or float16 network outputs (offset, rotation vector, log-scale change); columns
            past the 9th are not read (a network padded to aligned rows).
        means: [N] vec3 canonical centres [world units].
        quats: [N] vec4 unit orientations (w, x, y, z).
        scales: [N] vec3 scales [world units].
        offset_scale: [1] world length of a unit offset output.
        means_out, quats_out, scales_out: [N] outputs of the same types (may not alias the inputs).
    """
    count = means.shape[0]
    for name, array in (("outputs", outputs), ("quats", quats), ("scales", scales), ("means_out", means_out),
                        ("quats_out", quats_out), ("scales_out", scales_out)):
        if array.shape[0] != count:
            raise ValueError(f"{name} has {array.shape[0]} rows, means {count}")
    if outputs.shape[1] < 9 or offset_scale.shape != (1,):
        raise ValueError(f"outputs must be [N,>=9] and offset_scale [1], got {outputs.shape} and "
                         f"{offset_scale.shape}")
    if count == 0:
        return
    launch(apply_correction_kernel, dim=count, device=means.device,
              inputs=[outputs, means, quats, scales, offset_scale], outputs=[means_out, quats_out, scales_out])


@wp.kernel(enable_backward=False)
def pose_difference_kernel(frame_poses: wp.array2d(dtype=wp.float32), pose: wp.array(dtype=wp.float32),
                           differences: wp.array(dtype=wp.float32)):
    """One block per frame ``t`` (launched tiled): ``differences[t]`` = the largest absolute entry difference, each
    thread taking every block-size-th entry, then one block reduction (a maximum: the same in any order)."""
    t, lane = wp.tid()
    largest = wp.float32(0.0)
    for k in range(lane, frame_poses.shape[1], wp.block_dim()):
        largest = wp.max(largest, wp.abs(frame_poses[t, k] - pose[k]))
    total = wp.tile_max(wp.tile(largest))
    if lane == 0:
        differences[t] = total[0]


@wp.kernel(enable_backward=False)
def closest_code_kernel(differences: wp.array(dtype=wp.float32), codes: wp.array2d(dtype=wp.float32),
                        tolerance: wp.float32, code: wp.array(dtype=wp.float32)):
    """One block (launched tiled): the first frame of the smallest difference, found by two block reductions
    (the smallest difference, then the first frame that has it), its code written when within ``tolerance``,
    else zeros."""
    _, lane = wp.tid()
    frame_count = differences.shape[0]
    smallest = float(wp.inf)
    for t in range(lane, frame_count, wp.block_dim()):
        smallest = wp.min(smallest, differences[t])
    least = wp.tile_min(wp.tile(smallest))[0]
    first = int(frame_count)
    for t in range(lane, frame_count, wp.block_dim()):
        if differences[t] == least and t < first:
            first = t
    best = wp.tile_min(wp.tile(first))[0]
    matched = wp.float32(0.0)
    if differences[best] <= tolerance:
        matched = wp.float32(1.0)
    for c in range(lane, code.shape[0], wp.block_dim()):
        code[c] = codes[best, c] * matched


def match_frame_code(frame_poses: wp.array, pose: wp.array, codes: wp.array, tolerance: float,
                     differences: wp.array, code: wp.array) -> None:
    """Write the code of the training frame whose pose equals ``pose`` within ``tolerance`` (every entry), else
    zeros (the closest frame's code times 0; the first closest on ties).

    Args:
        frame_poses: [T, K] the training frames' poses, flattened (K = J*16).
        pose: [K'] this frame's pose, flattened (K' >= K: only the first K entries are compared).
        codes: [T, C] the frames' codes.
        tolerance: largest entry difference of a match.
        differences: [T] scratch: each frame's largest entry difference (written, not read first).
        code: [C] output.
    """
    count, width = frame_poses.shape
    if codes.shape[0] != count or differences.shape[0] != count or code.shape[0] != codes.shape[1]:
        raise ValueError(f"frame_poses {frame_poses.shape}, codes {codes.shape}, differences {differences.shape} and "
                         f"code {code.shape} do not agree")
    if pose.shape[0] < width:
        raise ValueError(f"pose has {pose.shape[0]} entries, the frames' poses {width}")
    if count == 0 or code.shape[0] == 0:
        return
    lanes = _reduce_lanes(pose.device)
    wp.launch_tiled(pose_difference_kernel, dim=[count], device=pose.device, inputs=[frame_poses, pose],
                    outputs=[differences], block_dim=lanes)
    wp.launch_tiled(closest_code_kernel, dim=[1], device=pose.device, inputs=[differences, codes, float(tolerance)],
                    outputs=[code], block_dim=lanes)


@wp.func
def relative_rotation_entry(bones: wp.array(dtype=wp.mat44), parent_index: wp.array(dtype=wp.int32), i: int):
    """Entry ``i`` of the pose feature (``relative_rotations_6d``): ``(R_parent^T R - I)[row, column]`` of joint
    ``i // 6`` over the first two columns (``row, column = divmod(i % 6, 2)``)."""
    joint = i // 6
    row = (i - joint * 6) // 2
    column = i - joint * 6 - row * 2
    rotation = bones[joint]
    parent = bones[parent_index[joint]]
    value = parent[0, row] * rotation[0, column] + parent[1, row] * rotation[1, column] + \
        parent[2, row] * rotation[2, column]
    if row == column:
        value = value - 1.0
    return value


@wp.kernel(enable_backward=False)
def pose_feature_kernel(bones: wp.array(dtype=wp.mat44), parent_index: wp.array(dtype=wp.int32),
                        encoder_weight: wp.array2d(dtype=wp.float32), encoder_bias: wp.array(dtype=wp.float32),
                        code: wp.array(dtype=wp.float32), feature: wp.array(dtype=wp.float32)):
    """One block per feature entry ``j`` (launched tiled): ``encoder_bias[j] + encoder_weight[j] . f`` with ``f``
    the pose feature (:func:`relative_rotation_entry`, made where it is read: a few loads an entry) for the
    encoded pose, the frame code's entry after it."""
    j, lane = wp.tid()
    width = encoder_bias.shape[0]
    if j >= width:  # the frame code follows the encoded pose (block-uniform)
        if lane == 0:
            feature[j] = code[j - width]
        return
    partial = float(0.0)
    for i in range(lane, encoder_weight.shape[1], wp.block_dim()):
        partial += encoder_weight[j, i] * relative_rotation_entry(bones, parent_index, i)
    total = wp.tile_sum(wp.tile(partial))
    if lane == 0:
        feature[j] = encoder_bias[j] + total[0]


@wp.kernel(enable_backward=False)
def first_bias_kernel(feature: wp.array(dtype=wp.float32), weight: wp.array2d(dtype=wp.float32),
                      bias: wp.array(dtype=wp.float32), low: wp.array(dtype=wp.float32),
                      high: wp.array(dtype=wp.float32), out: wp.array(dtype=Any)):
    """One block per hidden unit ``h`` (launched tiled): ``clamp(bias[h] + weight[h] . feature, low, high)``."""
    h, lane = wp.tid()
    partial = float(0.0)
    for j in range(lane, feature.shape[0], wp.block_dim()):
        partial += weight[h, j] * feature[j]
    total = wp.tile_sum(wp.tile(partial))
    if lane == 0:
        out[h] = out.dtype(wp.clamp(bias[h] + total[0], low[h], high[h]))


def frame_bias(bones: wp.array, parent_index: wp.array, encoder_weight: wp.array, encoder_bias: wp.array,
               code: wp.array, weight: wp.array, bias: wp.array, low: wp.array, high: wp.array, feature: wp.array,
               out: wp.array) -> None:
    """Write a frame's first-layer bias of the pose correction's network:
    ``clamp(bias + weight @ [encoder_bias + encoder_weight @ pose6d(bones), code], low, high)``.

    Args:
        bones: [J'] mat44 skinning transforms (J' >= J: the first J are the skeleton's).
        parent_index: [J] int32 each joint's parent, itself for roots.
        encoder_weight: [P, 6J] the pose encoder's weight; encoder_bias: [P] its bias.
        code: [C] the frame code, or None (C = 0).
        weight: [H, P+C] the first layer's pose and code columns (contiguous); bias: [H] its bias.
        low, high: [H] the clamp (+-inf for none).
        feature: [P+C] scratch: the encoded pose and the code.
        out: [H] float32 or float16 output.
    """
    joints, width = parent_index.shape[0], encoder_bias.shape[0]
    code_width = 0 if code is None else code.shape[0]
    if bones.shape[0] < joints or encoder_weight.shape != (width, 6 * joints):
        raise ValueError(f"bones {bones.shape}, parents {parent_index.shape} and encoder weight "
                         f"{encoder_weight.shape} do not agree")
    if feature.shape[0] != width + code_width or weight.shape[1] != feature.shape[0]:
        raise ValueError(f"feature {feature.shape}, code [{code_width}] and weight {weight.shape} do not agree")
    hidden = bias.shape[0]
    if weight.shape[0] != hidden or low.shape[0] != hidden or high.shape[0] != hidden or out.shape[0] != hidden:
        raise ValueError(f"weight {weight.shape}, bias, bounds and out must have {hidden} rows")
    lanes = _reduce_lanes(bones.device)
    wp.launch_tiled(pose_feature_kernel, dim=[feature.shape[0]], device=bones.device,
                    inputs=[bones, parent_index, encoder_weight, encoder_bias, code], outputs=[feature],
                    block_dim=lanes)
    wp.launch_tiled(first_bias_kernel, dim=[hidden], device=bones.device, inputs=[feature, weight, bias, low, high],
                    outputs=[out], block_dim=lanes)
