"""The MLPs of a training step and of playback, computed with less work (issue #18): the pose correction's first
layer split into a per-Gaussian product and a per-frame bias, the encoding of a frozen avatar's canonical centres
cached for playback, the skinning field's inputs gathered once per choice of grid points and its chosen points
written into the kept grid in place, and the ``--matmul-precision`` choice reaching the MLPs. Each is held to the
plain computation on random inputs."""

from __future__ import annotations

import copy

import pytest
import torch

from warpavatar._src import precision
from warpavatar.extensions.pose_correction import PoseCorrection, relative_rotations_6d
from warpavatar.geometry import quat_to_matrix

PARENTS = torch.tensor([-1, 0, 1, 2, 1, 4, 0, 6])


def _random_poses(count: int, generator: torch.Generator) -> torch.Tensor:
    """[count, J, 4, 4] rigid transforms with random rotations and translations."""
    quats = torch.randn(count, len(PARENTS), 4, generator=generator)
    poses = torch.eye(4).repeat(count, len(PARENTS), 1, 1)
    poses[..., :3, :3] = quat_to_matrix(quats / quats.norm(dim=-1, keepdim=True))
    poses[..., :3, 3] = 0.3 * torch.randn(count, len(PARENTS), 3, generator=generator)
    return poses


def _random_correction(device, *, frame_count: int, seed: int) -> PoseCorrection:
    part = PoseCorrection(torch.tensor([-0.5, -0.3, 0.0]), torch.tensor([0.5, 0.4, 1.8]), PARENTS, hidden=24,
                          layers=3, frame_count=frame_count, code_width=5)
    generator = torch.Generator().manual_seed(seed)
    with torch.no_grad():  # not the identity: random weights everywhere, the zero-initialized head included
        for parameter in part.parameters():
            parameter.copy_(0.3 * torch.randn(parameter.shape, generator=generator))
    return part.to(device)


def _concatenated_outputs(part: PoseCorrection, means, bone_transforms, code):
    """The network as it was first written: the pose (and code) repeated for every Gaussian beside its
    encoding, one [N, E + pose + code] input to the trunk."""
    pose = part.pose_encoder(relative_rotations_6d(bone_transforms, part.parents))
    if code is not None:
        pose = torch.cat([pose, code])
    features = torch.cat([part._encode(means.detach()), pose.expand(means.shape[0], -1)], dim=-1)
    return part.head(part.trunk(features))


@pytest.mark.parametrize("frame_count", [0, 4])
def test_split_first_layer_matches_the_concatenated_layer(device, frame_count):
    part = _random_correction(device, frame_count=frame_count, seed=frame_count + 1)
    generator = torch.Generator().manual_seed(11)
    means = (torch.rand(257, 3, generator=generator) * torch.tensor([1.2, 0.9, 2.0]) - torch.tensor([0.6, 0.35, 0.1]))
    means = means.to(device).requires_grad_()
    poses = _random_poses(2, generator).to(device)
    cotangent = torch.randn(257, 9, generator=generator).to(device)
    codes = [None] if not frame_count else [part.frame_codes[2], torch.zeros_like(part.frame_codes[0])]
    for pose in poses:
        for code in codes:
            results = []
            for outputs in (part._outputs, lambda *args: _concatenated_outputs(part, *args)):
                values = outputs(means, pose, code)
                grads = torch.autograd.grad(values, list(part.parameters()), cotangent, allow_unused=True)
                results.append((values.detach(), grads))
            (ours, our_grads), (theirs, their_grads) = results
            assert theirs.abs().max() > 0.1
            torch.testing.assert_close(ours, theirs, rtol=1e-5, atol=1e-5)
            for name, a, b in zip([n for n, _ in part.named_parameters()], our_grads, their_grads):
                if b is None:  # the frame codes without a code
                    assert a is None or not a.any(), name
                    continue
                assert b.abs().max() > 0 or name == "frame_codes", name
                # sums over the Gaussians: float32 rounding relative to the largest entry
                torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-6 * float(b.abs().max()), msg=name)


