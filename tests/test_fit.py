"""End-to-end fitting on the built-in demo subject: the fit learns, resumes exactly, and its outputs load back."""

import json
import math

import numpy as np
import pytest
import torch

from warpavatar import data
from warpavatar.model import Avatar
from warpavatar.fit import preset
from warpavatar.extensions.dynamics import SecondaryDynamics
from warpavatar.evaluate import evaluate_avatar
from warpavatar.fit import Trainer, load_training_video


def _tiny_config(**overrides):
    values = dict(iterations=160, image_scale=0.5, max_train_frames=12, init_points_per_bone=30,
                  init_carve_candidates=20000, init_carve_points=800, sh_degree=1, sh_increase_every=100,
                  grid_cells=16, grid_min_cells=6, field_hidden=32, field_layers=2, field_warmup_steps=40,
                  gaussian_only_steps=80, densify_from=40, densify_until=120, densify_every=40,
                  max_gaussians=3000, checkpoint_every=1000, log_every=20, preview_frames=1,
                  pose_correction=True, pose_correction_hidden=16, secondary_motion=True,
                  secondary_from=100)
    values.update(overrides)
    return preset("quick", **values)


@pytest.fixture(scope="module")
def demo_video():
    return load_training_video(data.demo_subject_path() / "train", _tiny_config())


def test_load_training_video_reads_the_folder_at_the_configs_image_scale(demo_video):
    folder = data.demo_subject_path() / "train"
    full = data.load_video_folder(folder)
    assert (full.width, full.height, demo_video.width, demo_video.height) == (128, 128, 64, 64)
    assert demo_video.images.shape == (full.frame_count, 64, 64, 3)
    resized = data.load_video_folder(folder, scale=0.5)  # the same resize of the same frames, bit for bit
    np.testing.assert_array_equal(demo_video.images, resized.images)
    np.testing.assert_array_equal(demo_video.masks, resized.masks)
    np.testing.assert_array_equal(demo_video.cameras[0].K, resized.cameras[0].K)
    unscaled = load_training_video(folder, _tiny_config(image_scale=1.0))
    np.testing.assert_array_equal(unscaled.images, full.images)
    np.testing.assert_array_equal(unscaled.cameras[0].K, full.cameras[0].K)


def _mean_train_psnr(trainer):
    with torch.no_grad():
        values = []
        for index in range(trainer.frames.count):
            image, _, _ = trainer.avatar.render(trainer.frames.cameras[index], trainer.frames.bone_transforms[index],
                                                background=trainer.frames.background)
            gt, _ = trainer.frames.target(index)
            values.append(float(-10 * torch.log10(((image - gt) ** 2).mean())))
    return float(np.mean(values))


def test_fit_learns_and_writes_outputs(demo_video, tmp_path):
    config = _tiny_config()
    trainer = Trainer(demo_video, config, tmp_path / "fit")
    trainer.skinning.warmup(config.field_warmup_steps)
    before = _mean_train_psnr(trainer)
    trainer.fit(progress=False)  # a fresh fit (its warm-up distils the same prior again)
    after = _mean_train_psnr(trainer)
    assert after > before + 3.0, (before, after)

    out = tmp_path / "fit"
    for name in ("avatar.pt", "canonical.ply", "config.json", "train_log.jsonl", "checkpoint.pt",
                 "training_poses.npz"):
        assert (out / name).is_file(), name
    log = [json.loads(line) for line in (out / "train_log.jsonl").read_text().splitlines()]
    assert log[-1]["step"] == config.iterations
    assert list((out / "previews").glob("*.png"))

    avatar = Avatar.load(out)
    assert avatar.gaussians.count == trainer.gaussians.count
    bones = torch.as_tensor(demo_video.bone_transforms[3], dtype=torch.float32)
    with torch.no_grad():
        reloaded, _, _ = avatar.render(demo_video.cameras[3], bones, background=trainer.frames.background)
        original, _, _ = trainer.avatar.render(demo_video.cameras[3], bones, background=trainer.frames.background)
    assert torch.allclose(reloaded, original, atol=1e-5)

    result = evaluate_avatar(avatar, demo_video, progress=False)
    assert result["frame_count"] == demo_video.frame_count
    assert result["psnr_masked"] is not None and result["psnr_masked"] > 10.0


