"""Warp kernels of refined poses: per-frame corrections of a skeleton's poses composed down the skeleton, and the
priors that hold a refined motion near its target and smooth in time (a fit's pose refinement).

Corrected poses. Frame ``t``, joint ``j``: the given pose ``B`` (rest-to-posed 4x4, rotation ``G``, translation
``b``), the rest pivot ``h``, the axis-angle correction ``d`` [rad] and the frame's root offset ``u``. The joint's
own correction turns the world about its given pivot ``p = G h + b``::

    m = [ G exp([d]) G^T | p - G exp([d]) G^T p + root_j u ]        (root_j: 1 for a root, else 0)

and the corrections compose from the roots down, ``M_j = M_parent(j) m_j`` (``M`` of a root is its ``m``); the
corrected pose is ``M_j B_j``. ``exp`` is Rodrigues' formula, with the Taylor series of ``sin(a)/a`` and
``(1 - cos(a))/a^2`` below ``a^2 = 1e-8``.

Priors, over ``T`` frames and ``J`` joints, of the corrected poses ``P`` (pivots ``q_tj = P_tj h_j`` times
``scale``, rotations ``R_tj``) and the corrections:

* prior: ``mean_tj |d_tj - d*_tj|^2 + mean_t |scale (u_t - u*_t)|^2`` (``*``: the target);
* depth: ``mean_tj a_tj^2`` with ``a_tj`` the mean of ``(q_sj - q*_sj) . v_s`` over the frames ``s`` within
  ``half`` of ``t`` (``v_s``: frame ``s``'s camera axis; fewer at the ends: the padding is not counted);
* smooth: ``mean`` over the inner frames (``1 <= t <= T-2``) and joints of ``|A q|^2 + |A R|_F^2``, ``A`` the
  second difference per video frame squared with the frames ``gaps`` apart:
  ``((x_{t+1} - x_t)/g_t - (x_t - x_{t-1})/g_{t-1}) * 2 / (g_{t-1} + g_t)``; zero with fewer than three frames.

Launch plan: ``local_motions`` (a thread per frame and joint, no loop: its backward is Warp's adjoint, launched
with ``adjoint=True``) writes every ``m``; ``compose_motions`` (a thread per frame and joint, walking up the joint's
ancestors: a thread per frame looping over the joints in order waited on 2J dependent loads, 0.44 ms a step on the
H100) writes ``M`` and the corrected poses. Backward, joint ``k``'s correction enters ``M_j = M_parent(k) m_k
(M_k^-1 M_j)`` for every ``j`` in its subtree, so ``adj m_k = M_parent(k)^T (sum over the subtree of E_j)
M_k^-T`` with ``E_j = (adj P_j) B_j^T M_j^T`` (``P_j``'s adjoint carried to ``M_j``, then to the world):
``motion_adjoint_terms`` writes every ``E`` and ``compose_motions_adjoint`` sums each subtree's (a thread per frame
and joint, no joint waiting for another). ``prior_shares`` writes each (frame, joint)'s shares of the three priors
(their sums are the priors); ``prior_shares_adjoint`` writes the gradients of the poses and corrections, a thread
per (frame, joint) owning its outputs (no atomics), recomputing the few neighbouring frames' pivots it needs.
Everything is float32. Launchers take ``warp.array`` objects and check their sizes; the torch bridge is
:mod:`warpavatar._src.poses`.
"""

from __future__ import annotations

import warp as wp

from warpavatar.kernels.launch import launch

__all__ = ["SMALL_ANGLE_SQ", "launch_local_motions", "launch_local_motions_adjoint", "launch_compose_motions",
           "launch_compose_motions_adjoint", "launch_prior_shares", "launch_prior_shares_adjoint"]

SMALL_ANGLE_SQ = wp.constant(1.0e-8)
"""Squared angle [rad^2] below which Rodrigues' coefficients come from their Taylor series."""


