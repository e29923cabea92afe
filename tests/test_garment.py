"""The garment extension: detection, the simulated part, fitting through the simulation, files and consumers."""

import copy
import dataclasses
import json
import math

import numpy as np
import pytest
import torch

from warpavatar import data
from warpavatar.extensions.garment import GarmentExtension, GarmentPart
from warpavatar.extensions.garment_detection import (detect_garments, lowest_common_ancestor, related_joints,
                                                     split_motion, split_weight)
from warpavatar.extensions.graph import voxel_downsample
from warpavatar.fit import Trainer, preset
from warpavatar.model import Avatar
from warpavatar.model.parts import frame_intervals

# a pelvis (0) with a spine (1) and two legs (2, 3), each leg with a shin (4, 5)
PARENTS = [-1, 0, 0, 0, 2, 3]
# their canonical heads: the hips at z = 1, the knees at z = 0.5
HEADS = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0], [0.0, 0.1, 1.0], [0.0, -0.1, 1.0], [0.0, 0.1, 0.5],
                      [0.0, -0.1, 0.5]])


def _ring(centre_xy, radius, heights, count, generator):
    angle = 2 * math.pi * torch.rand(count, generator=generator)
    z = heights[0] + (heights[1] - heights[0]) * torch.rand(count, generator=generator)
    r = radius(z) if callable(radius) else torch.full_like(z, radius)
    return torch.stack([centre_xy[0] + r * torch.cos(angle), centre_xy[1] + r * torch.sin(angle), z], dim=1)


def _body(generator, *, skirt: bool):
    """Legs, shins and a torso as cylinders of points, each skinned to its bone; with ``skirt``, a cone from the
    hips to the knees whose weights blend the two legs by side (as a fitted field gives cloth between them)."""
    parts = [(_ring((0.0, 0.0), 0.12, (1.0, 1.5), 800, generator), 1),
             (_ring((0.0, 0.1), 0.06, (0.5, 1.0), 500, generator), 2),
             (_ring((0.0, -0.1), 0.06, (0.5, 1.0), 500, generator), 3),
             (_ring((0.0, 0.1), 0.05, (0.0, 0.5), 400, generator), 4),
             (_ring((0.0, -0.1), 0.05, (0.0, 0.5), 400, generator), 5)]
    means = torch.cat([points for points, _ in parts])
    weights = torch.cat([torch.nn.functional.one_hot(torch.full((p.shape[0],), j), 6).float() for p, j in parts])
    if skirt:
        cone = _ring((0.0, 0.0), lambda z: 0.14 + 0.3 * (1.0 - z), (0.45, 1.0), 1200, generator)
        left = (0.5 + 0.5 * (cone[:, 1] / 0.45).clamp(-1, 1)) * 0.9
        cone_weights = torch.zeros(cone.shape[0], 6)
        cone_weights[:, 2], cone_weights[:, 3], cone_weights[:, 0] = left, 0.9 - left, 0.1
        means, weights = torch.cat([means, cone]), torch.cat([weights, cone_weights])
    return means, weights


def _walk(frame_count=8, swing=0.5):
    """The legs (and their shins) swing in opposition about the hips (z = 1) while the torso stays."""
    transforms = torch.eye(4).repeat(frame_count, 6, 1, 1)
    for frame in range(frame_count):
        angle = swing * math.sin(2 * math.pi * frame / frame_count)
        for joints, sign in (((2, 4), 1.0), ((3, 5), -1.0)):
            c, s = math.cos(sign * angle), math.sin(sign * angle)
            rotation = torch.tensor([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])
            pivot = torch.tensor([0.0, 0.0, 1.0])
            for joint in joints:
                transforms[frame, joint, :3, :3] = rotation
                transforms[frame, joint, :3, 3] = pivot - rotation @ pivot
    return transforms


def test_joint_relations_and_common_ancestors():
    related = related_joints(PARENTS)
    assert related[0, 4] and related[4, 0] and related[2, 4] and not related[2, 3] and not related[4, 5]
    assert not related[1, 2]
    assert lowest_common_ancestor(PARENTS, 4, 5) == 0 and lowest_common_ancestor(PARENTS, 4, 2) == 2
    weights = torch.tensor([[0.0, 0.0, 0.7, 0.3, 0.0, 0.0], [0.5, 0.0, 0.5, 0.0, 0.0, 0.0]])
    assert torch.allclose(split_weight(weights, related), torch.tensor([0.3, 0.0]))
    # 0.7 x 0.3 of how far apart the two legs carry the point; nothing for a blend along one chain
    points = torch.tensor([[0.0, 0.0, 0.5], [0.0, 0.0, 0.5]])
    motion = _walk()
    expected = torch.stack([0.21 * (t[2] @ torch.tensor([0.0, 0.0, 0.5, 1.0]) - t[3] @ torch.tensor([0.0, 0.0, 0.5, 1.0]))
                            [:3].norm() for t in motion]).mean()
    assert torch.allclose(split_motion(points, weights, related, motion), torch.stack([expected, torch.tensor(0.0)]),
                          atol=1e-6)