def test_split_first_layer_keeps_the_parameters_and_files():
    part = _random_correction("cpu", frame_count=3, seed=5)
    assert part.position_width == part.trunk[0].in_features - 32 - 5  # the pose's 32 and the code's 5 follow
    again = PoseCorrection.from_file_state(part.state_for_file())
    assert again.state_dict().keys() == part.state_dict().keys()
    means = torch.rand(40, 3)
    pose = _random_poses(1, torch.Generator().manual_seed(2))[0]
    with torch.no_grad():
        torch.testing.assert_close(again(means, torch.randn(40, 4), torch.rand(40, 3) + 0.1, pose)[0],
                                   part(means, torch.randn(40, 4), torch.rand(40, 3) + 0.1, pose)[0])


# ------------------------------------------------------------------------------------------------ playback
@pytest.fixture(scope="module")
def demo_video():
    from warpavatar import data

    return data.load_video_folder(data.demo_subject_path() / "train", scale=0.25)


def _frames(avatar, video, frames, *, device, player=None):
    """Images of training frames ``frames`` through their cameras: the player's, or the avatar's own render."""
    images = []
    for frame in frames:
        bones = torch.as_tensor(video.bone_transforms[frame], dtype=torch.float32, device=device)
        if player is None:
            with torch.no_grad():
                images.append(avatar.render(video.cameras[frame], bones)[0].clone())
        else:
            images.append(player.render(bones, camera=video.cameras[frame])[0].clone())
    return images


def _uncached(avatar):
    """A copy of the avatar without the pose correction's playback cache (nor the counting of encodings)."""
    avatar = copy.deepcopy(avatar)
    part = avatar.parts["pose_correction"]
    part.__dict__.pop("_encode", None)
    part._playback = None
    return avatar


def _assert_same_images(ours, theirs, device):
    for a, b in zip(ours, theirs):
        assert b.max() > 0.2
        # the player applies the correction in one kernel (tests/test_playback_cache.py), which rounds unlike
        # torch's ops; on CUDA atomics in the compositing may round differently too
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("cuda_graph", ["off", "on"])
def test_playback_cache_draws_what_uncached_frames_draw(demo_video, device, cuda_graph):
    from tests.test_step_graph import _playback_avatar
    from warpavatar.model.playback import Player

    if cuda_graph == "on" and not device.startswith("cuda"):
        pytest.skip("CUDA graphs need a CUDA device")
    avatar = _playback_avatar(demo_video).to(device)
    part = avatar.parts["pose_correction"]
    frames = (0, 3, 5, 2, 4)
    uncached = _frames(_uncached(avatar), demo_video, frames, device=device)
    player = Player(avatar, demo_video.cameras[0], cuda_graph=cuda_graph, check_every=2, matmul_precision="fp32")
    encodings = []
    original_encode = part._encode
    part._encode = lambda points: encodings.append(points.shape[0]) or original_encode(points)
    _assert_same_images(_frames(avatar, demo_video, frames, device=device, player=player), uncached, device)
    assert part._playback is not None and part._playback[1].shape == (avatar.gaussians.count, part.position_width)
    assert encodings == [], "the frames encoded the means again"

    # the avatar changes in place: the frames follow, the encoding is made again only for new means (in the
    # same storage, which a captured frame reads), and a changed field gives a new grid
    storage = part._playback[1].data_ptr()
    with torch.no_grad():
        part.trunk[0].weight.mul_(1.3)
        avatar.field.mlp[0].bias.add_(0.5)
    changed = _frames(avatar, demo_video, frames[:2], device=device, player=player)
    assert encodings == []
    _assert_same_images(changed, _frames(_uncached(avatar), demo_video, frames[:2], device=device), device)
    assert not any(torch.equal(a, b) for a, b in zip(changed, uncached))
    with torch.no_grad():
        avatar.gaussians.means.add_(0.01)
    moved = _frames(avatar, demo_video, frames[:3], device=device, player=player)
    assert encodings == [avatar.gaussians.count]  # once, for the new means
    assert part._playback[1].data_ptr() == storage
    _assert_same_images(moved, _frames(_uncached(avatar), demo_video, frames[:3], device=device), device)
    assert not any(torch.equal(a, b) for a, b in zip(moved, changed[:1]))
    # a state dict loaded into the part (copied in place) is a change too
    part.load_state_dict({name: value * 0.7 if name.startswith(("trunk", "head")) else value
                          for name, value in part.state_dict().items()})
    loaded = _frames(avatar, demo_video, frames[:2], device=device, player=player)
    _assert_same_images(loaded, _frames(_uncached(avatar), demo_video, frames[:2], device=device), device)
    if cuda_graph == "on":
        assert player.use_graph and player._graph is not None


