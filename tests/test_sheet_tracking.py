"""The garment sheet's tracking stage (:class:`~warpavatar.extensions.garment_sheet_part.SheetTracker`) on a synthetic
case: a cone skirt whose true per-frame states are known (swinging sideways about its waistband while the body
turns), masks rasterized from them, and states started hung low and narrow as a rollout leaves them."""

from __future__ import annotations

import math

import pytest
import torch

from warpavatar.extensions.garment_sheet_part import (GarmentSheetPart, SheetTracker, covered_cells, project_frames,
                                                      tracking_targets)
from warpavatar.sim import Capsules

FRAMES = 6
SIZE = 72  # image side [px]
CELLS = 36  # tracking grid cells a side (2 px cells)
ITERATIONS = 40


def _cone_sheet(rings=5, segments=10, top=0.12, hem=0.28, length=0.5, waist=1.0):
    """A closed cone from a waistband ring (pinned) down to its hem: vertices [V,3], faces [F,3], pinned [P]."""
    vertices = [[(top + (hem - top) * r / (rings - 1)) * math.cos(2 * math.pi * s / segments),
                 (top + (hem - top) * r / (rings - 1)) * math.sin(2 * math.pi * s / segments),
                 waist - length * r / (rings - 1)] for r in range(rings) for s in range(segments)]
    faces = []
    for r in range(rings - 1):
        for s in range(segments):
            a, b = r * segments + s, r * segments + (s + 1) % segments
            faces += [[a, a + segments, b], [b, a + segments, b + segments]]
    return torch.tensor(vertices), torch.tensor(faces), torch.arange(segments)


def _rotation(axis, angle) -> torch.Tensor:
    x, y, z = axis
    k = torch.tensor([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])
    return torch.eye(3) + math.sin(angle) * k + (1 - math.cos(angle)) * k @ k


def _about_waist(part, skinned, transform) -> torch.Tensor:
    """States [T,V,3] that move each frame's skinned sheet [T,V,3] by ``transform(t, offsets from the waist)``."""
    states = torch.zeros_like(skinned)
    for t in range(skinned.shape[0]):
        centre = skinned[t, part.attached].mean(0)
        states[t] = (transform(t, skinned[t] - centre) + centre - skinned[t]) * part.free_mask
    return states