def test_detection_finds_the_skirt_between_two_legs_and_nothing_on_a_bare_body():
    generator = torch.Generator().manual_seed(0)
    means, weights = _body(generator, skirt=True)
    found = detect_garments(means, weights, PARENTS, _walk())
    assert len(found) == 1
    garment = found[0]
    is_skirt = torch.zeros(means.shape[0], dtype=torch.bool)
    is_skirt[-1200:] = True
    hits = is_skirt[garment.gaussian_ids]
    assert hits.float().mean() > 0.9 and hits.sum() > 0.8 * 1200  # (the smoothing reaches the legs it touches)
    assert garment.joint == 0 and set(garment.split_joints) == {2, 3}
    bare, bare_weights = _body(torch.Generator().manual_seed(0), skirt=False)
    assert detect_garments(bare, bare_weights, PARENTS, _walk()) == []
    # the same skirt on a body that does not move its legs apart is not told from the body
    assert detect_garments(means, weights, PARENTS, torch.eye(4).repeat(4, 6, 1, 1)) == []


def test_detection_keeps_what_hangs_below_its_attachment_and_drops_a_blend_above_it():
    generator = torch.Generator().manual_seed(1)
    means, weights = _body(generator, skirt=True)
    # a patch of the torso (above the hips) that the field blends between the spine and the left leg, as a
    # forearm brushing the head: it moves apart with the leg like cloth would, but it does not hang
    patch = _ring((0.0, 0.0), 0.13, (1.1, 1.45), 900, generator)
    patch_weights = torch.zeros(patch.shape[0], 6)
    patch_weights[:, 1], patch_weights[:, 2] = 0.55, 0.45
    means, weights = torch.cat([means, patch]), torch.cat([weights, patch_weights])
    up = torch.tensor([0.0, 0.0, 1.0])
    without_rule = detect_garments(means, weights, PARENTS, _walk())
    above = [r for r in without_rule if float(means[r.gaussian_ids, 2].median()) > 1.0]
    assert above, "the patch above the hips must score as split without the hanging rule"
    found = detect_garments(means, weights, PARENTS, _walk(), heads=HEADS, up=up)
    assert len(found) == 1 and found[0].joint == 0 and set(found[0].split_joints) == {2, 3}
    assert float(means[found[0].gaussian_ids, 2].median()) < 1.0  # the skirt, below the hips
    # the rule measures along the given up axis: upside down the skirt is "above" the hips and the patch hangs
    flipped = detect_garments(means, weights, PARENTS, _walk(), heads=HEADS, up=-up)
    assert flipped and all(float(means[r.gaussian_ids, 2].median()) > 1.0 for r in flipped)
    with pytest.raises(ValueError, match="hang_fraction"):
        detect_garments(means, weights, PARENTS, _walk(), heads=HEADS, up=up, hang_fraction=1.5)


# the bones' ends: the pelvis is a point at the hips, the spine reaches z = 1.5, the legs the knees, the shins z = 0
TAILS = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, 1.5], [0.0, 0.1, 0.5], [0.0, -0.1, 0.5], [0.0, 0.1, 0.0],
                      [0.0, -0.1, 0.0]])
UP = torch.tensor([0.0, 0.0, 1.0])


def _panelled_skirt(generator):
    """A bare body in a skirt whose weights blend the legs only in the strips between them (front and back); the
    panels over each leg's side carry that leg's weights alone, as a fitted field gives them. Returns the means,
    the weights and the masks of the skirt's blended strips and of its one-leg panels."""
    means, weights = _body(generator, skirt=False)
    cone = _ring((0.0, 0.0), lambda z: 0.14 + 0.15 * (1.0 - z), (0.45, 1.0), 1600, generator)
    side = cone[:, 1] / (0.14 + 0.15 * (1.0 - cone[:, 2]))  # -1 (right leg's side) .. 1 (left leg's side)
    strip = side.abs() < 0.5
    left = torch.where(strip, 0.45 + 0.45 * side, torch.where(side > 0, 0.9, 0.0))
    cone_weights = torch.zeros(cone.shape[0], 6)
    cone_weights[:, 2], cone_weights[:, 3], cone_weights[:, 0] = left, 0.9 - left, 0.1
    body = torch.zeros(means.shape[0], dtype=torch.bool)
    return (torch.cat([means, cone]), torch.cat([weights, cone_weights]), torch.cat([body, strip]),
            torch.cat([body, ~strip]))


