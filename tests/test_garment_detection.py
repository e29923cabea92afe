"""Garment detection on a skinned figure: which loose garments are found, and the joint each hangs from.

The figure (metres, z up, x forward, y to its left) is a small skeleton of hips, spine, chest, neck (with the
head), two arms and hands, the left hand with two fingers side by side, and two legs, its surface sampled as
tubes round the bones, walking: the legs swing in opposition about the hips, each arm against its own leg, the
fingers curl against each other. Its weights are what a fitted skinning field gives (one chain per body point,
smooth blends at the joints, a crotch blended between the thighs); each garment is a cone frustum hand-placed
over it (not simulated: detection reads only canonical positions and weights, and settling a sheet on the
figure would add Warp compilation and stepping to tests meant to take about a second), with weights blended
across the chains that push it. The body a garment hides is left out, as a fit prunes the Gaussians nothing
sees.
"""

import math

import pytest
import torch

from warpavatar.extensions.garment_detection import detect_garments

HIPS, SPINE, CHEST, NECK, ARM_L, ARM_R, LEG_L, LEG_R, HAND_L, FINGER_A, FINGER_B, HAND_R = range(12)
PARENTS = [-1, 0, 1, 2, 2, 2, 0, 0, 4, 8, 8, 5]
HEADS = torch.tensor([[0.0, 0.0, 0.77], [0.0, 0.0, 0.93], [0.0, 0.0, 1.10], [0.0, 0.0, 1.32],
                      [0.0, 0.15, 1.28], [0.0, -0.15, 1.28], [0.0, 0.09, 0.72], [0.0, -0.09, 0.72],
                      [0.0, 0.45, 0.98], [0.012, 0.51, 0.92], [-0.012, 0.51, 0.92], [0.0, -0.45, 0.98]])
TAILS = torch.tensor([[0.0, 0.0, 0.93], [0.0, 0.0, 1.10], [0.0, 0.0, 1.32], [0.0, 0.0, 1.70],
                      [0.0, 0.45, 0.98], [0.0, -0.45, 0.98], [0.0, 0.09, 0.0], [0.0, -0.09, 0.0],
                      [0.0, 0.51, 0.92], [0.012, 0.55, 0.88], [-0.012, 0.55, 0.88], [0.0, -0.51, 0.92]])
UP = torch.tensor([0.0, 0.0, 1.0])
JOINTS = len(PARENTS)
DENSITY = 2500.0  # surface samples per square metre


def _rotation(axis: int, angle: float) -> torch.Tensor:
    c, s = math.cos(angle), math.sin(angle)
    i, j = [k for k in range(3) if k != axis]
    rotation = torch.eye(3)
    rotation[i, i], rotation[i, j], rotation[j, i], rotation[j, j] = c, -s, s, c
    return rotation


def _walk(frame_count: int = 8) -> torch.Tensor:
    """Rest-to-posed transforms ``[T, J, 4, 4]``: each joint turns about its head (parents first)."""
    transforms = torch.eye(4).repeat(frame_count, JOINTS, 1, 1)
    for frame in range(frame_count):
        phase = math.sin(2 * math.pi * frame / frame_count)
        turns = {LEG_L: (1, 0.5 * phase), LEG_R: (1, -0.5 * phase), ARM_L: (1, -0.4 * phase),
                 ARM_R: (1, 0.4 * phase), FINGER_A: (0, 0.5 * phase), FINGER_B: (0, -0.5 * phase)}
        for joint, parent in enumerate(PARENTS):
            local = torch.eye(4)
            if joint in turns:
                rotation = _rotation(*turns[joint])
                local[:3, :3], local[:3, 3] = rotation, HEADS[joint] - rotation @ HEADS[joint]
            transforms[frame, joint] = local if parent < 0 else transforms[frame, parent] @ local
    return transforms