def test_resume_matches_uninterrupted(demo_video, tmp_path):
    config = _tiny_config(iterations=60, densify_from=20, densify_every=20, densify_until=50,
                          gaussian_only_steps=30, secondary_from=25, lighting=True, checkpoint_every=1000,
                          backward_mapping=True, backward_from=30, backward_every=10, backward_until=60)
    whole = Trainer(demo_video, config, tmp_path / "whole")
    whole.fit(progress=False)

    interrupted = Trainer(demo_video, config, tmp_path / "parts")
    interrupted.fit(progress=False, stop_at=35)  # as if killed after step 35 (a checkpoint is written)
    resumed = Trainer(demo_video, config, tmp_path / "parts")
    resumed.fit(resume=True, progress=False)
    assert resumed.step == whole.step == 60
    for name in ("means", "log_scales", "quats", "opacity_logits", "sh_dc", "sh_rest"):
        a, b = getattr(whole.gaussians, name), getattr(resumed.gaussians, name)
        assert a.shape == b.shape, name
        assert torch.allclose(a, b, atol=1e-6), name
    assert resumed.avatar.part("secondary_motion") is not None
    # the backward mapping ran (its cache was rebuilt after the last densification) and resumed the same way
    backward, resumed_backward = (t.extension("backward_mapping").mapping for t in (whole, resumed))
    assert backward.ready and resumed_backward.ready
    assert torch.equal(backward.index, resumed_backward.index)
    assert torch.allclose(backward.target_means, resumed_backward.target_means, atol=1e-6)
    log = [json.loads(line) for line in (tmp_path / "whole" / "train_log.jsonl").read_text().splitlines()]
    assert any(entry.get("ambiguous", 0) > 0 for entry in log), log
    assert torch.equal(whole.avatar.part("lighting").directional, resumed.avatar.part("lighting").directional)
    assert torch.allclose(whole.avatar.part("secondary_motion").displacement,
                          resumed.avatar.part("secondary_motion").displacement, atol=1e-6)


def test_dynamics_fit_resumes_exactly_and_rolls_out_new_motions(demo_video, tmp_path):
    config = _tiny_config(iterations=50, densify_from=20, densify_every=20, densify_until=40,
                          gaussian_only_steps=25, secondary_motion=False, dynamics=True, secondary_from=25,
                          dynamics_hidden=16, dynamics_window=3, dynamics_refresh_every=10, checkpoint_every=1000)
    whole = Trainer(demo_video, config, tmp_path / "whole")
    whole.fit(progress=False)
    interrupted = Trainer(demo_video, config, tmp_path / "parts")
    interrupted.fit(progress=False, stop_at=33)  # between two refreshes of the cached rollout
    resumed = Trainer(demo_video, config, tmp_path / "parts")
    resumed.fit(resume=True, progress=False)
    dynamics, resumed_dynamics = whole.avatar.part("dynamics"), resumed.avatar.part("dynamics")
    assert isinstance(dynamics, SecondaryDynamics) and isinstance(resumed_dynamics, SecondaryDynamics)
    for name, parameter in dynamics.named_parameters():
        assert torch.allclose(parameter, dict(resumed_dynamics.named_parameters())[name], atol=1e-6), name
    assert torch.allclose(whole.gaussians.means, resumed.gaussians.means, atol=1e-6)
    # the saved avatar replays the training instants from its table ...
    avatar = Avatar.load(tmp_path / "whole")
    table = avatar.part("dynamics").frame_displacement
    assert table.shape == (whole.frames.count, dynamics.node_count, 3)
    assert float(table[1:].abs().max()) > 0
    bones = whole.frames.bone_transforms[5]
    assert torch.equal(avatar.part("dynamics").node_displacement(bones), table[5])
    # ... and rolls out a motion it never saw (every training frame, at the video's own rate)
    motion = torch.as_tensor(demo_video.bone_transforms, dtype=torch.float32)
    avatar.prepare_sequence(motion, frame_ids=demo_video.frame_ids, fps=demo_video.fps)
    unseen = [t for t in range(demo_video.frame_count) if t not in set(whole.frames.indices.tolist())]
    assert unseen
    moved = avatar.part("dynamics").node_displacement(motion[unseen[-1]])
    assert float(moved.abs().max()) > 0
    with_dynamics = evaluate_avatar(avatar, demo_video, progress=False)["psnr_masked"]
    del avatar.parts["dynamics"]
    without = evaluate_avatar(avatar, demo_video, progress=False)["psnr_masked"]
    assert abs(with_dynamics - without) < 1.0, (with_dynamics, without)  # a short fit: small, sane motion