def test_detection_grows_the_blended_strips_into_the_whole_skirt_and_stops_at_the_hem():
    means, weights, strip, panel = _panelled_skirt(torch.Generator().manual_seed(2))
    seeds_only = detect_garments(means, weights, PARENTS, _walk())
    assert seeds_only  # the front and the back strip, apart
    chosen = torch.zeros(means.shape[0], dtype=torch.bool)
    chosen[torch.cat([region.gaussian_ids for region in seeds_only])] = True
    assert (chosen & panel).sum() < 0.5 * panel.sum(), "the one-leg panels must not be seeds by themselves"
    found = detect_garments(means, weights, PARENTS, _walk(), heads=HEADS, tails=TAILS, up=UP)
    assert len(found) == 1 and found[0].joint == 0 and set(found[0].split_joints) == {2, 3}
    chosen = torch.zeros(means.shape[0], dtype=torch.bool)
    chosen[found[0].gaussian_ids] = True
    assert (chosen & panel).sum() > 0.95 * panel.sum() and (chosen & strip).sum() > 0.95 * strip.sum()
    hem = float(means[strip, 2].min())
    assert float(means[chosen, 2].min()) >= hem - 1e-6  # the shins below the hem stay body
    assert not bool((chosen & (means[:, 2] > 1.0)).any())  # and so does the torso above the hips
    # a bare body grows nothing
    bare, bare_weights = _body(torch.Generator().manual_seed(2), skirt=False)
    assert detect_garments(bare, bare_weights, PARENTS, _walk(), heads=HEADS, tails=TAILS, up=UP) == []


def test_detection_sees_past_clones():
    """Density control leaves clones of a Gaussian almost on top of each other: the k-NN graph must still link
    the surface, or the garment falls apart into patches smaller than a garment."""
    means, weights, strip, panel = _panelled_skirt(torch.Generator().manual_seed(6))
    clones = 6
    generator = torch.Generator().manual_seed(7)
    cloned = means.repeat(clones, 1) + 0.002 * torch.randn(means.shape[0] * clones, 3, generator=generator)
    found = detect_garments(cloned, weights.repeat(clones, 1), PARENTS, _walk(), heads=HEADS, tails=TAILS, up=UP)
    assert len(found) == 1
    skirt = (strip | panel).repeat(clones)
    assert skirt[found[0].gaussian_ids].sum() > 0.95 * skirt.sum()
    # with 8 neighbours (links up to twice the distance to the 8th) the clones cut the surface apart
    assert detect_garments(cloned, weights.repeat(clones, 1), PARENTS, _walk(), heads=HEADS, tails=TAILS, up=UP,
                           neighbours=8, link=2.0) == []


def test_the_whole_skirt_is_held_by_a_waistband_ring():
    generator = torch.Generator().manual_seed(4)
    means, weights, strip, panel = _panelled_skirt(generator)
    # the hips under the skirt, skinned to the pelvis: body that holds, but the cloth hangs from the waist only
    hips = _ring((0.0, 0.0), 0.1, (0.7, 1.0), 400, generator)
    means = torch.cat([means, hips])
    weights = torch.cat([weights, torch.nn.functional.one_hot(torch.zeros(400, dtype=torch.long), 6).float()])
    garment = torch.cat([strip | panel, torch.zeros(400, dtype=torch.bool)])
    voxel = 0.05
    nodes = voxel_downsample(means[garment], voxel)
    node_weights = torch.zeros(nodes.shape[0], 6)
    node_weights[:, 0], node_weights[:, 2], node_weights[:, 3] = 0.1, 0.45, 0.45
    anywhere = GarmentExtension._attached(means, weights, garment, nodes, node_weights, PARENTS, 0, voxel)
    assert float(nodes[anywhere, 2].min()) < 0.8  # without up, the hips hold the skirt down to their bottom
    held = GarmentExtension._attached(means, weights, garment, nodes, node_weights, PARENTS, 0, voxel, up=UP)
    top = float(nodes[:, 2].max())
    assert 0 < held.numel() < nodes.shape[0] // 4
    assert float(nodes[held, 2].min()) >= top - 3.0 * voxel - 1e-6  # the top edge, not the hips below it
    sectors = ((torch.atan2(nodes[held, 1], nodes[held, 0]) + math.pi) / (2 * math.pi) * 8).long().clamp(0, 7)
    assert torch.unique(sectors).numel() == 8  # a closed ring round the waist