def _tube(generator, start, end, radius, *, count=None):
    """Points on a tube round a segment, and each one's distance along it from ``start``."""
    start, end = torch.as_tensor(start), torch.as_tensor(end)
    along = end - start
    length = float(along.norm())
    count = count or max(24, int(DENSITY * 2 * math.pi * radius * length))
    axis = along / length
    side = torch.linalg.cross(axis, torch.tensor([1.0, 0.0, 0.0]))
    if float(side.norm()) < 1e-3:
        side = torch.linalg.cross(axis, torch.tensor([0.0, 0.0, 1.0]))
    side = side / side.norm()
    other = torch.linalg.cross(axis, side)
    s = length * torch.rand(count, generator=generator)
    angle = 2 * math.pi * torch.rand(count, generator=generator)
    points = start + s[:, None] * axis + radius * (torch.cos(angle)[:, None] * side + torch.sin(angle)[:, None] * other)
    return points, s


def _torso_chain(z: torch.Tensor) -> torch.Tensor:
    """Weights ``[N, J]`` along hips - spine - chest by height, blended over 4 cm either side of each joint."""
    weights = torch.zeros(z.shape[0], JOINTS)
    to_spine = ((z - 0.89) / 0.08).clamp(0, 1)
    to_chest = ((z - 1.06) / 0.08).clamp(0, 1)
    weights[:, HIPS] = 1 - to_spine
    weights[:, SPINE] = to_spine * (1 - to_chest)
    weights[:, CHEST] = to_chest
    return weights


def _limb(points, s, joint, parent, blend=0.06):
    """One limb's weights, blended into its parent within ``blend`` of the joint (the skin round a joint)."""
    weights = torch.zeros(points.shape[0], JOINTS)
    share = 0.5 * (1 - s / blend).clamp_min(0)
    weights[:, joint], weights[:, parent] = 1 - share, share
    return weights


def _body(generator):
    """The bare figure: ``(means [N,3], weights [N,J])``."""
    parts = []
    torso, _ = _tube(generator, (0.0, 0.0, 0.72), (0.0, 0.0, 1.32), 0.13)
    parts.append((torso, _torso_chain(torso[:, 2])))
    head, s = _tube(generator, (0.0, 0.0, 1.32), (0.0, 0.0, 1.70), 0.08)
    parts.append((head, _limb(head, s, NECK, CHEST)))
    for joint, parent, radius in ((ARM_L, CHEST, 0.04), (ARM_R, CHEST, 0.04), (LEG_L, HIPS, 0.06),
                                  (LEG_R, HIPS, 0.06), (HAND_L, ARM_L, 0.025), (HAND_R, ARM_R, 0.025)):
        points, s = _tube(generator, HEADS[joint], TAILS[joint], radius)
        weights = _limb(points, s, joint, parent)
        if joint in (LEG_L, LEG_R):  # the crotch: the inner thighs' top blends the two legs
            other = LEG_R if joint == LEG_L else LEG_L
            inner = (points[:, 1] * HEADS[joint, 1] < 0.0045) & (s < 0.08)
            weights[inner] *= 0.6
            weights[inner, other] += 0.4 * (1 - s[inner] / 0.08)
            weights[inner, joint] += 0.4 * s[inner] / 0.08
        parts.append((points, weights))
    # the fingers side by side, blended half and half along their length (a field cannot tell them apart)
    for joint in (FINGER_A, FINGER_B):
        points, s = _tube(generator, HEADS[joint], TAILS[joint], 0.009, count=80)
        weights = torch.zeros(points.shape[0], JOINTS)
        weights[:, FINGER_A] = weights[:, FINGER_B] = 0.5
        parts.append((points, weights))
    return torch.cat([p for p, _ in parts]), torch.cat([w for _, w in parts])


def _drape(generator, top, hem):
    """A cone frustum about the vertical axis from ``top = (z, radius x, radius y)`` down to ``hem`` (elliptic where
    the two radii differ), sampled evenly over its area (near enough); returns its points and the function
    telling which body points it hides (those inside it)."""
    (z_top, x_top, y_top), (z_hem, x_hem, y_hem) = top, hem
    r_top, r_hem = 0.5 * (x_top + y_top), 0.5 * (x_hem + y_hem)
    slant = math.hypot(z_top - z_hem, r_hem - r_top)
    count = int(DENSITY * math.pi * (r_top + r_hem) * slant)
    u = torch.rand(count, generator=generator)  # area-uniform along the slant of a circular frustum
    fraction = (torch.sqrt(r_top ** 2 + u * (r_hem ** 2 - r_top ** 2)) - r_top) / max(r_hem - r_top, 1e-9)
    angle = 2 * math.pi * torch.rand(count, generator=generator)
    points = torch.stack([(x_top + fraction * (x_hem - x_top)) * torch.cos(angle),
                          (y_top + fraction * (y_hem - y_top)) * torch.sin(angle),
                          z_top + fraction * (z_hem - z_top)], dim=1)

    def hides(body):
        height = body[:, 2]
        at = ((z_top - height) / (z_top - z_hem)).clamp(0, 1)
        x_radius, y_radius = x_top + at * (x_hem - x_top), y_top + at * (y_hem - y_top)
        inside = (body[:, 0] / x_radius) ** 2 + (body[:, 1] / y_radius) ** 2 < 1.0
        return inside & (height <= z_top) & (height >= z_hem)

    return points, hides