def test_joint_growth_fit_grows_replays_and_resumes_exactly(demo_video, tmp_path):
    """ToMiE's growth in a fit: joints grow at grow_at, train, replay their rotations at training instants only,
    and a fit interrupted after the growth resumes to the same result."""
    config = _tiny_config(iterations=60, densify_from=10, densify_every=10, densify_until=40,
                          gaussian_only_steps=25, secondary_motion=True, secondary_from=25, grow_joints=True,
                          grow_at=30, grow_threshold=0.5, grow_max_joints=2, grow_kernel_frames=6,
                          checkpoint_every=1000, log_every=10)
    whole = Trainer(demo_video, config, tmp_path / "whole")
    whole.fit(progress=False)
    extra = whole.avatar.part("joint_growth")
    assert extra is not None and extra.count == 2
    assert whole.avatar.field.joint_count == demo_video.skeleton.joint_count + 2
    log = [json.loads(line) for line in (tmp_path / "whole" / "train_log.jsonl").read_text().splitlines()]
    growth = [entry for entry in log if entry.get("stage") == "grow_joints"]
    assert len(growth) == 1 and growth[0]["step"] == 30
    # densification renumbered the Gaussians before the growth: the pooled statistics had to follow
    counts = [entry["gaussians"] for entry in log if "step" in entry and "loss" in entry and entry["step"] <= 30]
    assert len(set(counts)) > 1, counts
    names = demo_video.skeleton.names
    assert growth[0]["grown_parents"] == [names[j] for j in extra.parents.tolist()]
    gradients = growth[0]["joint_gradient"]
    assert min(gradients[name] for name in growth[0]["grown_parents"]) >= growth[0]["threshold"] > 0

    # interrupted after the growth (the checkpoint holds the grown joints) and before it (the pooled statistics)
    for stop in (45, 25):
        interrupted = Trainer(demo_video, config, tmp_path / f"parts{stop}")
        interrupted.fit(progress=False, stop_at=stop)
        resumed = Trainer(demo_video, config, tmp_path / f"parts{stop}")
        resumed.fit(resume=True, progress=False)
        for name, parameter in extra.named_parameters():
            assert torch.allclose(parameter, dict(resumed.avatar.part("joint_growth").named_parameters())[name],
                                  atol=1e-6), (stop, name)
        for name, parameter in whole.avatar.field.named_parameters():
            resumed_parameter = dict(resumed.avatar.field.named_parameters())[name]
            assert torch.allclose(parameter, resumed_parameter, atol=1e-6), (stop, name)
        assert torch.allclose(whole.gaussians.means, resumed.gaussians.means, atol=1e-6), stop

    # the saved avatar replays each training instant's learned rotations; other poses keep the joints at rest
    avatar = Avatar.load(tmp_path / "whole")
    rotations = avatar.part("joint_growth").rotations_for_pose(whole.frames.bone_transforms[4])
    assert torch.allclose(rotations, extra.frame_rotations(torch.tensor(4)))
    assert float(rotations[:, 1:].detach().abs().max()) > 0
    unseen = [t for t in range(demo_video.frame_count) if t not in set(whole.frames.indices.tolist())][0]
    rest = avatar.part("joint_growth").rotations_for_pose(torch.as_tensor(demo_video.bone_transforms[unseen],
                                                                  dtype=torch.float32))
    assert torch.equal(rest, torch.tensor([[1.0, 0.0, 0.0, 0.0]] * 2))
    frame = int(whole.frames.indices[4])
    with torch.no_grad():
        bones = whole.frames.bone_transforms[4]
        replayed, _, _ = avatar.render(demo_video.cameras[frame], bones)
        trained, _, _ = whole.avatar.render(demo_video.cameras[frame], bones)
        at_rest, _, _ = avatar.render(demo_video.cameras[frame], bones,
                                      inputs={"joint_growth": torch.tensor([[1.0, 0.0, 0.0, 0.0]] * 2)})
    assert (replayed - trained).abs().max() < 1e-5
    assert (replayed - at_rest).abs().max() > 1e-4


def test_history_criterion_locates_the_joint_with_the_largest_code_offsets(demo_video, tmp_path):
    config = _tiny_config(iterations=45, densify_from=20, densify_every=20, densify_until=40,
                          gaussian_only_steps=25, secondary_motion=False, grow_joints=True, grow_at=40,
                          grow_criterion="history", grow_threshold=0.5, grow_max_joints=1, grow_kernel_frames=6,
                          frame_codes=True)
    trainer = Trainer(demo_video, config, tmp_path / "fit")
    trainer.fit(progress=False, stop_at=41)
    report = trainer.extension("joint_growth").report
    values = report["joint_gradient"]
    assert all(math.isfinite(v) and v > 0 for v in values.values())
    assert report["grown_parents"] == [max(values, key=values.get)]
    assert trainer.avatar.part("joint_growth").count == 1


def test_dynamics_and_per_frame_displacements_are_exclusive():
    with pytest.raises(ValueError, match="choose one secondary-motion model"):
        preset("quick", dynamics=True, secondary_motion=True)