def test_detection_rejects_blends_with_a_far_bone_or_a_trace_of_weight():
    generator = torch.Generator().manual_seed(3)
    means, weights = _body(generator, skirt=False)
    shin = (weights[:, 5] > 0.5) & (means[:, 2] < 0.4)  # the right shin, below the skirt's usual hem
    blended = weights.clone()
    blended[shin, 5], blended[shin, 1] = 0.85, 0.15  # a trace of the spine, half a body away
    up_to_rule_1 = detect_garments(means, blended, PARENTS, _walk(), heads=HEADS, up=UP, reach=0.99)
    assert up_to_rule_1 and set(up_to_rule_1[0].split_joints) == {5, 1}, "scores as cloth without nearness"
    assert detect_garments(means, blended, PARENTS, _walk(), heads=HEADS, tails=TAILS, up=UP) == []
    # a trace of a near, unrelated bone: the other shin, at 5 % of the weight
    traced = weights.clone()
    traced[shin, 5], traced[shin, 4] = 0.95, 0.05
    assert detect_garments(means, traced, PARENTS, _walk(), min_weight=0.0, threshold=0.001)
    assert detect_garments(means, traced, PARENTS, _walk(), threshold=0.001) == []
    with pytest.raises(ValueError, match="min_weight"):
        detect_garments(means, traced, PARENTS, _walk(), min_weight=1.0)


# ---------------------------------------------------------------------------------------------- tiny fits
def _tiny(**overrides):
    values = dict(iterations=24, image_scale=0.5, max_train_frames=6, init_points_per_bone=20,
                  init_carve_candidates=8000, init_carve_points=600, sh_degree=1, grid_cells=12, grid_min_cells=4,
                  field_hidden=16, field_layers=1, field_warmup_steps=6, gaussian_only_steps=6, densify_from=8,
                  densify_every=8, densify_until=20, checkpoint_every=1000, log_every=4, preview_frames=1,
                  garment_from=10)
    values.update(overrides)
    return preset("quick", **values)


# a forced garment on the robot: every slightly split Gaussian, hung from the root; coarse nodes and substeps
FORCED = dict(garment_threshold=0.0005, garment_min_fraction=0.01, garment_voxel=0.12, garment_substep=1.0 / 60.0,
              garment_window=2, garment_refresh_every=6)


@pytest.fixture(scope="module")
def video():
    return data.load_video_folder(data.demo_subject_path() / "train", max_frames=8, scale=0.5)


@pytest.fixture(scope="module")
def forced(video, tmp_path_factory):
    config = _tiny(garment="auto", garment_attach=video.skeleton.names[0], **FORCED)
    trainer = Trainer(video, config, tmp_path_factory.mktemp("forced"))
    part_before = {}

    def snapshot():
        part = trainer.avatar.part("garment")
        if part is not None and not part_before:
            part_before.update({n: p.detach().clone() for n, p in part.cloth.named_parameters()})

    original = trainer.extension("garment").optimizers

    def optimizers(step):
        snapshot()
        return original(step)

    trainer.extension("garment").optimizers = optimizers
    trainer.fit(progress=False)
    return trainer, config, part_before


def test_auto_changes_nothing_until_a_garment_is_found(video, tmp_path):
    # detection reads the model and draws no random numbers: a fit where it has not found a garment (here: not
    # yet run) is the fit with the garment off, bit for bit
    auto = Trainer(video, _tiny(garment="auto", garment_from=1000), tmp_path / "auto")
    auto.fit(progress=False)
    assert auto.avatar.part("garment") is None
    off = Trainer(video, _tiny(garment="off"), tmp_path / "off")
    off.fit(progress=False)
    assert off.extension("garment") is None
    for name in ("means", "quats", "log_scales", "opacity_logits", "sh_dc"):
        assert torch.equal(getattr(auto.gaussians, name), getattr(off.gaussians, name)), name


