"""The garment's learned rest shape: its gradient path through a simulated window, its recovery from rollouts of a
wider true shape, its penalties, files and options (issue #17, item 4)."""

import copy
import math

import pytest
import torch

from warpavatar import ops
from warpavatar._torch_impl import cloth as reference_cloth
from warpavatar._torch_impl import collision as reference_collision
from warpavatar._torch_impl import skinning as reference_skinning
from warpavatar._torch_impl import splat as reference_splat
from warpavatar._torch_impl import springs as reference_springs
from warpavatar.extensions.garment import GarmentPart
from warpavatar.sim import Capsules, ClothModel, ClothState, cloth_graph, nearest_nodes, ride_on_nodes

def host_window(part: GarmentPart, cache, bones, seconds, index: int, frames: int) -> ClothState:
    """The reference of a training window (:meth:`GarmentExtension.step_input` does it as device work): frame
    ``index`` simulated with gradients over the ``frames`` frames before it, from ``skinned_s(P) + d_s`` at frame
    ``s = max(0, index - frames)`` (the cached displacement carried by the current rest shape), host-indexed, each
    simulated frame's displacement and velocity written back into ``cache`` = (displacements, velocities) [T,M,3]."""
    displacements, velocities = cache
    start = max(0, index - frames)
    state = ClothState(part.skinned_rest(bones[start]) + displacements[start], velocities[start].clone())
    for frame in range(start + 1, index + 1):
        state = part.step(state, bones[frame - 1], bones[frame], seconds[frame])
        with torch.no_grad():
            displacements[frame] = state.positions - part.skinned_rest(bones[frame])
            velocities[frame] = state.velocities
    return state


RING = 8  # nodes per ring
DEPTHS = (0.0, 0.05, 0.10, 0.15)  # the rings' depths below the top ring [m]
TUBE_RADIUS = 0.1
FLARE = 0.8  # the true cone's radius grows by this much per metre of depth


def _rings(flare: float, device) -> torch.Tensor:
    """Nodes ``[RING * len(DEPTHS), 3]`` of a cone hung from a ring of radius TUBE_RADIUS at z = 0 (flare 0: a
    tube); each ring is turned by half a node spacing from the one above, as woven cloth would not be."""
    points = []
    for ring, depth in enumerate(DEPTHS):
        angle = 2 * math.pi * (torch.arange(RING) + 0.5 * (ring % 2)) / RING
        radius = TUBE_RADIUS + flare * depth
        points.append(torch.stack([radius * torch.cos(angle), radius * torch.sin(angle),
                                   torch.full((RING,), -depth)], dim=1))
    return torch.cat(points).to(device)


def _part(device, *, rest_bound=0.2, flare=0.0, strain_limit=0.0) -> GarmentPart:
    """A tiny garment: a tube (or a cone) hung by its top ring from a one-joint body with a thin capsule inside."""
    nodes = _rings(flare, device)
    capsules = Capsules(torch.tensor([[0.0, 0.0, 0.05]], device=device),
                        torch.tensor([[0.0, 0.0, -0.3]], device=device), torch.tensor([0.02], device=device))
    return GarmentPart(torch.arange(0, device=device), nodes, torch.ones(nodes.shape[0], 1, device=device),
                       torch.arange(RING, device=device), joint=0, capsules=capsules,
                       capsule_ids=torch.tensor([0], device=device), voxel_size=0.05, max_substep=1.0 / 120.0,
                       settle_frames=60, rest_bound=rest_bound, strain_limit=strain_limit,
                       graph=cloth_graph(nodes, neighbours=6, bend_per_node=4))


def _set_rest_shape(cloth: ClothModel, positions: torch.Tensor) -> None:
    """Make the learned rest shape ``positions`` (inverting ``o = b z / sqrt(1 + |z|^2)``)."""
    offset = positions - cloth.initial_rest_positions
    with torch.no_grad():
        cloth.rest_offset_logit.copy_(offset / (cloth.rest_offset_bound**2 - (offset * offset).sum(1, keepdim=True))
                                      .sqrt())
    torch.testing.assert_close(cloth.rest_positions(), positions.to(cloth.rest_positions().dtype), rtol=0, atol=1e-6)


def _sway(frame_count: int, device, *, amplitude=0.06) -> torch.Tensor:
    """The body's one joint translates side to side and turns about the vertical: ``[T, 1, 4, 4]``."""
    bones = torch.eye(4).repeat(frame_count, 1, 1, 1)
    for frame in range(frame_count):
        phase = 2 * math.pi * frame / frame_count
        turn = 0.3 * math.sin(phase)
        bones[frame, 0, :2, :2] = torch.tensor([[math.cos(turn), -math.sin(turn)], [math.sin(turn), math.cos(turn)]])
        bones[frame, 0, 0, 3] = amplitude * math.sin(phase)
    return bones.to(device)