def _by_side(points, share):
    """The two legs' (or arms') shares of ``share [N]`` by side: the strip in front and behind, within 60 % of
    the radius of the middle, is blended; the panels over each side move with that side's limb alone."""
    radius = points[:, :2].norm(dim=1).clamp_min(1e-6)
    left = 0.5 + 0.5 * (points[:, 1] / (0.6 * radius)).clamp(-1, 1)
    return share * left, share * (1 - left)


def _dressed(generator, garment: str):
    """The figure in a garment: ``(means, weights, cloth [N] bool)``."""
    body, body_weights = _body(generator)
    if garment == "skirt":  # from the waist (the top of the hips' bone) to below the knees' height
        cloth, hides = _drape(generator, (0.93, 0.15, 0.15), (0.45, 0.34, 0.34))
        legs = 0.9 * ((0.93 - cloth[:, 2]) / 0.15).clamp(0, 1)
        weights = torch.zeros(cloth.shape[0], JOINTS)
        weights[:, HIPS] = 1 - legs
        weights[:, LEG_L], weights[:, LEG_R] = _by_side(cloth, legs)
    elif garment == "tunic":  # loose from under the chest's top to the knees; the legs push it more the lower
        cloth, hides = _drape(generator, (1.22, 0.14, 0.14), (0.45, 0.32, 0.32))
        legs = 0.9 * ((1.22 - cloth[:, 2]) / 0.5).clamp(0, 1).sqrt()
        weights = _torso_chain(cloth[:, 2]) * (1 - legs)[:, None]
        weights[:, LEG_L], weights[:, LEG_R] = _by_side(cloth, legs)
    elif garment == "poncho":  # from round the neck over the shoulders and arms to the elbows; flat in front
        cloth, hides = _drape(generator, (1.34, 0.12, 0.20), (0.95, 0.20, 0.52))
        arms = 0.3 + 0.5 * ((1.34 - cloth[:, 2]) / 0.39).clamp(0, 1)
        weights = torch.zeros(cloth.shape[0], JOINTS)
        weights[:, CHEST] = 1 - arms
        weights[:, ARM_L], weights[:, ARM_R] = _by_side(cloth, arms)
    else:
        raise ValueError(garment)
    shown = ~hides(body)
    means = torch.cat([body[shown], cloth])
    is_cloth = torch.cat([torch.zeros(int(shown.sum()), dtype=torch.bool),
                          torch.ones(cloth.shape[0], dtype=torch.bool)])
    return means, torch.cat([body_weights[shown], weights]), is_cloth


def _detect(means, weights, **options):
    return detect_garments(means, weights, PARENTS, _walk(), heads=HEADS, tails=TAILS, up=UP, **options)


def _assert_found(means, weights, cloth, joint, *, coverage=0.85, body=0.1):
    found = _detect(means, weights)
    assert len(found) == 1, [(r.gaussian_ids.numel(), r.joint) for r in found]
    garment = torch.zeros(means.shape[0], dtype=torch.bool)
    garment[found[0].gaussian_ids] = True
    covered = float((garment & cloth).sum() / cloth.sum())
    wrong = float((garment & ~cloth).sum() / garment.sum())
    assert found[0].joint == joint, (found[0].joint, found[0].anchor, found[0].split_joints)
    assert covered > coverage and wrong < body, (covered, wrong)
    return found[0]