def test_a_forced_garment_trains_its_cloth(forced):
    trainer, _, before = forced
    part = trainer.avatar.part("garment")
    assert part is not None and part.gaussian_ids.numel() > 0 and part.attached.numel() > 0
    assert part.anchor.shape == part.gaussian_ids.shape
    assert int(part.gaussian_ids.max()) < trainer.gaussians.count
    changed = [name for name, value in part.cloth.named_parameters() if not torch.equal(value.detach(), before[name])]
    assert "stiffness_logit" in changed and "rest_length_logit" in changed and "rest_offset_logit" in changed
    for value in part.cloth.parameters():
        assert torch.isfinite(value).all()
    log = [line for line in (trainer.log_path.read_text().splitlines()) if "garment_stiffness" in line]
    assert log, "the cloth's values are logged"
    assert all("garment_rest_offset" in line and "garment_rest_smooth" in line for line in log)
    moved = (part.cloth.rest_positions().detach() - part.nodes).norm(dim=1)
    assert float(moved.max()) > 0.0 and float(moved.max()) < part.hyper["rest_bound"]
    assert float(moved[part.attached].max()) == 0.0
    summary = trainer.extension("garment").summary_lines()
    assert any(line.startswith("garment rest shape: nodes moved") for line in summary)


def test_resume_gives_the_same_avatar_bit_for_bit(forced, video, tmp_path):
    whole, config, _ = forced
    Trainer(video, config, tmp_path / "parts").fit(progress=False, stop_at=14)
    resumed = Trainer(video, config, tmp_path / "parts")
    resumed.fit(resume=True, progress=False)
    for name in ("means", "quats", "sh_dc"):
        assert torch.equal(getattr(whole.gaussians, name), getattr(resumed.gaussians, name)), name
    for (name, a), b in zip(whole.avatar.part("garment").cloth.named_parameters(),
                            resumed.avatar.part("garment").cloth.parameters()):
        assert torch.equal(a, b), name


def _motion(video, count=6):
    bones = torch.as_tensor(video.bone_transforms[:count], dtype=torch.float32)
    return bones.flip(0).contiguous()  # the training motion backwards: a motion the fit never saw


def test_the_part_round_trips_through_the_avatar_file_and_renders_the_same(forced, video, tmp_path):
    trainer = forced[0]
    path = trainer.avatar.save(tmp_path / "avatar.pt")
    loaded = Avatar.load(path)
    part = loaded.part("garment")
    assert isinstance(part, GarmentPart)
    camera = video.cameras[0]
    with torch.no_grad():
        for avatar in (trainer.avatar, loaded):
            avatar.prepare_sequence(_motion(video))
        for index in (0, 3):
            pose = trainer.frames.bone_transforms[index]  # a training instant: the table
            assert torch.equal(trainer.avatar.render(camera, pose)[0], loaded.render(camera, pose)[0])
            pose = _motion(video)[index]  # the prepared motion
            assert torch.equal(trainer.avatar.render(camera, pose)[0], loaded.render(camera, pose)[0])
        lone = trainer.frames.bone_transforms[2].clone()
        lone[:, 2, 3] += 0.05  # a pose of no sequence: the cloth settles there
        image = trainer.avatar.render(camera, lone)[0]
        assert torch.isfinite(image).all() and torch.equal(image, loaded.render(camera, lone)[0])


def test_a_displacement_before_skinning_rides_on_the_cloth(forced):
    # another part (as --secondary-motion does) displaces Gaussians before skinning: the garment's keep it, turned
    # with their node's frame, and their rotations stay the cloth's
    from warpavatar.model.parts import AvatarPart

    class Shove(AvatarPart):
        name = "shove"

        def __init__(self, offset):
            super().__init__()
            self.offset = offset

        def deform_canonical(self, canonical, bones, frame):
            return canonical.displaced(self.offset)

    avatar = copy.deepcopy(forced[0].avatar)
    ids = avatar.part("garment").gaussian_ids
    count = avatar.gaussians.means.shape[0]
    offset = 0.02 * torch.randn(count, 3, generator=torch.Generator().manual_seed(4))
    pose = forced[0].frames.bone_transforms[3]  # a training instant: the cloth from the rollout's table
    with torch.no_grad():
        before = avatar.pose(pose)
        avatar.add_part(Shove(offset))
        after = avatar.pose(pose)
    assert after["canonical_offsets"] is not None and before["canonical_offsets"] is None
    moved = after["means"][ids] - before["means"][ids]
    assert torch.allclose(moved.norm(dim=1), offset[ids].norm(dim=1), atol=1e-5)  # a rotation of the offset
    assert (moved - offset[ids]).norm(dim=1).max() > 1e-4  # turned, not merely added
    assert torch.equal(after["quats"][ids], before["quats"][ids])
    others = torch.ones(count, dtype=torch.bool)
    others[ids] = False
    assert (after["means"][others] - before["means"][others]).norm(dim=1).min() > 0  # skinned with the offset