def _raster(pixels: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """Masks [T,SIZE,SIZE] uint8 of projected sheets (pixel centres inside a triangle, edges included)."""
    y, x = torch.meshgrid(torch.arange(SIZE).float(), torch.arange(SIZE).float(), indexing="ij")
    centre = torch.stack([x, y], -1).reshape(-1, 1, 2)
    masks = []
    for frame in pixels:
        a, b, c = frame[faces].unbind(1)
        sides = [(v[:, 0] - u[:, 0]) * (centre[..., 1] - u[:, 1]) - (v[:, 1] - u[:, 1]) * (centre[..., 0] - u[:, 0])
                 for u, v in ((a, b), (b, c), (c, a))]
        inside = (torch.stack(sides) >= 0).all(0) | (torch.stack(sides) <= 0).all(0)
        masks.append(inside.any(1).reshape(SIZE, SIZE))
    return torch.stack(masks).to(torch.uint8) * 255


@pytest.fixture(scope="module")
def case():
    vertices, faces, pinned = _cone_sheet()
    capsules = Capsules(torch.tensor([[0.0, 0.0, 0.95]]), torch.tensor([[0.0, 0.0, 0.3]]), torch.tensor([0.08]))
    part = GarmentSheetPart(torch.zeros(0, dtype=torch.int64), vertices, faces, pinned, torch.ones(len(vertices), 1),
                            joint=0, capsules=capsules, capsule_ids=torch.tensor([0]), max_substep=1.0 / 120.0,
                            joint_count=1, settle_substeps=60)
    bones = torch.eye(4).repeat(FRAMES, 1, 1, 1)
    for t in range(FRAMES):  # the body turns and walks sideways
        bones[t, 0, :3, :3] = _rotation((0.0, 0.0, 1.0), 0.15 * t)
        bones[t, 0, 0, 3] = 0.01 * t
    focal = 120.0
    intrinsics = torch.tensor([[focal, 0.0, (SIZE - 1) / 2], [0.0, focal, (SIZE - 1) / 2], [0.0, 0.0, 1.0]])
    rotation = torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])  # looking along +y
    world_to_camera = torch.eye(4)
    world_to_camera[:3, :3] = rotation
    world_to_camera[:3, 3] = -rotation @ torch.tensor([0.0, -2.5, 0.75])
    intrinsics, world_to_cameras = intrinsics.repeat(FRAMES, 1, 1), world_to_camera.repeat(FRAMES, 1, 1)
    skinned = torch.stack([part.skinned_rest(b) for b in bones])
    truth = _about_waist(part, skinned, lambda t, offset: offset @ _rotation(
        (0.0, 1.0, 0.0), 0.3 * math.sin(2 * math.pi * t / FRAMES)).T)
    hung = _about_waist(part, skinned, lambda t, offset: offset * torch.tensor([0.7, 0.7, 1.35]))
    masks = _raster(project_frames(skinned + truth, intrinsics, world_to_cameras)[0], faces)
    targets = tracking_targets(masks, cells=CELLS)
    seconds = [1.0 / 30.0] * FRAMES

    def tracked(**weights):
        tracker = SheetTracker(part, bones, seconds, intrinsics, world_to_cameras, targets,
                               **{"lambda_dynamics": 0.1, "lambda_edges": 1.0, "dynamics_frames": 2, **weights})
        return tracker.run(hung, iterations=ITERATIONS, lr=0.1 * part.edge_length)

    return dict(part=part, bones=bones, truth=truth, hung=hung, masks=masks, targets=targets, tracked=tracked(),
                tracked_without_physics=tracked(lambda_dynamics=0.0), skinned=skinned,
                cameras=(intrinsics, world_to_cameras))


def _state_error(part, states, truth) -> float:
    """Mean distance of the free vertices from their true places, in edge lengths."""
    free = part.free_mask[:, 0] > 0
    return float((states - truth)[:, free].norm(dim=2).mean()) / part.edge_length


def test_tracking_fits_the_masks_and_brings_the_states_to_the_truth(case):
    part, (fitted, record) = case["part"], case["tracked"]
    assert record["iterations"] == ITERATIONS and record["frames"] == FRAMES
    iou = record["coverage_iou"]
    assert iou["before"]["mean"] < 0.6 and iou["after"]["mean"] > max(0.8, iou["before"]["mean"] + 0.3), iou
    assert iou["after"]["min"] > 0.75, iou
    assert len(iou["after"]["per_frame"]) == FRAMES
    for name in ("outside", "uncovered"):
        assert record[name]["after"] < 0.1 * record[name]["before"], (name, record[name])
    before, after = _state_error(part, case["hung"], case["truth"]), _state_error(part, fitted, case["truth"])
    assert after < 0.6 * before, (before, after)
    assert float(fitted[:, part.attached].abs().max()) == 0.0  # the ring stays the body's


def test_the_physics_term_keeps_the_residual_bounded(case):
    _, record = case["tracked"]
    _, unheld = case["tracked_without_physics"]
    residual = record["dynamics"]
    assert residual["after"] < 2.0 * residual["before"], residual
    assert unheld["dynamics"]["after"] > 5.0 * residual["after"], (unheld["dynamics"], residual)


def test_covered_cells_are_the_cells_whose_centre_a_triangle_holds(case):
    part = case["part"]
    intrinsics, world_to_cameras = case["cameras"]
    pixels, depth = project_frames(case["skinned"] + case["truth"], intrinsics, world_to_cameras)
    covered = covered_cells(pixels, depth > 0, part.faces, cell=1, rows=SIZE, columns=SIZE)
    assert torch.equal(covered, case["masks"] > 0)  # (1-pixel cells: the exact raster)
    behind = covered_cells(pixels, torch.zeros_like(depth, dtype=torch.bool), part.faces, cell=1, rows=SIZE,
                           columns=SIZE)
    assert not bool(behind.any())