def test_playback_cache_serves_only_its_means_without_gradients():
    part = _random_correction("cpu", frame_count=0, seed=3)
    means = torch.rand(30, 3)
    part.prepare_playback(means)
    with torch.no_grad():
        assert part._cached_encoding(means) is not None
        assert part._cached_encoding(means.clone()) is None  # another tensor, even with equal values
    assert part._cached_encoding(means) is None  # gradients asked for: computed anew
    with torch.no_grad():
        means.add_(0.1)  # changed in place
        assert part._cached_encoding(means) is None
        part.prepare_playback(means)
        assert torch.equal(part._cached_encoding(means), part._encode(means))


# ------------------------------------------------------------------------------------------------ the field
def test_field_inputs_gathered_once_per_choice_give_the_same_grid(device):
    from tests.test_field_cells import _field, _points, _stage

    field = _field(device, seed=4)
    stage = _stage(device, "active", field)
    for step, count, seed in ((0, 300, 1), (1, 200, 2)):  # fewer points: chosen again in the same buffers
        points = _points(count, device, seed, spread=0.9)
        stage.forget_cells()
        stage.begin_step(step, points, train_field=True)
        grid = stage.grid(step, train_field=True)
        cells = stage._encode_cells
        torch.testing.assert_close(stage._cell_encoding, field.grid_encoding[cells], rtol=0, atol=0)
        expected = field.grid_weights().reshape(field.cell_count, -1)[cells[:stage.active_cells]]
        torch.testing.assert_close(grid.reshape(field.cell_count, -1)[cells[:stage.active_cells]], expected)
        if step == 0:
            key = stage.graph_key()
        else:
            assert stage.graph_key() == key  # the kept encoding too: a captured step reads it


def test_active_points_are_written_into_the_grid_in_place_step_after_step(device):
    """The step's grid is the kept grid with the chosen points rewritten in place (no copy of the whole grid): over
    steps whose field changes, with and without the graph released after the backward, it and its gradients are
    those of evaluating every grid point."""
    from tests.test_field_cells import _field, _points, _stage

    points = _points(300, device, 5, spread=0.9)
    runs = {}
    for mode in ("all", "active"):
        field = _field(device, seed=2)
        stage = _stage(device, mode, field)
        optimizer = torch.optim.SGD(field.parameters(), lr=0.5)
        target = torch.softmax(torch.cos(points @ torch.ones(3, 6, device=device) * 3.0), -1)
        runs[mode] = []
        for step in range(3):
            stage.begin_step(step, points, train_field=True)
            grid = stage.grid(step, train_field=True)
            if mode == "active":
                assert grid.data_ptr() == stage._base.data_ptr()  # a view of the kept grid
            optimizer.zero_grad()
            ((field.weights(points, grid) - target) ** 2).sum().backward()
            runs[mode].append([p.grad.clone() for p in field.parameters()])
            optimizer.step()
            if step != 1:  # step 1 keeps its graph: the next step must not reach into it
                stage.release_graph()
    for active, whole in zip(runs["active"], runs["all"]):
        assert all(g.abs().max() > 0 for g in whole)
        for a, b in zip(active, whole):  # sums over points: float32 rounding relative to the largest entry
            torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-5 * float(b.abs().max()))


# ------------------------------------------------------------------------------------------------ precision
def _cublas_flag() -> str:
    flags = torch.backends.cuda.matmul
    return flags.fp32_precision if hasattr(flags, "fp32_precision") else str(flags.allow_tf32)