def test_resume_refuses_a_checkpoint_of_an_earlier_format_clearly(demo_video, tmp_path):
    """A checkpoint written before the extension protocol (no format tag, one key per optional part) is refused
    with a message naming its format; a fresh fit in the same folder still runs."""
    config = _tiny_config(iterations=20, checkpoint_every=1000, secondary_motion=False)
    Trainer(demo_video, config, tmp_path / "run").fit(progress=False, stop_at=10)
    path = tmp_path / "run" / "checkpoint.pt"
    state = torch.load(path, weights_only=True)
    legacy = {key: value for key, value in state.items() if key not in ("format", "extensions", "skinning")}
    legacy.update(field=state["skinning"]["field"], pose_correction=None, secondary_motion=None)
    torch.save(legacy, path)
    with pytest.raises(ValueError, match="checkpoint format 'warpavatar-checkpoint/1' was written by an earlier"):
        Trainer(demo_video, config, tmp_path / "run").fit(resume=True, progress=False)
    fresh = Trainer(demo_video, config, tmp_path / "run")
    fresh.fit(progress=False)
    assert fresh.step == 20


def test_resume_refuses_other_config(demo_video, tmp_path):
    config = _tiny_config(iterations=20, checkpoint_every=1000)
    Trainer(demo_video, config, tmp_path / "run").fit(progress=False, stop_at=10)
    other = Trainer(demo_video, _tiny_config(iterations=20, lambda_ssim=0.5), tmp_path / "run")
    with pytest.raises(ValueError, match="--lambda-ssim: 0.2 in the checkpoint vs 0.5 given"):
        other.fit(resume=True, progress=False)


def test_bad_shading_is_a_clear_error():
    with pytest.raises(ValueError, match="shading must be 'world' or 'view'"):
        preset("quick", shading="lambert")


def test_training_target_keeps_edge_pixels_of_flat_background_frames(demo_video, tmp_path):
    import dataclasses

    index = 2
    auto = Trainer(demo_video, _tiny_config(iterations=1), tmp_path / "auto")
    frame_index = int(auto.frames.indices[index])  # the tiny config trains on a subset of the frames
    image = torch.as_tensor(demo_video.images[frame_index]).float() / 255.0
    mask = torch.as_tensor(demo_video.masks[frame_index]).float() / 255.0
    background = torch.as_tensor(demo_video.background, dtype=torch.float32)
    composite = image * mask[..., None] + background * (1 - mask[..., None])
    # the demo's meta.json declares the flat background its frames were rendered over: 'auto' keeps the frame
    assert "background" in demo_video.meta
    target, target_mask = auto.frames.target(index)
    assert torch.equal(target, image) and torch.equal(target_mask, mask)
    # the frame and the composite differ at the anti-aliased pixels just outside the mask
    outside = (mask == 0) & (image.sum(-1) > 0)
    assert bool(outside.any())
    masked = Trainer(demo_video, _tiny_config(iterations=1, target="masked"), tmp_path / "masked")
    assert torch.equal(masked.frames.target(index)[0], composite)
    # a folder that declares no background (a real video) is cut out by its mask under 'auto'
    undeclared = dataclasses.replace(demo_video, meta={})
    cut = Trainer(undeclared, _tiny_config(iterations=1), tmp_path / "undeclared")
    assert torch.equal(cut.frames.target(index)[0], composite)
    frame = Trainer(undeclared, _tiny_config(iterations=1, target="frame"), tmp_path / "frame")
    assert torch.equal(frame.frames.target(index)[0], image)


def test_bad_target_is_a_clear_error():
    with pytest.raises(ValueError, match="target must be"):
        preset("quick", target="alpha")


def test_skinning_prior_temperature_blends_neighbouring_bones(demo_video, tmp_path):
    from warpavatar.model.skinning_field import bone_distance_prior

    sharp = Trainer(demo_video, _tiny_config(iterations=1), tmp_path / "sharp")
    smooth = Trainer(demo_video, _tiny_config(iterations=1, skinning_prior_temperature=0.1), tmp_path / "smooth")
    # the field's warm-up target is the bone-distance prior at the configured temperature, per grid point
    heads, tails = (torch.as_tensor(a, dtype=torch.float32) for a in (demo_video.skeleton.heads,
                                                                      demo_video.skeleton.tails))
    for trainer, temperature in ((sharp, 0.02), (smooth, 0.1)):
        points = trainer.avatar.field.grid_points.reshape(-1, 3)
        expected = bone_distance_prior(points, heads, tails, temperature=temperature * trainer.extent)
        assert torch.allclose(trainer.skinning.prior, expected, atol=1e-6)

    # a higher temperature spreads each point's weight over more bones
    def entropy(weights):
        return float(-(weights * weights.clamp_min(1e-12).log()).sum(-1).mean())

    assert entropy(smooth.skinning.prior) > 1.5 * entropy(sharp.skinning.prior)
    with pytest.raises(ValueError, match="skinning_prior_temperature must be positive"):
        preset("quick", skinning_prior_temperature=0.0)