FRAMES, SECONDS = 8, 1.0 / 30.0


def _cache(part, bones):
    positions, velocities = part.rollout(bones, [SECONDS] * bones.shape[0])
    return part.displacements(bones, positions), velocities


def test_rest_shape_moves_free_nodes_within_its_bound_and_the_rest_lengths_follow(device):
    part = _part(device, rest_bound=0.05)
    cloth = part.cloth
    with torch.no_grad():
        cloth.rest_offset_logit.normal_(0.0, 30.0)
    offset = (cloth.rest_positions() - part.nodes).norm(dim=1)
    offset = offset.detach()
    assert float(offset[RING:].max()) < 0.05 and float(offset[RING:].min()) > 0.03  # near, never past, the bound
    assert float(offset[:RING].abs().max()) == 0.0  # the top ring is held: it keeps its place
    rest = cloth.rest_positions()
    expected = (rest[cloth.pairs[:, 0]] - rest[cloth.pairs[:, 1]]).norm(dim=1)
    torch.testing.assert_close(cloth.rest_shape_lengths(), expected)
    torch.testing.assert_close(cloth.rest_lengths(), expected * 1.0)  # the length factors start at 1
    assert float(cloth.rest_shape_roughness().detach()) > 0.1 and float(cloth.rest_shape_collapse().detach()) > 0.0
    # a fixed rest shape (bound 0) has no parameter for it, and no penalty
    fixed = _part(device, rest_bound=0.0).cloth
    assert fixed.rest_offset_logit is None and "rest_offset_logit" not in dict(fixed.named_parameters())
    assert torch.equal(fixed.rest_positions(), fixed.initial_rest_positions)
    assert float(fixed.rest_shape_roughness()) == 0.0 and float(fixed.rest_shape_collapse()) == 0.0


def test_the_fused_frame_follows_a_changed_rest_shape(device):
    part = _part(device)
    cloth = part.cloth
    bones = _sway(3, device)
    state = part.settled(bones[0], SECONDS)
    targets = part.attachment_targets(bones[1])
    with torch.no_grad():
        before = cloth.step(state, targets, SECONDS)  # fused: caches its coefficients
        cloth.rest_offset_logit.add_(0.5)  # in place, as an optimizer step does
        fused = cloth.step(state, targets, SECONDS)
        by_ops = cloth.step(state, targets, SECONDS, fused=False)
    assert (fused.positions - before.positions).abs().max() > 1e-4, "the longer springs move the cloth"
    torch.testing.assert_close(fused.positions, by_ops.positions, rtol=0, atol=1e-5)


def _camera(device, width=20, height=16):
    """A camera 1 m in front of the tube (looking along +y), its axis at the tube's middle height."""
    K = torch.tensor([[40.0, 0.0, (width - 1) / 2], [0.0, 40.0, (height - 1) / 2], [0.0, 0.0, 1.0]], device=device)
    world_to_camera = torch.tensor([[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, -1.0, -0.08], [0.0, 1.0, 0.0, 1.0],
                                    [0.0, 0.0, 0.0, 1.0]], device=device)
    return K, world_to_camera, width, height


def _rendered_loss(part, cache, bones, cotangent, gaussians, rasterize):
    """A window of 2 frames to frame 5, the garment Gaussians riding on its nodes, rendered and weighted."""
    state = host_window(part, tuple(t.clone() for t in cache), bones, [SECONDS] * FRAMES, 5, 2)
    means, quats = ride_on_nodes(state.positions, part.node_quats(state.positions, bones[5]), gaussians["anchor"],
                                 gaussians["offset"], gaussians["quats"])
    image, alpha, _ = rasterize(means, quats, gaussians["scales"], gaussians["opacities"], gaussians["colors"],
                                *_camera(means.device))
    return (image * cotangent).sum() + (alpha * cotangent[..., 0]).sum()