def test_a_skirt_is_found_and_hangs_from_the_hips():
    means, weights, cloth = _dressed(torch.Generator().manual_seed(0), "skirt")
    found = _assert_found(means, weights, cloth, HIPS)
    assert set(found.split_joints) == {LEG_L, LEG_R} and found.anchor == HIPS


def test_a_tunic_hung_from_the_chest_is_found_whole_and_hangs_from_the_chest():
    means, weights, cloth = _dressed(torch.Generator().manual_seed(1), "tunic")
    found = _assert_found(means, weights, cloth, CHEST)
    assert found.anchor == HIPS  # the legs push it; it moves with the chest at its top
    assert float(means[found.gaussian_ids, 2].max()) > 1.15  # its upper part, above the seeds between the legs


def test_a_poncho_is_found_and_hangs_from_the_shoulders():
    means, weights, cloth = _dressed(torch.Generator().manual_seed(2), "poncho")
    found = _assert_found(means, weights, cloth, CHEST)
    assert set(found.split_joints) == {ARM_L, ARM_R}
    # the forearms and hands out of it stay body
    dominant = weights.argmax(dim=1)
    hands = ((dominant == HAND_L) | (dominant == HAND_R) | (dominant == ARM_L) | (dominant == ARM_R)) & ~cloth
    assert hands.sum() > 30 and float(hands[found.gaussian_ids].sum()) < 0.2 * float(hands.sum())


def test_a_rigid_body_with_a_crotch_and_armpits_has_no_garment():
    means, weights = _body(torch.Generator().manual_seed(3))
    assert _detect(means, weights) == []
    # the crotch's blend of the thighs scores little (it lies near the hip joints, which the legs turn about);
    # seen with a lower threshold, it is still no garment: it does not hang a skirt's length below the hips
    # (rule 5)
    tiny = dict(min_fraction=0.001, seed_fraction=0.001, threshold=0.002)
    assert _detect(means, weights, **tiny) == []
    patches = _detect(means, weights, min_length=0.0, hang_fraction=0.0, reach=0.99, **tiny)
    crotch = [r for r in patches if set(r.split_joints) == {LEG_L, LEG_R}]
    assert crotch and all(float(means[r.gaussian_ids, 2].min()) > 0.55 for r in crotch)


def test_fingers_side_by_side_are_no_garment():
    means, weights = _body(torch.Generator().manual_seed(4))
    fingers = (weights[:, FINGER_A] > 0) & (weights[:, FINGER_B] > 0)
    tiny = dict(min_fraction=0.001, seed_fraction=0.001, threshold=0.001)
    # their blend is seen (they curl against each other) but hangs a finger's length below the hand (rule 5)
    assert not any(bool(fingers[r.gaussian_ids].any()) for r in _detect(means, weights, **tiny))
    loose = _detect(means, weights, min_length=0.0, reach=0.99, **tiny)
    assert any(set(r.split_joints) == {FINGER_A, FINGER_B} for r in loose)


def test_offsets_are_a_second_cue():
    """A garment whose weights skinning fitted to one chain is found by the free offsets the fit gave it."""
    generator = torch.Generator().manual_seed(5)
    body, body_weights = _body(generator)
    cloth, hides = _drape(generator, (0.93, 0.15, 0.15), (0.45, 0.34, 0.34))
    shown = ~hides(body)
    means = torch.cat([body[shown], cloth])
    weights = torch.cat([body_weights[shown], torch.nn.functional.one_hot(torch.full((cloth.shape[0],), HIPS),
                                                                          JOINTS).float()])
    assert _detect(means, weights) == []
    swing = 0.1 * ((0.93 - cloth[:, 2]) / 0.48).clamp(0, 1)  # the hem swings 10 cm, the waistband not at all
    offsets = torch.zeros(6, means.shape[0], 3)
    for frame in range(6):
        offsets[frame, -cloth.shape[0]:, 0] = swing * math.sin(2 * math.pi * frame / 6)
    found = _detect(means, weights, offsets=offsets)
    assert len(found) == 1 and found[0].joint == HIPS
    assert float(found[0].gaussian_ids.ge(int(shown.sum())).float().mean()) > 0.9
    with pytest.raises(ValueError, match="offsets"):
        _detect(means, weights, offsets=offsets[:, :10])