@wp.func
def axis_angle_rotation(d: wp.vec3):
    """Rotation matrix of the axis-angle vector ``d`` (angle = its norm [rad])."""
    angle_sq = wp.dot(d, d)
    first = float(0.0)
    second = float(0.0)
    if angle_sq < SMALL_ANGLE_SQ:
        first = 1.0 - angle_sq / 6.0
        second = 0.5 - angle_sq / 24.0
    else:
        angle = wp.sqrt(angle_sq)
        first = wp.sin(angle) / angle
        second = (1.0 - wp.cos(angle)) / angle_sq
    cross = wp.skew(d)
    return wp.identity(n=3, dtype=float) + first * cross + second * (cross @ cross)


@wp.func
def rotation_part(pose: wp.mat44):
    return wp.mat33(pose[0, 0], pose[0, 1], pose[0, 2], pose[1, 0], pose[1, 1], pose[1, 2],
                    pose[2, 0], pose[2, 1], pose[2, 2])


@wp.func
def translation_part(pose: wp.mat44):
    return wp.vec3(pose[0, 3], pose[1, 3], pose[2, 3])


@wp.func
def rigid_matrix(rotation: wp.mat33, translation: wp.vec3):
    return wp.mat44(rotation[0, 0], rotation[0, 1], rotation[0, 2], translation[0],
                    rotation[1, 0], rotation[1, 1], rotation[1, 2], translation[1],
                    rotation[2, 0], rotation[2, 1], rotation[2, 2], translation[2],
                    0.0, 0.0, 0.0, 1.0)


@wp.kernel
def local_motions(poses: wp.array2d(dtype=wp.mat44), heads: wp.array(dtype=wp.vec3),
                  root: wp.array(dtype=wp.float32), rotation: wp.array2d(dtype=wp.vec3),
                  translation: wp.array(dtype=wp.vec3), motions: wp.array2d(dtype=wp.mat44)):
    """Each joint's own correction ``m`` [T,J] (module docstring); differentiated by Warp (adjoint launch)."""
    t, j = wp.tid()
    pose = poses[t, j]
    given = rotation_part(pose)
    pivot = given @ heads[j] + translation_part(pose)
    turn = given @ axis_angle_rotation(rotation[t, j]) @ wp.transpose(given)
    motions[t, j] = rigid_matrix(turn, pivot - turn @ pivot + root[j] * translation[t])


@wp.kernel(enable_backward=False)
def compose_motions(poses: wp.array2d(dtype=wp.mat44), parents: wp.array(dtype=wp.int32),
                    motions: wp.array2d(dtype=wp.mat44), world: wp.array2d(dtype=wp.mat44),
                    corrected: wp.array2d(dtype=wp.mat44)):
    """``M_j``, the product of the corrections from joint ``j``'s root down to it, and the corrected pose
    ``M_j B_j``: a thread per frame and joint, walking up its ancestors (no joint waits for another)."""
    t, j = wp.tid()
    motion = motions[t, j]
    ancestor = parents[j]
    while ancestor >= 0:
        motion = motions[t, ancestor] @ motion
        ancestor = parents[ancestor]
    world[t, j] = motion
    corrected[t, j] = motion @ poses[t, j]


@wp.kernel(enable_backward=False)
def motion_adjoint_terms(poses: wp.array2d(dtype=wp.mat44), world: wp.array2d(dtype=wp.mat44),
                         adj_corrected: wp.array2d(dtype=wp.mat44), terms: wp.array2d(dtype=wp.mat44)):
    """``E_j = (adj P_j) B_j^T M_j^T``: each corrected pose's adjoint carried to the world, for
    :data:`compose_motions_adjoint`."""
    t, j = wp.tid()
    terms[t, j] = adj_corrected[t, j] @ wp.transpose(poses[t, j]) @ wp.transpose(world[t, j])