def test_a_rendered_loss_reaches_the_rest_shape_through_a_window(device, monkeypatch):
    """Analytic: the Warp ops in float32 through torch autograd. Numeric: central differences of the same
    window and render with the ops' float64 torch references; both start from the same cached rollout."""
    generator = torch.Generator().manual_seed(3)
    part = _part(device)
    with torch.no_grad():  # a rest shape away from the initial one, where every term of the bound is alive
        part.cloth.rest_offset_logit.copy_(0.3 * torch.randn(part.node_count, 3, generator=generator))
    bones = _sway(FRAMES, device)
    cache = _cache(part, bones)
    count = 3 * part.node_count
    means = part.nodes.repeat(3, 1) + 0.01 * torch.randn(count, 3, generator=generator).to(device)
    gaussians = dict(anchor=nearest_nodes(means, part.nodes), scales=torch.full((count, 3), 0.04, device=device),
                     quats=torch.nn.functional.normalize(torch.randn(count, 4, generator=generator), dim=1).to(device),
                     opacities=torch.full((count,), 0.5, device=device),
                     colors=torch.rand(count, 3, generator=generator).to(device))
    gaussians["offset"] = means - part.nodes[gaussians["anchor"]]
    cotangent = torch.randn(16, 20, 3, generator=generator).to(device)
    loss = _rendered_loss(part, cache, bones, cotangent, gaussians, ops.rasterize_gaussians)
    (analytic,) = torch.autograd.grad(loss, [part.cloth.rest_offset_logit])
    assert float(analytic[RING:].abs().max()) > 1e-3, "the free nodes' rest positions get a gradient"
    assert float(analytic[:RING].abs().max()) == 0.0, "the held ring's do not (they never move)"

    monkeypatch.setattr(ops, "spring_step", reference_springs.spring_step)
    monkeypatch.setattr(ops, "cloth_edge_terms", reference_cloth.cloth_edge_terms)
    monkeypatch.setattr(ops, "push_out_of_capsules", reference_collision.push_out_of_capsules)
    monkeypatch.setattr(ops, "lbs", reference_skinning.lbs)
    part64 = copy.deepcopy(part).to("cpu", torch.float64)
    logit = part64.cloth.rest_offset_logit
    inputs = [tuple(t.detach().cpu().double() for t in cache), bones.cpu().double(), cotangent.cpu().double(),
              {k: (v.cpu().double() if v.is_floating_point() else v.cpu()) for k, v in gaussians.items()},
              reference_splat.rasterize_gaussians]
    (reference,) = torch.autograd.grad(_rendered_loss(part64, *inputs), [logit])
    directions = torch.randn(4, *logit.shape, generator=generator, dtype=torch.float64)
    epsilon = 1e-6
    for direction in directions:
        with torch.no_grad():
            original = logit.clone()
            logit.copy_(original + epsilon * direction)
            plus = _rendered_loss(part64, *inputs)
            logit.copy_(original - epsilon * direction)
            minus = _rendered_loss(part64, *inputs)
            logit.copy_(original)
        numeric = float((plus - minus) / (2 * epsilon))
        assert abs(numeric) > 1e-3
        # the float64 references' own autograd agrees tightly; the Warp float32 one within float32 round-off
        assert abs(float((reference * direction).sum()) - numeric) < 1e-6 * abs(numeric) + 1e-8
        error = abs(float((analytic.double().cpu() * direction).sum()) - numeric) / abs(numeric)
        assert error < 2e-3, error


def _absolute_window(part, cache, bones, index, frames):
    """The window as it was before the rest shape was learned: it starts at the cached node positions."""
    positions, velocities = cache
    start = max(0, index - frames)
    state = ClothState(positions[start].clone(), velocities[start].clone())
    for frame in range(start + 1, index + 1):
        state = part.step(state, bones[frame - 1], bones[frame], SECONDS)
        positions[frame], velocities[frame] = state.positions.detach(), state.velocities.detach()
    return state


def _fit_rest_shape(part, targets, bones, *, steps, refresh_every, window, lr, carried=True):
    """Fit the rest shape alone to target node trajectories [T,M,3] the way the garment extension trains: windows
    from a cache of displacements (``carried``; else of positions), refreshed by rollouts."""
    cloth = part.cloth
    optimizer = torch.optim.Adam([cloth.rest_offset_logit], lr=lr)
    generator = torch.Generator().manual_seed(0)
    for step in range(steps):
        if step % refresh_every == 0:
            cache = _cache(part, bones) if carried else part.rollout(bones, [SECONDS] * bones.shape[0])
        index = int(torch.randint(0, bones.shape[0], (1,), generator=generator))
        if carried:
            state = host_window(part, cache, bones, [SECONDS] * bones.shape[0], index, window)
        else:
            state = _absolute_window(part, cache, bones, index, window)
        loss = (state.positions - targets[index]).square().sum(dim=1).mean()
        loss = loss + 1e-4 * cloth.rest_shape_roughness() + 1e-2 * cloth.rest_shape_collapse()
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()


