"""The pieces of warpavatar.sim together, as a garment part would use them: capsules from the body's Gaussians,
a skirt of nodes attached at its waist and simulated over a twisting, walking body, and the garment Gaussians
riding on the nodes."""

import math

import torch

from warpavatar.geometry import quat_to_matrix
from warpavatar.sim import (
    ClothModel,
    capsules_near,
    cloth_graph,
    fit_body_capsules,
    nearest_nodes,
    node_rotations,
    pose_capsules,
    ride_on_nodes,
)
from warpavatar.sim.capsules import select

HEADS = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0], [0.3, 0.0, 1.4]])  # spine, pelvis, an arm
TAILS = torch.tensor([[0.0, 0.0, 1.5], [0.0, 0.0, 0.6], [0.6, 0.0, 1.4]])
RADII = torch.tensor([0.14, 0.13, 0.05])


def ring_points(generator, head, tail, radius, count, spread=0.005):
    angle = 2 * math.pi * torch.rand(count, generator=generator)
    t = torch.rand(count, 1, generator=generator)
    axis = tail - head
    unit = axis / axis.norm()
    side = torch.linalg.cross(unit, torch.tensor([0.0, 1.0, 0.0]) if unit[1].abs() < 0.9 else torch.tensor([1.0, 0, 0]))
    side = side / side.norm()
    other = torch.linalg.cross(unit, side)
    r = radius + spread * torch.randn(count, 1, generator=generator)
    return head + t * axis + r * (angle.cos()[:, None] * side + angle.sin()[:, None] * other)


def twist(frame):
    """Bone transforms [3,4,4] of a frame: the upper body twists about z, the whole body walks along x."""
    angle = 0.15 * frame
    transforms = torch.eye(4).repeat(3, 1, 1)
    rotation = torch.tensor([[math.cos(angle), -math.sin(angle), 0.0], [math.sin(angle), math.cos(angle), 0.0],
                             [0.0, 0.0, 1.0]])
    for bone in (0, 2):
        transforms[bone, :3, :3] = rotation
    transforms[:, 0, 3] += 0.02 * frame
    return transforms


def test_a_skirt_on_a_twisting_walking_body():
    generator = torch.Generator().manual_seed(0)
    body = torch.cat([ring_points(generator, HEADS[b], TAILS[b], RADII[b], 400) for b in range(3)])
    owner = torch.arange(3).repeat_interleave(400)
    # the skirt: from the waist (z = 1.05) down to z = 0.65, around the pelvis, a little outside it
    skirt = ring_points(generator, torch.tensor([0.0, 0.0, 1.05]), torch.tensor([0.0, 0.0, 0.65]), 0.16, 1500,
                        spread=0.002)
    means = torch.cat([body, skirt])
    weights = torch.nn.functional.one_hot(torch.cat([owner, torch.ones(1500, dtype=torch.long)]), 3).float()
    garment = torch.cat([torch.zeros(1200, dtype=torch.bool), torch.ones(1500, dtype=torch.bool)])

    capsules = fit_body_capsules(HEADS, TAILS, means, weights, exclude=garment)
    torch.testing.assert_close(capsules.radius, RADII, rtol=0, atol=0.005)  # (the points spread 0.005)
    # the skirt's nodes: a subset of its Gaussians; the waist row is attached to the spine
    nodes = skirt[::6]
    near = capsules_near(capsules, nodes, margin=0.1)
    assert near.tolist() == [0, 1]  # the arm is too far to matter
    body_capsules = select(capsules, near)
    waist = torch.nonzero(nodes[:, 2] > 1.03).reshape(-1)
    assert 5 < len(waist) < 40
    graph = cloth_graph(nodes, neighbours=6, bend_per_node=4)
    model = ClothModel(nodes, graph, waist, node_mass=0.5 / len(nodes), max_substep=1 / 240)
    edges = torch.cat([graph.stretch, graph.stretch.flip(1)])

    anchor = nearest_nodes(skirt, nodes)
    offset = skirt - nodes[anchor]
    gaussian_quats = torch.nn.functional.normalize(torch.randn(len(skirt), 4, generator=generator), dim=1)

    state = model.rest_state(nodes)
    state, _ = model.settle(state, nodes[waist], capsules=pose_capsules(body_capsules, twist(0)[near]), max_frames=15)
    quats = None
    with torch.no_grad():
        for frame in range(1, 16):
            transforms = twist(frame)
            posed = pose_capsules(body_capsules, transforms[near])
            targets = nodes[waist] @ transforms[0, :3, :3].T + transforms[0, :3, 3]  # skinned to the spine
            state = model.step(state, targets, 1 / 30, capsules=posed)
            assert torch.equal(state.positions[waist], targets)
            # no node inside the body
            x = state.positions
            for start, end, radius in zip(posed.segment_start, posed.segment_end, posed.radius):
                d = end - start
                t = (((x - start) @ d) / (d @ d)).clamp(0, 1)
                assert ((x - start - t[:, None] * d).norm(dim=1) >= radius - 1e-5).all()
            quats = node_rotations(nodes, state.positions, edges, initial=quats, iterations=3)
            gaussian_means, rotations = ride_on_nodes(state.positions, quats, anchor, offset, gaussian_quats)
            assert torch.isfinite(gaussian_means).all() and torch.isfinite(rotations).all()
            # riding keeps each Gaussian at its rest distance from its node
            torch.testing.assert_close((gaussian_means - state.positions[anchor]).norm(dim=1), offset.norm(dim=1),
                                       rtol=1e-4, atol=1e-6)
    # the skirt followed the body: its centre walked with it and the waist twisted with the spine
    walked = state.positions[:, 0].mean() - nodes[:, 0].mean()
    assert 0.2 < walked.item() < 0.4
    waist_rotation = quat_to_matrix(quats[waist]).mean(dim=0)
    assert abs(math.atan2(waist_rotation[1, 0], waist_rotation[0, 0]) - 0.15 * 15) < 0.15