@wp.kernel(enable_backward=False)
def compose_motions_adjoint(parents: wp.array(dtype=wp.int32), subtree_offsets: wp.array(dtype=wp.int32),
                            subtree_members: wp.array(dtype=wp.int32), world: wp.array2d(dtype=wp.mat44),
                            terms: wp.array2d(dtype=wp.mat44), adj_motions: wp.array2d(dtype=wp.mat44)):
    """Backward of :data:`compose_motions`: joint ``k``'s correction enters ``M_j = M_parent(k) m_k (M_k^-1 M_j)``
    of every joint ``j`` of its subtree, so its adjoint is ``M_parent(k)^T (sum of E_j over the subtree)
    M_k^-T`` (:data:`motion_adjoint_terms`), a thread per frame and joint."""
    t, k = wp.tid()
    total = wp.mat44()
    for s in range(subtree_offsets[k], subtree_offsets[k + 1]):
        total += terms[t, subtree_members[s]]
    total = total @ wp.transpose(wp.inverse(world[t, k]))
    parent = parents[k]
    if parent >= 0:
        total = wp.transpose(world[t, parent]) @ total
    adj_motions[t, k] = total


# ----------------------------------------------------------------------------------------------------- priors
@wp.func
def scaled_pivot(poses: wp.array2d(dtype=wp.mat44), heads: wp.array(dtype=wp.vec3), scale: float, t: int, j: int):
    pose = poses[t, j]
    return (rotation_part(pose) @ heads[j] + translation_part(pose)) * scale


@wp.func
def depth_move(poses: wp.array2d(dtype=wp.mat44), heads: wp.array(dtype=wp.vec3),
               target_pivots: wp.array2d(dtype=wp.vec3), view_axes: wp.array(dtype=wp.vec3), scale: float, t: int,
               j: int):
    """The scaled pivot's move from its target along frame ``t``'s camera axis."""
    return wp.dot(scaled_pivot(poses, heads, scale, t, j) - target_pivots[t, j], view_axes[t])


@wp.func
def window_start(t: int, half: int):
    return wp.max(t - half, 0)


@wp.func
def window_end(t: int, half: int, count: int):
    return wp.min(t + half, count - 1)


@wp.func
def depth_average(poses: wp.array2d(dtype=wp.mat44), heads: wp.array(dtype=wp.vec3),
                  target_pivots: wp.array2d(dtype=wp.vec3), view_axes: wp.array(dtype=wp.vec3), scale: float, t: int,
                  j: int, half: int):
    """The depth moves averaged over the frames within ``half`` of ``t`` (the padding not counted)."""
    first = window_start(t, half)
    last = window_end(t, half, poses.shape[0])
    total = float(0.0)
    for s in range(first, last + 1):
        total += depth_move(poses, heads, target_pivots, view_axes, scale, s, j)
    return total / float(last - first + 1)


@wp.func
def difference_weights(gaps: wp.array(dtype=wp.float32), t: int):
    """Weights of frames ``t-1, t, t+1`` in the second difference at inner frame ``t`` [per video frame^2]."""
    before = gaps[t - 1]
    after = gaps[t]
    k = 2.0 / (before + after)
    return wp.vec3(k / before, -k * (1.0 / before + 1.0 / after), k / after)


@wp.func
def pivot_acceleration(poses: wp.array2d(dtype=wp.mat44), heads: wp.array(dtype=wp.vec3),
                       gaps: wp.array(dtype=wp.float32), scale: float, t: int, j: int):
    w = difference_weights(gaps, t)
    return (w[0] * scaled_pivot(poses, heads, scale, t - 1, j) + w[1] * scaled_pivot(poses, heads, scale, t, j)
            + w[2] * scaled_pivot(poses, heads, scale, t + 1, j))


@wp.func
def rotation_acceleration(poses: wp.array2d(dtype=wp.mat44), gaps: wp.array(dtype=wp.float32), t: int, j: int):
    w = difference_weights(gaps, t)
    return (w[0] * rotation_part(poses[t - 1, j]) + w[1] * rotation_part(poses[t, j])
            + w[2] * rotation_part(poses[t + 1, j]))