def test_fitting_recovers_a_wider_rest_shape_from_its_rollout(device):
    """The truth: a cone flaring out from its ring; the start: a tube. Target trajectories are the cone's
    rollout under the swaying body; fitting the tube's rest shape to them widens it into the cone."""
    bones = _sway(FRAMES, device)
    truth = _rings(FLARE, device)
    true_part = _part(device)
    _set_rest_shape(true_part.cloth, truth)
    targets, _ = true_part.rollout(bones, [SECONDS] * FRAMES)
    part = _part(device)
    assert float((targets[:, RING:, :2].norm(dim=2) - TUBE_RADIUS).mean()) > 0.03, "the cone hangs wide"

    def error():
        return float((part.cloth.rest_positions().detach() - truth)[RING:].norm(dim=1).mean())

    before = error()
    _fit_rest_shape(part, targets, bones, steps=80, refresh_every=10, window=1, lr=0.05)
    after = error()
    print(f"rest shape error: {before:.4f} -> {after:.4f} m")
    assert after < 0.25 * before, (before, after)


def test_windows_from_absolute_cached_states_recover_less(device):
    """What the displacement cache buys: windows that start from the cached node positions themselves (the rest
    shape reaches them only through one frame's spring forces) recover the same cone less well (measured on CPU,
    80 steps, window 1: rest-shape error 0.034 m against 0.012 m)."""
    bones = _sway(FRAMES, device)
    truth = _rings(FLARE, device)
    true_part = _part(device)
    _set_rest_shape(true_part.cloth, truth)
    targets, _ = true_part.rollout(bones, [SECONDS] * FRAMES)
    errors = []
    for carried in (True, False):
        part = _part(device)
        _fit_rest_shape(part, targets, bones, steps=80, refresh_every=10, window=1, lr=0.05, carried=carried)
        errors.append(float((part.cloth.rest_positions().detach() - truth)[RING:].norm(dim=1).mean()))
    assert errors[0] < errors[1] / 1.5, errors


def test_the_rest_shape_round_trips_through_the_part_file(device):
    part = _part(device)
    generator = torch.Generator().manual_seed(5)
    with torch.no_grad():
        part.cloth.rest_offset_logit.copy_(torch.randn(part.node_count, 3, generator=generator))
    loaded = GarmentPart.from_file_state(part.state_for_file(), device=device)
    assert loaded.hyper["rest_bound"] == part.hyper["rest_bound"] == 0.2
    assert torch.equal(loaded.cloth.rest_positions(), part.cloth.rest_positions())
    bones = _sway(4, device)
    assert torch.equal(loaded.rollout(bones, [SECONDS] * 4)[0], part.rollout(bones, [SECONDS] * 4)[0])
    # a file written before the rest shape was learned: no bound, no initial rest positions; it loads fixed
    old = _part(device, rest_bound=0.0).state_for_file()
    old["hyper"].pop("rest_bound")
    old["state_dict"].pop("cloth.initial_rest_positions")
    legacy = GarmentPart.from_file_state(old, device=device)
    assert legacy.cloth.rest_offset_logit is None and torch.equal(legacy.cloth.rest_positions(), legacy.nodes)


def test_the_strain_limit_round_trips_and_holds_the_swaying_cloth(device):
    bones = _sway(12, device, amplitude=0.2)
    stretch = {}
    for limit in (0.0, 1.05):
        part = _part(device, strain_limit=limit)
        loaded = GarmentPart.from_file_state(part.state_for_file(), device=device)
        assert loaded.hyper["strain_limit"] == limit and loaded.cloth.strain_iterations == (8 if limit else 0)
        positions = loaded.rollout(bones, [SECONDS] * 12)[0]
        assert torch.equal(positions, part.rollout(bones, [SECONDS] * 12)[0])
        pairs = part.cloth.pairs[: part.cloth.stretch_count]
        lengths = (positions[:, pairs[:, 0]] - positions[:, pairs[:, 1]]).norm(dim=-1)
        stretch[limit] = float((lengths / part.cloth.rest_lengths().detach()[: part.cloth.stretch_count]).max())
    assert stretch[0.0] > 2.0 and stretch[1.05] < 1.25, stretch  # (8 Jacobi passes a substep: near the limit)
    old = _part(device).state_for_file()  # a file written before strain limiting: none
    old["hyper"].pop("strain_limit")
    assert GarmentPart.from_file_state(old, device=device).cloth.strain_iterations == 0