def test_a_new_motion_starts_settled_and_the_attached_nodes_follow_the_body(forced, video):
    part = forced[0].avatar.part("garment")
    motion = _motion(video)
    bones = torch.stack([forced[0].avatar.pose_bones(b) for b in motion])
    intervals = frame_intervals(range(motion.shape[0]), 30.0)
    with torch.no_grad():
        positions, velocities = part.rollout(bones, intervals.tolist())
        # settled: the nodes drift by less than a tenth of their spacing per frame at frame 0
        speed = velocities[0].norm(dim=1).mean()
        assert speed * intervals[0] < 0.1 * part.hyper["voxel_size"]
        for frame in range(motion.shape[0]):
            assert torch.allclose(positions[frame][part.attached], part.attachment_targets(bones[frame]), atol=1e-5)
        # the free nodes are simulated, not skinned: they differ from the skinned shape
        skinned, _ = part.skinned_nodes(bones[3])
        free = torch.ones(part.node_count, dtype=torch.bool)
        free[part.attached] = False
        assert (positions[3][free] - skinned[free]).norm(dim=1).max() > 1e-3
        # a still pose stays still (settled), and two rollouts are the same (determinism)
        still = bones[:1].expand(4, -1, -1, -1).contiguous()
        rest, _ = part.rollout(still, [1 / 30] * 4)
        assert (rest[-1] - rest[0]).norm(dim=1).max() < 0.05 * part.hyper["voxel_size"] + 1e-4
        again, _ = part.rollout(bones, intervals.tolist())
        assert torch.equal(again, positions)


def test_consumers_run_the_simulation(forced, video):
    from warpavatar.io.animation import posed_frames

    avatar = forced[0].avatar
    part = avatar.part("garment")
    motion = _motion(video).numpy()
    frames = list(posed_frames(avatar, motion, frame_ids=np.arange(motion.shape[0]), fps=30.0))
    ids = part.gaussian_ids
    garment_means = [posed["means"][ids] for posed in frames]
    assert (garment_means[1] - garment_means[4]).norm(dim=1).max() > 1e-3  # the cloth moves between samples
    # and it is not what skinning alone gives
    avatar.parts.pop("garment")
    try:
        skinned = avatar.pose(torch.as_tensor(motion[4]))["means"][ids]
    finally:
        avatar.add_part(part)
    assert (skinned - garment_means[4]).norm(dim=1).max() > 1e-3


def test_bad_garment_options_are_one_line_errors(capsys, tmp_path):
    from warpavatar.cli import fit as fit_cli

    demo = str(data.demo_subject_path() / "train")
    for flags, message in ((["--garment-attach", "Nowhere"], "no such joint"),
                           (["--garment-from", "-3"], "--garment-from"),
                           (["--garment-window", "0"], "--garment-window")):
        status = fit_cli.main([demo, "-o", str(tmp_path / "out"), "--preset", "quick", "--iterations", "2",
                               "--no-progress", "--overwrite", "--garment", "auto", *flags])
        error = capsys.readouterr().err.strip()
        assert status == 2 and message in error and "\n" not in error, error


def test_rollouts_run_the_fused_frame_and_match_the_op_by_op_one(forced, video, monkeypatch):
    from warpavatar._src.cloth_frame import ClothFrame
    from warpavatar.sim import ClothModel

    part = forced[0].avatar.part("garment")
    motion = _motion(video)
    bones = torch.stack([forced[0].avatar.pose_bones(b) for b in motion])
    intervals = frame_intervals(range(motion.shape[0]), 30.0).tolist()
    runs = []
    original = ClothFrame.run
    monkeypatch.setattr(ClothFrame, "run", lambda self, *a, **k: runs.append(1) or original(self, *a, **k))
    fused, fused_velocities = part.rollout(bones, intervals)
    assert len(runs) >= motion.shape[0] - 1  # the settling frames and every frame of the motion, fused
    monkeypatch.setattr(ClothModel, "_needs_gradient", lambda self, *args: True)  # everything op by op
    reference, reference_velocities = part.rollout(bones, intervals)
    # float32 sums in another order (tests/test_cloth_frame.py), carried through the settling frames (up to 300)
    # and the motion: measured 8e-6 m (7.6e-6 of it after settling) and 1.5e-5 m/s on CPU; allowed: 5e-5 m and
    # 2e-4 m/s
    assert (fused - reference).abs().max() < 5e-5
    assert (fused_velocities - reference_velocities).abs().max() < 2e-4
    assert (fused[-1] - fused[0]).abs().max() > 1e-3  # the motion moved the cloth