@wp.kernel(enable_backward=False)
def prior_shares(poses: wp.array2d(dtype=wp.mat44), heads: wp.array(dtype=wp.vec3),
                 rotation: wp.array2d(dtype=wp.vec3), translation: wp.array(dtype=wp.vec3),
                 target_rotation: wp.array2d(dtype=wp.vec3), target_translation: wp.array(dtype=wp.vec3),
                 target_pivots: wp.array2d(dtype=wp.vec3), view_axes: wp.array(dtype=wp.vec3),
                 gaps: wp.array(dtype=wp.float32), scale: float, half: int, shares: wp.array2d(dtype=wp.vec3)):
    """Frame ``t`` and joint ``j``'s shares of (prior, depth, smooth): their sums over all are the priors."""
    t, j = wp.tid()
    frames = poses.shape[0]
    joints = poses.shape[1]
    entries = float(frames * joints)
    offset = rotation[t, j] - target_rotation[t, j]
    prior = wp.dot(offset, offset) / entries
    if j == 0:  # the frame's root offset, averaged over the frames
        shift = (translation[t] - target_translation[t]) * scale
        prior += wp.dot(shift, shift) / float(frames)
    average = depth_average(poses, heads, target_pivots, view_axes, scale, t, j, half)
    smooth = float(0.0)
    if t >= 1 and t + 1 < frames:
        a = pivot_acceleration(poses, heads, gaps, scale, t, j)
        r = rotation_acceleration(poses, gaps, t, j)
        smooth = (wp.dot(a, a) + wp.ddot(r, r)) / float((frames - 2) * joints)
    shares[t, j] = wp.vec3(prior, average * average / entries, smooth)


@wp.kernel(enable_backward=False)
def prior_shares_adjoint(poses: wp.array2d(dtype=wp.mat44), heads: wp.array(dtype=wp.vec3),
                         rotation: wp.array2d(dtype=wp.vec3), translation: wp.array(dtype=wp.vec3),
                         target_rotation: wp.array2d(dtype=wp.vec3), target_translation: wp.array(dtype=wp.vec3),
                         target_pivots: wp.array2d(dtype=wp.vec3), view_axes: wp.array(dtype=wp.vec3),
                         gaps: wp.array(dtype=wp.float32), scale: float, half: int,
                         adj_priors: wp.array(dtype=wp.float32), adj_poses: wp.array2d(dtype=wp.mat44),
                         adj_rotation: wp.array2d(dtype=wp.vec3), adj_translation: wp.array(dtype=wp.vec3)):
    """Backward of :data:`prior_shares` summed: ``adj_priors`` [3] the gradients of the three priors; writes every
    entry of ``adj_poses`` [T,J], ``adj_rotation`` [T,J] and ``adj_translation`` [T]."""
    t, j = wp.tid()
    frames = poses.shape[0]
    joints = poses.shape[1]
    entries = float(frames * joints)
    adj_rotation[t, j] = adj_priors[0] * 2.0 / entries * (rotation[t, j] - target_rotation[t, j])
    if j == 0:
        adj_translation[t] = (adj_priors[0] * 2.0 * scale * scale / float(frames)) * (
            translation[t] - target_translation[t])
    # depth: frame t's move enters the average of every frame s within half of it
    adj_move = float(0.0)
    for s in range(window_start(t, half), window_end(t, half, frames) + 1):
        count = window_end(s, half, frames) - window_start(s, half) + 1
        adj_move += 2.0 * depth_average(poses, heads, target_pivots, view_axes, scale, s, j, half) / float(count)
    adj_pivot = view_axes[t] * (adj_move * adj_priors[1] / entries)  # of the scaled pivot
    adj_turn = wp.mat33()
    if frames >= 3:  # smooth: frame t enters the second differences at t-1, t and t+1
        weight = adj_priors[2] * 2.0 / float((frames - 2) * joints)
        for s in range(wp.max(t - 1, 1), wp.min(t + 1, frames - 2) + 1):
            w = difference_weights(gaps, s)[t - s + 1] * weight
            adj_pivot += w * pivot_acceleration(poses, heads, gaps, scale, s, j)
            adj_turn += w * rotation_acceleration(poses, gaps, s, j)
    adj_pivot = adj_pivot * scale  # of the pose's pivot, P h
    adj_turn += wp.outer(adj_pivot, heads[j])
    adj_poses[t, j] = wp.mat44(adj_turn[0, 0], adj_turn[0, 1], adj_turn[0, 2], adj_pivot[0],
                               adj_turn[1, 0], adj_turn[1, 1], adj_turn[1, 2], adj_pivot[1],
                               adj_turn[2, 0], adj_turn[2, 1], adj_turn[2, 2], adj_pivot[2],
                               0.0, 0.0, 0.0, 0.0)