def test_matmul_precision_sets_cublas_only_inside_and_only_for_cuda():
    before = _cublas_flag()
    with precision.matmul_precision("tf32", "cuda:0"):
        assert _cublas_flag() in ("tf32", "True")
        with precision.matmul_precision("fp32", torch.device("cuda")):
            assert _cublas_flag() in ("ieee", "False")
        assert _cublas_flag() in ("tf32", "True")
    assert _cublas_flag() == before
    with precision.matmul_precision("tf32", "cpu"):
        assert _cublas_flag() == before
    with pytest.raises(RuntimeError), precision.matmul_precision("tf32", "cuda"):
        raise RuntimeError("an error inside the block")
    assert _cublas_flag() == before
    with pytest.raises(ValueError, match="matmul precision must be 'tf32' or 'fp32', got 'fp16'"):
        with precision.matmul_precision("fp16", "cpu"):
            pass


@pytest.fixture
def recorded_precisions(monkeypatch):
    """Every (precision, device type) an :func:`mlp_matmuls` or :func:`matmul_precision` block is entered with."""
    calls = []
    original = precision.matmul_precision

    def recording(choice, device):
        calls.append((choice, torch.device(device).type))
        return original(choice, device)

    monkeypatch.setattr(precision, "matmul_precision", recording)
    return calls


@pytest.mark.parametrize("choice", ["tf32", "fp32"])
def test_the_fit_and_the_player_run_their_mlps_in_the_chosen_precision(demo_video, tmp_path, recorded_precisions,
                                                                     choice, monkeypatch):
    from tests.test_step_graph import _tiny_trainer
    from warpavatar.fit import trainer as trainer_module
    from warpavatar.model import Avatar
    from warpavatar.model.playback import Player

    monkeypatch.setattr(trainer_module, "matmul_precision", precision.matmul_precision)  # the recording one
    trainer = _tiny_trainer(demo_video, tmp_path, matmul_precision=choice)
    trainer.step = 20  # the field and the pose correction train
    trainer.train_step()
    assert recorded_precisions.count((choice, "cpu")) >= 3  # the field, the correction, the backward pass
    assert all(call == (choice, "cpu") for call in recorded_precisions)
    # the avatar file keeps the choice, and a player of the loaded avatar follows it
    state = trainer.avatar.state_for_file(config=trainer.config.to_dict())
    avatar = Avatar.from_state(state)
    assert avatar.matmul_precision == choice and Avatar.from_state({**state, "config": {}}).matmul_precision == "tf32"
    bones = torch.as_tensor(demo_video.bone_transforms[1], dtype=torch.float32)
    other = "fp32" if choice == "tf32" else "tf32"
    for given, expected in ((None, choice), (other, other)):
        recorded_precisions.clear()
        with precision.mlp_precision("fp32"):  # what a caller chose around it does not matter: the player's own
            Player(avatar, demo_video.cameras[0], cuda_graph="off", matmul_precision=given).render(bones)
        assert len(recorded_precisions) >= 2 and set(recorded_precisions) == {(expected, "cpu")}
    recorded_precisions.clear()
    avatar.field.grid_weights()  # outside a fit and a player: torch's own setting, untouched
    assert recorded_precisions == []


def test_matmul_precision_option_is_checked_and_explained():
    import argparse

    from warpavatar.fit.arguments import add_config_arguments
    from warpavatar.fit.config import FitConfig

    assert FitConfig().matmul_precision == "tf32"
    assert FitConfig.from_flat({"matmul_precision": "fp32"}).matmul_precision == "fp32"
    with pytest.raises(ValueError, match="matmul_precision must be 'tf32' or 'fp32', got 'fp16'"):
        FitConfig.from_flat({"matmul_precision": "fp16"})
    parser = argparse.ArgumentParser()
    add_config_arguments(parser)
    assert parser.parse_args(["--matmul-precision", "fp32"]).matmul_precision == "fp32"
    text = " ".join(parser.format_help().split())
    assert "--matmul-precision {tf32,fp32}" in text and "(default: tf32)" in text
    assert "10-bit mantissas" in text and "no effect on a CPU" in text