def test_detection_rejects_a_blend_between_the_shins_that_does_not_reach_the_hips():
    """A fitted robot's field blended its two shins at shin height, far below the root it would hang from: cloth
    hangs from its attachment, so a garment reaches up to it (rule 7); the skirt, which does, is still found."""
    generator = torch.Generator().manual_seed(8)
    means, weights = _body(generator, skirt=False)
    # a robot's legs: the shins' shells end well below the knees (a gap, as between a robot's plates)
    keep = ~(((weights[:, 4] > 0.5) | (weights[:, 5] > 0.5)) & (means[:, 2] > 0.3))
    means, weights = means[keep], weights[keep]
    # a patch between the shins (y = +-0.1, radius 0.05), blended half and half, joined to nothing above it
    patch = torch.stack([0.04 * torch.randn(600, generator=generator),
                         0.02 * torch.randn(600, generator=generator),
                         0.05 + 0.2 * torch.rand(600, generator=generator)], dim=1)
    patch_weights = torch.zeros(patch.shape[0], 6)
    patch_weights[:, 4], patch_weights[:, 5] = 0.5, 0.5
    means, weights = torch.cat([means, patch]), torch.cat([weights, patch_weights])
    shin_blend = detect_garments(means, weights, PARENTS, _walk(), heads=HEADS, tails=TAILS, up=UP, reach=0.99)
    assert shin_blend and all(float(means[r.gaussian_ids, 2].max()) < 0.6 for r in shin_blend), \
        "without rule 7 the shin blend must be found, hanging from the pelvis"
    assert detect_garments(means, weights, PARENTS, _walk(), heads=HEADS, tails=TAILS, up=UP) == []
    skirt, skirt_weights, strip, panel = _panelled_skirt(torch.Generator().manual_seed(8))
    found = detect_garments(skirt, skirt_weights, PARENTS, _walk(), heads=HEADS, tails=TAILS, up=UP)
    assert len(found) == 1 and found[0].joint == 0
    with pytest.raises(ValueError, match="reach"):
        detect_garments(means, weights, PARENTS, _walk(), heads=HEADS, tails=TAILS, up=UP, reach=1.5)


def test_grown_regions_merge_only_with_those_they_overlap():
    """Rule 6's merge of seed regions that grew into each other (it once compared mask tensors with ``==``)."""
    from warpavatar.extensions.garment_detection import _merge_overlapping

    def mask(*ids):
        m = torch.zeros(12, dtype=torch.bool)
        m[list(ids)] = True
        return m

    grown = [(mask(0, 1), 1, 2, 3), (mask(3, 4, 5, 6), 4, 5, 6), (mask(8), 7, 8, 9)]
    merged = _merge_overlapping(grown, (mask(6, 7, 8), 10, 11, 12))  # overlaps the second and the third
    assert len(merged) == 2
    assert torch.equal(merged[0][0], mask(0, 1)) and merged[0][1:] == (1, 2, 3)
    assert torch.equal(merged[1][0], mask(3, 4, 5, 6, 7, 8)) and merged[1][1:] == (4, 5, 6)  # the largest part's joints
    alone = _merge_overlapping(merged, (mask(10, 11), 0, 1, 2))
    assert len(alone) == 3 and alone[-1][1:] == (0, 1, 2)