# -------------------------------------------------------------------------------------------------- launchers
def _check_rows(expected: tuple[int, ...], **arrays) -> None:
    for name, array in arrays.items():
        if tuple(array.shape[: len(expected)]) != expected:
            raise ValueError(f"{name} has shape {tuple(array.shape)}, expected {expected} leading")


def launch_local_motions(poses, heads, root, rotation, translation, motions) -> None:
    """Write each joint's own correction ``motions`` [T,J] (mat44).

    Args:
        poses: mat44 [T,J] the given poses; heads: vec3 [J] rest pivots [world units]; root: float32 [J], 1 for
            a root joint, else 0; rotation: vec3 [T,J] axis-angle corrections [rad]; translation: vec3 [T] the
            roots' offsets [world units].
    """
    frames, joints = poses.shape
    _check_rows((frames, joints), rotation=rotation, motions=motions)
    _check_rows((joints,), heads=heads, root=root)
    _check_rows((frames,), translation=translation)
    if frames * joints == 0:
        return
    launch(local_motions, dim=(frames, joints), inputs=[poses, heads, root, rotation, translation],
              outputs=[motions], device=poses.device)


def launch_local_motions_adjoint(poses, heads, root, rotation, translation, scratch_motions, adj_motions,
                                 adj_rotation, adj_translation) -> None:
    """Adjoint launch of :data:`local_motions`: adds to ``adj_rotation`` [T,J] and ``adj_translation`` [T] (zero
    on entry) the gradients from ``adj_motions`` [T,J]; ``scratch_motions`` [T,J] is written, never read."""
    frames, joints = poses.shape
    _check_rows((frames, joints), rotation=rotation, scratch_motions=scratch_motions, adj_motions=adj_motions,
                adj_rotation=adj_rotation)
    _check_rows((frames,), translation=translation, adj_translation=adj_translation)
    if frames * joints == 0:
        return
    launch(local_motions, dim=(frames, joints), inputs=[poses, heads, root, rotation, translation],
              outputs=[scratch_motions], adj_inputs=[None, None, None, adj_rotation, adj_translation],
              adj_outputs=[adj_motions], adjoint=True, device=poses.device)


def launch_compose_motions(poses, parents, motions, world, corrected) -> None:
    """Compose the joints' corrections down the skeleton: ``world`` [T,J] (each joint's ``M``) and ``corrected``
    [T,J] (the corrected poses). ``parents`` int32 [J]: each joint's parent, -1 for a root (a forest)."""
    frames, joints = poses.shape
    _check_rows((joints,), parents=parents)
    _check_rows((frames, joints), motions=motions, world=world, corrected=corrected)
    if frames * joints == 0:
        return
    launch(compose_motions, dim=(frames, joints), inputs=[poses, parents, motions], outputs=[world, corrected],
              device=poses.device)