def test_the_targets_hold_the_masks_distance_and_the_garments_cells(case):
    targets, masks = case["targets"], case["masks"]
    assert targets.cell == 2 and targets.region.shape == (FRAMES, CELLS, CELLS)
    inside = torch.nn.functional.avg_pool2d(masks.float()[:, None] / 255.0, 2)[:, 0] > 0.5
    assert torch.equal(targets.region, inside) and not bool(targets.other.any())
    assert float(targets.distance[inside].max()) <= 1.0  # within half a cell inside the mask
    far = targets.distance[0, 0, 0]  # a corner: about its distance to the mask's nearest pixel
    ys, xs = torch.nonzero(masks[0] > 0, as_tuple=True)
    assert abs(float(far) - float(((xs - 0.5) ** 2 + (ys - 0.5) ** 2).sqrt().min())) < 1.5
    body = torch.zeros_like(masks, dtype=torch.bool)
    body[:, : SIZE // 2] = True  # the upper half is "the body"
    split = tracking_targets(masks, body, cells=CELLS, distance=targets.distance)
    assert not bool(split.region[:, : CELLS // 2].any()) and torch.equal(split.region | split.other, inside)
    anchor = torch.zeros_like(targets.region)
    anchor[:, 0, 0] = True  # a first guess far away: nothing is within reach
    assert not bool(tracking_targets(masks, cells=CELLS, anchor=anchor, reach=0.05).region.any())


def test_a_frame_whose_sheet_collapses_or_breaks_is_not_kept(case):
    part, skinned = case["part"], case["skinned"]
    intrinsics, world_to_cameras = case["cameras"]
    tracker = SheetTracker(part, case["bones"], [1.0 / 30.0] * FRAMES, intrinsics, world_to_cameras, case["targets"],
                           lambda_dynamics=0.1, lambda_edges=1.0)
    states = case["truth"].clone()
    assert bool(tracker.valid_frames(states).all())
    free = part.free_mask[:, 0] > 0
    centre = tracker.vertices(states)[1, free].mean(dim=0)
    states[1, free] = centre - skinned[1, free]  # frame 1: every free vertex at one point
    squashed = tracker.vertices(states)[2] - skinned[2]
    squashed[free, 0] = skinned[2, free, 0].mean() - skinned[2, free, 0]  # frame 2: flattened into a plane x = c
    states[2] = squashed
    states[3, int(free.nonzero()[0])] = float("nan")  # frame 3: a vertex lost
    assert tracker.valid_frames(states).tolist() == [True, False, False, False] + [True] * (FRAMES - 4)
    _, record = case["tracked"]
    assert record["kept_frames"] == 0  # the fixture's tracking keeps every fitted frame


def test_a_motion_that_comes_back_to_a_pose_keeps_its_own_sheet_there(case):
    from warpavatar.model.parts import PoseFrame

    part = case["part"]
    swing = case["bones"][:3].clone()
    bones = torch.cat([swing, swing[:1]])  # the fourth frame repeats the first pose, the sheet still swinging
    part.prepare_sequence(bones, torch.full((4,), 1.0 / 30.0))
    sheets = part._sequence[1]
    assert float((sheets[3] - sheets[0]).abs().max()) > 1e-4  # (the rollout does differ there)
    for index in (0, 3):
        looked_up = part._lookup(PoseFrame(bones[index], index, {}, None), bones[index])
        assert torch.equal(looked_up, sheets[index]), index
    # without an index the pose alone decides: its first frame
    assert torch.equal(part._lookup(PoseFrame(bones[3], None, {}, None), bones[3]), sheets[0])