def test_detection_tries_again_while_none_is_found_until_its_last_step(video, tmp_path, monkeypatch):
    """No garment at --garment-from: detection runs again every --garment-retry-every steps up to --garment-until
    (the field keeps training), and stops at the first garment or the last attempt; it resumes on schedule."""
    import warpavatar.extensions.garment as garment_module

    real = garment_module.detect_garments
    attempts = []

    def detect_on_the_third_attempt(*args, **kwargs):
        attempts.append(len(attempts))
        return real(*args, **kwargs) if len(attempts) >= 3 else []

    monkeypatch.setattr(garment_module, "detect_garments", detect_on_the_third_attempt)
    config = _tiny(garment="auto", garment_attach=video.skeleton.names[0], garment_from=6, garment_retry_every=4,
                   garment_until=20, **{k: v for k, v in FORCED.items() if k != "garment_refresh_every"},
                   garment_refresh_every=50)
    trainer = Trainer(video, config, tmp_path / "retry")
    trainer.fit(progress=False)
    log = [json.loads(line) for line in (tmp_path / "retry" / "train_log.jsonl").read_text().splitlines()]
    found = [(entry["step"], entry["garment"]) for entry in log if "garment" in entry]
    assert [step for step, _ in found] == [6, 10, 14] and len(attempts) == 3
    assert found[0][1] == found[1][1] == "none" and isinstance(found[2][1], dict)
    assert trainer.avatar.part("garment") is not None

    # never found: attempts at 6, 10, 14, 18 (not 22 > --garment-until), then none is final
    attempts.clear()
    monkeypatch.setattr(garment_module, "detect_garments", lambda *args, **kwargs: attempts.append(0) or [])
    never = Trainer(video, config, tmp_path / "never")
    never.fit(progress=False)
    assert len(attempts) == 4 and never.extension("garment").decided
    assert never.extension("garment").summary_lines() == [
        f"garment: none detected among {never.extension('garment').report['gaussians']} Gaussians"]
    # one attempt only
    attempts.clear()
    once = Trainer(video, dataclasses.replace(config, extensions={
        **config.extensions, "garment": dataclasses.replace(config.extensions["garment"], garment_retry_every=0)}),
        tmp_path / "once")
    once.fit(progress=False)
    assert len(attempts) == 1

    # interrupted between attempts: the resumed fit keeps the schedule
    attempts.clear()
    parts = Trainer(video, config, tmp_path / "parts")
    parts.fit(progress=False, stop_at=12)
    assert len(attempts) == 2
    resumed = Trainer(video, config, tmp_path / "parts")
    resumed.fit(resume=True, progress=False)
    assert len(attempts) == 4


def test_detection_retry_options_are_checked():
    for name in ("garment_retry_every", "garment_until"):
        with pytest.raises(ValueError, match=name.replace("_", "-")):
            _tiny(garment="auto", **{name: -1})


def test_a_region_the_avatar_draws_as_well_as_the_rest_is_no_garment(video, tmp_path, monkeypatch):
    """Rule 8: a region the rules find counts only when its pixels' image error exceeds the rest's by
    --garment-residual. The measure responds to a region drawn wrong (its colours inverted), and detection keeps
    or rejects the same region on it (logged with its excess)."""
    import warpavatar.extensions.garment as garment_module
    from warpavatar.extensions.garment_detection import GarmentRegion

    trainer = Trainer(video, _tiny(garment="auto", garment_from=1000, **FORCED), tmp_path / "rule8")
    trainer.fit(progress=False)
    extension = trainer.extension("garment")
    grid = trainer.skinning.field.grid_weights().detach()
    means = trainer.gaussians.means.detach()
    up = torch.as_tensor(video.skeleton.up, dtype=torch.float32)
    height = means @ up
    ids = torch.nonzero(height < height.median()).squeeze(1)  # the lower half: legs, a region of the body
    fitted = extension.residual_excess(ids, grid)
    assert abs(fitted) < 0.05, fitted
    with torch.no_grad():
        trainer.gaussians.sh_dc[ids] = -trainer.gaussians.sh_dc[ids] - 1.0  # drawn wrong: colours inverted
    wrong = extension.residual_excess(ids, grid)
    assert wrong > fitted + 0.05, (fitted, wrong)

    monkeypatch.setattr(garment_module, "detect_garments", lambda *args, **kwargs: [GarmentRegion(ids, 0, (0, 0))])
    default = extension.options
    # under a threshold above its excess: rejected, and the log says why
    extension.options = dataclasses.replace(default, garment_residual=wrong + 0.01)
    extension.detect(grid)
    assert extension.part is None and extension.report["garments"] == 0
    entry = [json.loads(line) for line in (tmp_path / "rule8" / "train_log.jsonl").read_text().splitlines()][-1]
    assert entry["garment"] == "none" and entry["rejected"][0]["gaussians"] == ids.numel()
    assert entry["rejected"][0]["residual_excess"] == pytest.approx(wrong, abs=1e-3)
    # under the default threshold: kept
    extension.options = default
    extension.detect(grid)
    assert extension.part is not None and extension.report["residual_excess"] == pytest.approx(wrong, abs=1e-3)
    with pytest.raises(ValueError, match="garment-residual"):
        _tiny(garment="auto", garment_residual=1.0)