def launch_compose_motions_adjoint(poses, parents, subtree_offsets, subtree_members, world, adj_corrected, terms,
                                   adj_motions) -> None:
    """Backward of :func:`launch_compose_motions`: writes ``adj_motions`` [T,J] from ``adj_corrected`` [T,J] in two
    launches. ``subtree_offsets`` int32 [J+1] and ``subtree_members`` int32: joint ``k``'s subtree (itself and
    every descendant) is ``subtree_members[subtree_offsets[k]:subtree_offsets[k+1]]``; ``terms`` [T,J] is scratch."""
    frames, joints = poses.shape
    _check_rows((joints,), parents=parents)
    _check_rows((joints + 1,), subtree_offsets=subtree_offsets)
    _check_rows((frames, joints), world=world, adj_corrected=adj_corrected, terms=terms, adj_motions=adj_motions)
    if frames * joints == 0:
        return
    launch(motion_adjoint_terms, dim=(frames, joints), inputs=[poses, world, adj_corrected], outputs=[terms],
              device=poses.device)
    launch(compose_motions_adjoint, dim=(frames, joints),
              inputs=[parents, subtree_offsets, subtree_members, world, terms], outputs=[adj_motions],
              device=poses.device)


def _check_priors(poses, heads, rotation, translation, target_rotation, target_translation, target_pivots,
                  view_axes, gaps, half) -> tuple[int, int]:
    frames, joints = poses.shape
    _check_rows((frames, joints), rotation=rotation, target_rotation=target_rotation, target_pivots=target_pivots)
    _check_rows((frames,), translation=translation, target_translation=target_translation, view_axes=view_axes)
    _check_rows((joints,), heads=heads)
    if frames >= 3 and gaps.shape[0] < frames - 1:
        raise ValueError(f"gaps has {gaps.shape[0]} entries, expected {frames - 1}")
    if half < 0:
        raise ValueError(f"half must be >= 0, got {half}")
    return frames, joints


def launch_prior_shares(poses, heads, rotation, translation, target_rotation, target_translation, target_pivots,
                        view_axes, gaps, *, scale: float, half: int, shares) -> None:
    """Write each (frame, joint)'s shares of (prior, depth, smooth) into ``shares`` vec3 [T,J] (module docstring).

    Args:
        poses: mat44 [T,J] the corrected poses; heads: vec3 [J] rest pivots [world units].
        rotation, target_rotation: vec3 [T,J] the corrections and their target [rad].
        translation, target_translation: vec3 [T] the root offsets and their target [world units].
        target_pivots: vec3 [T,J] the target's pivots times ``scale``; view_axes: vec3 [T] each frame's camera
            axis (unit, world).
        gaps: float32 [T-1] video frames between consecutive frames (> 0; any one entry when T < 3).
        scale: lengths' factor (1 / the canonical extent); half: the depth prior's averaging half-width [frames].
    """
    frames, joints = _check_priors(poses, heads, rotation, translation, target_rotation, target_translation,
                                   target_pivots, view_axes, gaps, half)
    _check_rows((frames, joints), shares=shares)
    if frames * joints == 0:
        return
    launch(prior_shares, dim=(frames, joints),
              inputs=[poses, heads, rotation, translation, target_rotation, target_translation, target_pivots,
                      view_axes, gaps, float(scale), int(half)], outputs=[shares], device=poses.device)


def launch_prior_shares_adjoint(poses, heads, rotation, translation, target_rotation, target_translation,
                                target_pivots, view_axes, gaps, *, scale: float, half: int, adj_priors, adj_poses,
                                adj_rotation, adj_translation) -> None:
    """Backward of the priors (the sums of :func:`launch_prior_shares`' shares): from ``adj_priors`` float32 [3],
    writes ``adj_poses`` mat44 [T,J], ``adj_rotation`` vec3 [T,J] and ``adj_translation`` vec3 [T]."""
    frames, joints = _check_priors(poses, heads, rotation, translation, target_rotation, target_translation,
                                   target_pivots, view_axes, gaps, half)
    _check_rows((frames, joints), adj_poses=adj_poses, adj_rotation=adj_rotation)
    _check_rows((frames,), adj_translation=adj_translation)
    _check_rows((3,), adj_priors=adj_priors)
    if frames * joints == 0:
        return
    launch(prior_shares_adjoint, dim=(frames, joints),
              inputs=[poses, heads, rotation, translation, target_rotation, target_translation, target_pivots,
                      view_axes, gaps, float(scale), int(half), adj_priors],
              outputs=[adj_poses, adj_rotation, adj_translation], device=poses.device)