def test_bad_rest_shape_options_are_one_line_errors(capsys, tmp_path):
    from warpavatar import data
    from warpavatar.cli import fit as fit_cli

    demo = str(data.demo_subject_path() / "train")
    for flags, message in ((["--garment-rest-bound", "-0.1"], "--garment-rest-bound must be a number >= 0"),
                           (["--lr-garment-rest", "0"], "--lr-garment-rest must be > 0"),
                           (["--lambda-garment-rest-smooth", "-2"], "--lambda-garment-rest-smooth"),
                           (["--lambda-garment-rest-collapse", "-1"], "--lambda-garment-rest-collapse"),
                           (["--garment-strain-limit", "1"], "--garment-strain-limit must be 0 (off) or > 1"),
                           (["--garment-strain-limit", "-2"], "--garment-strain-limit must be 0 (off) or > 1")):
        status = fit_cli.main([demo, "-o", str(tmp_path / "out"), "--preset", "quick", "--iterations", "2",
                               "--no-progress", "--overwrite", "--garment", "auto", *flags])
        error = capsys.readouterr().err.strip()
        assert status == 2 and message in error and "\n" not in error, error
    with pytest.raises(ValueError, match="rest_offset_bound must be >= 0"):
        ClothModel(_rings(0.0, "cpu"), cloth_graph(_rings(0.0, "cpu")), torch.arange(RING), rest_offset_bound=-1.0)


def test_a_checkpoint_that_cached_positions_resumes_with_displacements(device):
    """Checkpoints written before the cache held displacements hold the rollout's node positions: loading one
    converts them, so the next window starts where that rollout left the cloth. Their cloth optimizer held the
    rest offsets as a second parameter group: its moments go to the rest offsets' own optimizer."""
    from types import SimpleNamespace

    from warpavatar.extensions.garment import GarmentExtension, GarmentOptions

    part = _part(device)
    with torch.no_grad():
        part.cloth.rest_offset_logit.fill_(0.4)
    bones = _sway(FRAMES, device)
    positions, velocities = part.rollout(bones, [SECONDS] * FRAMES)
    fit = SimpleNamespace(device=device, avatar=SimpleNamespace(add_part=lambda p: p, pose_bones=lambda b: b),
                          frames=SimpleNamespace(bone_transforms=bones, seconds=[SECONDS] * FRAMES,
                                                 skeleton=SimpleNamespace(names=["root"])))
    extension = GarmentExtension(GarmentOptions(garment="auto"), fit)  # (load_state_dict builds the rest)
    extension.attach()
    cloth = part.cloth
    physics = [p for name, p in cloth.named_parameters() if name != "rest_offset_logit"]
    grouped = torch.optim.Adam([{"params": physics}, {"params": [cloth.rest_offset_logit], "lr": 0.005}], lr=0.02)
    (host_window(part, (positions * 0, velocities.clone()), bones, [SECONDS] * FRAMES, 3, 2).positions.square().sum()
     + cloth.rest_shape_roughness()).backward()
    grouped.step()
    old = {"decided": True, "report": {}, "refreshed": 0, "part": part.state_for_file(),
           "optimizer": grouped.state_dict(), "cache": [positions.cpu(), velocities.cpu()]}
    extension.load_state_dict(old)
    displacements, _ = extension.cache
    torch.testing.assert_close(displacements, part.displacements(bones, positions))
    state = host_window(extension.part, extension.cache, bones, [SECONDS] * FRAMES, 3, 0)
    torch.testing.assert_close(state.positions, positions[3], rtol=0, atol=1e-6)
    loaded = extension.part.cloth
    loaded_physics = [p for name, p in loaded.named_parameters() if name != "rest_offset_logit"]
    for group, optimizer, parameters, theirs in ((0, extension.optimizer, loaded_physics, physics),
                                                 (1, extension.rest_optimizer, [loaded.rest_offset_logit],
                                                  [cloth.rest_offset_logit])):
        assert optimizer.param_groups[0]["lr"] == grouped.param_groups[group]["lr"]
        for ours, their in zip(parameters, theirs):
            torch.testing.assert_close(optimizer.state[ours]["exp_avg"], grouped.state[their]["exp_avg"])
            step = optimizer.state[ours]["step"]  # torch's count (a CPU tensor) on the device, as the kernel wants it
            assert step.dtype == torch.float32 and step.device == ours.device and float(step) == 1.0
    assert extension.rest_optimizer.state[loaded.rest_offset_logit]["exp_avg"].abs().sum() > 0
