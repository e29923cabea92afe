"""Pose refinement: the corrected skeleton (against a plain forward-kinematics reference and finite differences),
the part's lookups, and refinement in a fit and at test time recovering poses perturbed by a known amount."""

import json
import math

import numpy as np
import pytest
import torch
from conftest import load_tool
from scipy.spatial.transform import Rotation

from research.perturb_poses import perturb_folder
from warpavatar import data
from warpavatar.data.writer import write_video_folder
from warpavatar.extensions.pose_refinement import PoseRefinement
from warpavatar.geometry import skeleton_levels
from warpavatar.model.kinematics import ancestor_jumps, axis_angle_to_matrix, corrected_transforms, rigid_poses
from warpavatar.fit import Trainer, preset
from warpavatar.model import Avatar

PARENTS = [-1, 0, 1, 2, 1, 4, 0, 6]


def _skeleton(generator, dtype=torch.float64):
    heads = torch.randn(len(PARENTS), 3, generator=generator, dtype=dtype)
    return heads, torch.tensor(PARENTS)


def _random_pose(heads, parents, generator):
    """Rigid forward kinematics of random local rotations: [J,4,4] rest-to-posed transforms."""
    joint_count = heads.shape[0]
    local = axis_angle_to_matrix(0.6 * torch.randn(joint_count, 3, generator=generator, dtype=heads.dtype))
    world = [None] * joint_count
    pivot = [None] * joint_count
    for joint in range(joint_count):
        parent = int(parents[joint])
        if parent < 0:
            world[joint] = local[joint]
            pivot[joint] = heads[joint] + torch.randn(3, generator=generator, dtype=heads.dtype)
        else:
            world[joint] = world[parent] @ local[joint]
            pivot[joint] = pivot[parent] + world[parent] @ (heads[joint] - heads[parent])
    pose = torch.eye(4, dtype=heads.dtype).repeat(joint_count, 1, 1)
    for joint in range(joint_count):
        pose[joint, :3, :3] = world[joint]
        pose[joint, :3, 3] = pivot[joint] - world[joint] @ heads[joint]
    return pose


def _reference(pose, heads, parents, rotation, translation):
    """The corrected pose joint by joint: local rotations L_j = R_p^T R_j turned by exp(d_j), then forward
    kinematics from the (moved) root with the given offsets between pivots."""
    joint_count = heads.shape[0]
    rotations, pivots = pose[:, :3, :3], (pose[:, :3, :3] @ heads[:, :, None])[:, :, 0] + pose[:, :3, 3]
    new_rotation, new_pivot = [None] * joint_count, [None] * joint_count
    for joint in range(joint_count):
        parent = int(parents[joint])
        turn = torch.as_tensor(Rotation.from_rotvec(rotation[joint].detach().numpy()).as_matrix(), dtype=pose.dtype)
        if parent < 0:
            new_rotation[joint] = rotations[joint] @ turn
            new_pivot[joint] = pivots[joint] + translation
        else:
            local = rotations[parent].T @ rotations[joint]
            new_rotation[joint] = new_rotation[parent] @ local @ turn
            offset = rotations[parent].T @ (pivots[joint] - pivots[parent])
            new_pivot[joint] = new_pivot[parent] + new_rotation[parent] @ offset
    out = pose.clone()
    for joint in range(joint_count):
        out[joint, :3, :3] = new_rotation[joint]
        out[joint, :3, 3] = new_pivot[joint] - new_rotation[joint] @ heads[joint]
    return out


def test_axis_angle_matches_scipy_and_is_smooth_at_zero():
    generator = torch.Generator().manual_seed(0)
    vectors = torch.randn(20, 3, generator=generator, dtype=torch.float64)
    vectors[0] = 1e-6 * vectors[0]  # the small-angle branch
    expected = torch.as_tensor(Rotation.from_rotvec(vectors.numpy()).as_matrix())
    assert torch.allclose(axis_angle_to_matrix(vectors), expected, atol=1e-12)
    zero = torch.zeros(3, dtype=torch.float64, requires_grad=True)
    axis_angle_to_matrix(zero).sum().backward()
    assert torch.isfinite(zero.grad).all()
    assert torch.autograd.gradcheck(axis_angle_to_matrix, (torch.zeros(2, 3, dtype=torch.float64,
                                                                        requires_grad=True),))


def test_levels_put_parents_first_and_jumps_reach_every_ancestor():
    levels = skeleton_levels(PARENTS)
    assert levels == [[0], [1, 6], [2, 4, 7], [3, 5]]
    with pytest.raises(ValueError, match="cycle"):
        skeleton_levels([1, 2, 0])
    with pytest.raises(ValueError, match="cycle"):
        ancestor_jumps([1, 2, 0])
    none = len(PARENTS)
    jumps = [jump.tolist() for jump in ancestor_jumps(PARENTS)]
    assert jumps == [[none, 0, 1, 2, 1, 4, 0, 6], [none, none, 0, 1, 0, 1, none, 0]]  # depth 4: two rounds
    assert [jump.tolist() for jump in ancestor_jumps([-1, 0])] == [[2, 0]]
    chain = [-1] + list(range(8))  # depth 9: four rounds, the last jumping 8 joints up
    assert [jump.tolist() for jump in ancestor_jumps(chain)][-1] == [9] * 8 + [0]


def test_corrected_transforms_match_forward_kinematics_and_keep_the_skeleton_rigid():
    generator = torch.Generator().manual_seed(1)
    heads, parents = _skeleton(generator)
    pose = _random_pose(heads, parents, generator)
    jumps = ancestor_jumps(PARENTS)
    rotation = 0.3 * torch.randn(len(PARENTS), 3, generator=generator, dtype=torch.float64)
    translation = torch.randn(3, generator=generator, dtype=torch.float64)
    corrected = corrected_transforms(pose, heads, jumps, rotation, translation)
    assert torch.allclose(corrected, _reference(pose, heads, parents, rotation, translation), atol=1e-10)
    # zero corrections give the pose back; every bone keeps its length
    assert torch.allclose(corrected_transforms(pose, heads, jumps, torch.zeros_like(rotation),
                                               torch.zeros(3, dtype=torch.float64)), pose, atol=1e-12)

    def pivots(p):
        return (p[:, :3, :3] @ heads[:, :, None])[:, :, 0] + p[:, :3, 3]

    for joint, parent in enumerate(PARENTS):
        if parent >= 0:
            before = (pivots(pose)[joint] - pivots(pose)[parent]).norm()
            after = (pivots(corrected)[joint] - pivots(corrected)[parent]).norm()
            assert torch.allclose(before, after, atol=1e-10)
    rotations = corrected[:, :3, :3]
    assert torch.allclose(rotations @ rotations.transpose(-1, -2), torch.eye(3, dtype=torch.float64).expand_as(
        rotations), atol=1e-10)


def test_corrected_transforms_gradients_match_finite_differences():
    generator = torch.Generator().manual_seed(2)
    heads, parents = _skeleton(generator)
    pose = _random_pose(heads, parents, generator)
    jumps = ancestor_jumps(PARENTS)
    rotation = (0.2 * torch.randn(len(PARENTS), 3, generator=generator, dtype=torch.float64)).requires_grad_()
    translation = torch.randn(3, generator=generator, dtype=torch.float64).requires_grad_()
    assert torch.autograd.gradcheck(
        lambda r, t: corrected_transforms(pose, heads, jumps, r, t), (rotation, translation))


def test_the_part_refines_training_instants_and_leaves_other_poses(tmp_path):
    generator = torch.Generator().manual_seed(3)
    heads, parents = _skeleton(generator, dtype=torch.float32)
    poses = torch.stack([_random_pose(heads.double(), parents, generator).float() for _ in range(4)])
    part = PoseRefinement(poses, heads, parents, torch.tensor([0, 2, 4, 6]))
    with torch.no_grad():
        part.rotation.normal_(0.0, 0.1, generator=generator)
        part.translation.normal_(0.0, 0.05, generator=generator)

    from warpavatar.model import PoseFrame

    def Frame(pose, explicit=None, skeleton_pose=None):
        return PoseFrame(pose, None, {} if explicit is None else {"pose_refinement": explicit}, skeleton_pose)

    with torch.no_grad():
        looked_up = part.skinning_transforms(poses[2], Frame(poses[2]))
        assert torch.allclose(looked_up, part.refined(2), atol=1e-6)
        assert (looked_up - poses[2]).abs().max() > 1e-3
        other = poses[1].clone()
        other[0, 0, 3] += 0.1  # not a training pose: used as given
        assert torch.equal(part.skinning_transforms(other, Frame(other)), other)
        assert torch.allclose(part.skinning_transforms(poses[0], Frame(poses[0], 3)), part.refined(3), atol=1e-6)
        explicit = poses[3] * 1.0  # a pose refined at test time is kept
        assert torch.equal(part.skinning_transforms(explicit, Frame(poses[0], skeleton_pose=explicit)), explicit)
    part.write_poses(tmp_path / "poses.npz")
    saved = np.load(tmp_path / "poses.npz")
    assert saved["bone_transforms"].shape == (4, len(PARENTS), 4, 4)
    assert saved["frame_ids"].tolist() == [0, 2, 4, 6]
    assert np.allclose(saved["bone_transforms"], part.refined_poses().numpy(), atol=1e-6)


def test_the_refined_table_follows_the_corrections_even_where_their_versions_do_not():
    """The table of refined poses is made again after an in-place change of the corrections, and after
    ``forget_table`` where the change left no trace in the tensors' versions (what a replayed CUDA graph does; here
    a write through ``.data``)."""
    generator = torch.Generator().manual_seed(9)
    heads, parents = _skeleton(generator, dtype=torch.float32)
    poses = torch.stack([_random_pose(heads.double(), parents, generator).float() for _ in range(3)])
    part = PoseRefinement(poses, heads, parents, torch.arange(3))
    first = part.refined_poses()
    with torch.no_grad():
        part.rotation.add_(0.1)  # seen: a new version
    second = part.refined_poses()
    assert (second - first).abs().max() > 1e-3
    part.rotation.data.add_(0.1)  # unseen
    assert part.refined_poses() is second
    part.forget_table()
    assert torch.allclose(part.refined_poses(), part.refined(slice(None)).detach(), atol=1e-6)
    assert (part.refined_poses() - second).abs().max() > 1e-3


def test_refined_poses_of_slightly_skewed_given_poses_are_written_rigid(tmp_path):
    """Given poses a little off rigid (a refined pose refined again: |R^T R - I| about 1e-3) drift further through
    the corrections; the written poses.npz is rigid again (the reader accepts it), with every pivot where the
    refined pose put it."""
    from warpavatar.data.reader import read_poses
    from warpavatar.model.kinematics import posed_pivots, rigid_poses

    generator = torch.Generator().manual_seed(8)
    heads, parents = _skeleton(generator, dtype=torch.float32)
    poses = torch.stack([_random_pose(heads.double(), parents, generator).float() for _ in range(5)])
    skew = 1e-3 * torch.randn(5, len(PARENTS), 3, 3, generator=generator)
    poses[..., :3, :3] += skew + skew.transpose(-1, -2)
    part = PoseRefinement(poses, heads, parents, torch.arange(5))
    with torch.no_grad():
        part.rotation.normal_(0.0, 0.2, generator=generator)
    refined = part.refined_poses()
    gram = refined[..., :3, :3].transpose(-1, -2) @ refined[..., :3, :3]
    skewed = float((gram - torch.eye(3)).abs().max())
    assert skewed > 2e-3  # what the reader would refuse
    part.write_poses(tmp_path / "poses.npz")
    written, ids, pivots = read_poses(tmp_path / "poses.npz", joint_count=len(PARENTS))
    assert ids.tolist() == list(range(5))
    written = torch.as_tensor(written)
    assert np.allclose(pivots, posed_pivots(refined, heads).numpy(), atol=1e-5)
    assert torch.allclose(posed_pivots(written, heads), posed_pivots(refined, heads), atol=1e-5)
    gram = written[..., :3, :3].transpose(-1, -2) @ written[..., :3, :3]
    assert float((gram - torch.eye(3)).abs().max()) < 1e-5
    # the nearest rotations: R = Q (I + S) with |S| about half of |R^T R - I|
    assert float((written[..., :3, :3] - refined[..., :3, :3]).abs().max()) <= 2.0 * skewed
    assert torch.equal(rigid_poses(written, heads)[..., 3, :], written[..., 3, :])


def test_corrected_transforms_move_every_root_of_a_forest():
    generator = torch.Generator().manual_seed(4)
    parents = torch.tensor([-1, 0, 1, -1, 3, 3])
    heads = torch.randn(6, 3, generator=generator, dtype=torch.float64)
    pose = _random_pose(heads, parents, generator)
    rotation = 0.3 * torch.randn(6, 3, generator=generator, dtype=torch.float64)
    translation = torch.randn(3, generator=generator, dtype=torch.float64)
    corrected = corrected_transforms(pose, heads, ancestor_jumps(parents.tolist()), rotation, translation)
    assert torch.allclose(corrected, _reference(pose, heads, parents, rotation, translation), atol=1e-10)


# --- options, meta.json ----------------------------------------------------------------------------------------------

@pytest.mark.parametrize("values, match", [
    (dict(refine_poses="maybe"), "--refine-poses must be one of auto, on, off, got .maybe."),
    (dict(refine_poses="on", lr_pose_rotation=-1e-3), "lr_pose_rotation"),
    (dict(refine_poses="on", lambda_pose_smooth=float("nan")), "lambda_pose_smooth"),
    (dict(refine_poses="on", refine_poses_from=-5), "refine_poses_from"),
    (dict(refine_poses="on", refine_poses_until=-1), "refine_poses_until"),
    (dict(refine_poses="on", lr_pose_final=0.0), r"lr_pose_final must lie in \(0, 1\]"),
    (dict(refine_poses="on", lr_pose_final=1.5), r"lr_pose_final must lie in \(0, 1\]"),
    (dict(refine_poses="on", refine_poses_from=500, refine_poses_until=300), r"refine_poses_until \(300\) must lie"),
    (dict(refine_poses="on", iterations=100, refine_poses_from=10, refine_poses_until=200), "the last step"),
])
def test_bad_refinement_options_are_clear_errors(values, match):
    with pytest.raises(ValueError, match=match):
        preset("quick", **values)


def test_cli_rejects_bad_refinement_values_in_one_line(capsys):
    from warpavatar.cli.fit import main
    with pytest.raises(SystemExit) as stop:
        main(["--demo", "--refine-poses", "sometimes"])
    assert stop.value.code == 2
    error = capsys.readouterr().err.strip().splitlines()[-1]
    assert "--refine-poses" in error and "sometimes" in error and "Traceback" not in error


def test_meta_json_poses_value_is_checked(tmp_path):
    import shutil
    folder = tmp_path / "train"
    shutil.copytree(data.demo_subject_path() / "train", folder)
    meta = json.loads((folder / "meta.json").read_text())
    (folder / "meta.json").write_text(json.dumps({**meta, "poses": "guessed"}))
    with pytest.raises(data.VideoFolderError, match=r"meta\.json.*'poses' must be one of 'exact', 'estimated'"):
        data.load_video_folder(folder)
    (folder / "meta.json").write_text(json.dumps({**meta, "poses": "estimated"}))
    assert data.load_video_folder(folder).meta["poses"] == data.ESTIMATED_POSES


# --- refinement in a fit ---------------------------------------------------------------------------------------------

def _fit_config(**overrides):
    values = dict(iterations=600, image_scale=0.5, max_train_frames=25, init_points_per_bone=30,
                  init_carve_candidates=20000, init_carve_points=800, sh_degree=1, sh_increase_every=100,
                  grid_cells=16, grid_min_cells=6, field_hidden=32, field_layers=2, field_warmup_steps=40,
                  gaussian_only_steps=80, densify_from=40, densify_until=400, densify_every=50,
                  max_gaussians=3000, checkpoint_every=10000, log_every=100, preview_frames=1,
                  refine_poses_from=200)
    values.update(overrides)
    return preset("quick", **values)


def _pivots(poses, heads):
    return (poses[..., :3, :3] @ heads[:, :, None])[..., 0] + poses[..., :3, 3]


def _projected(points, cameras):
    """[T,J,2] pixel positions of [T,J,3] world points seen by each frame's camera."""
    out = []
    for frame_points, camera in zip(points, cameras):
        K, world_to_camera = camera.K.cpu(), camera.world_to_camera.cpu()
        local = frame_points @ world_to_camera[:3, :3].T + world_to_camera[:3, 3]
        pixels = local @ K.T
        out.append(pixels[:, :2] / pixels[:, 2:])
    return torch.stack(out)


@pytest.fixture(scope="module")
def noisy_fit(tmp_path_factory):
    """A fit of the demo subject from poses perturbed by 5 degrees per joint and 3 cm at the root (auto mode: the
    perturbed folder says its poses are estimated), with the exact poses of its training frames."""
    root = tmp_path_factory.mktemp("noisy_fit")
    perturb_folder(data.demo_subject_path() / "train", root / "train", rotation_deg=5.0,
                   translation=0.03, seed=0)
    video = data.load_video_folder(root / "train", scale=0.5)
    trainer = Trainer(video, _fit_config(), root / "fit")
    trainer.fit(progress=False)
    exact = data.load_video_folder(data.demo_subject_path() / "train", scale=0.5)
    truth = torch.as_tensor(exact.bone_transforms[trainer.frames.indices]).float()
    return trainer, truth


def test_fit_recovers_a_known_pose_perturbation(noisy_fit):
    trainer, truth = noisy_fit
    part = trainer.avatar.part("pose_refinement")
    assert part is not None  # auto mode: meta.json says the poses are estimated
    heads = torch.as_tensor(trainer.frames.skeleton.heads, dtype=torch.float32)
    given, refined = trainer.frames.bone_transforms.cpu(), part.refined_poses().cpu()
    error = {name: (_pivots(poses, heads) - _pivots(truth, heads)).norm(dim=-1).mean()
             for name, poses in (("given", given), ("refined", refined))}
    pixels = {name: (_projected(_pivots(poses, heads), trainer.frames.cameras)
                     - _projected(_pivots(truth, heads), trainer.frames.cameras)).norm(dim=-1).mean()
              for name, poses in (("given", given), ("refined", refined))}
    # the joints' positions come clearly closer to the exact ones, most of all across the image (what one camera
    # sees; along its axis only the priors and the other frames constrain them)
    assert error["refined"] < 0.8 * error["given"], error
    assert pixels["refined"] < 0.7 * pixels["given"], pixels
    # the corrections have zero mean over the frames (the gauge); the refined poses are written with the fit
    assert part.rotation.mean(0).abs().max() < 1e-5 and part.translation.mean(0).abs().max() < 1e-6
    saved = np.load(trainer.output_dir / "poses_refined.npz")  # rigid again: the nearest rotations, same pivots
    assert np.allclose(saved["bone_transforms"], rigid_poses(refined, heads).numpy(), atol=1e-6)
    skew = float((refined[..., :3, :3].transpose(-1, -2) @ refined[..., :3, :3] - torch.eye(3)).abs().max())
    assert np.abs(saved["bone_transforms"] - refined.numpy()).max() <= 2.0 * skew + 1e-6, skew
    assert saved["frame_ids"].tolist() == trainer.frames.frame_ids.tolist()


def test_joints_the_images_barely_see_stay_nearer_their_prior_target(noisy_fit):
    trainer, _ = noisy_fit
    part = trainer.avatar.part("pose_refinement")
    with torch.no_grad():
        posed = trainer.avatar.pose(trainer.frames.bone_transforms[0])
        influence = posed["weights"][:, : part.joint_count].sum(0).cpu()  # [J] skinning weight over the Gaussians
    parents = trainer.frames.skeleton.parents
    # a joint's turn moves its own Gaussians and its descendants': what the images see of it
    carried = influence.clone()
    for joint in reversed(range(len(parents))):
        if parents[joint] >= 0:
            carried[parents[joint]] += carried[joint]
    order = torch.argsort(carried)
    # [J] mean move away from the prior's target [rad] (the given motion smoothed in time, where the corrections
    # start; with --pose-prior-window 0 the given pose itself)
    target = trainer.extension("pose_refinement").target_rotation
    angles = (part.rotation.detach() - target).norm(dim=-1).mean(0).cpu()
    # every joint was perturbed alike (5 degrees); the priors hold the barely seen ones (small fingers at 64x64
    # pixels) near their target while the images move the well seen ones
    barely, well = angles[order[:5]].mean(), angles[order[-5:]].mean()
    assert barely < 0.5 * well, (barely, well)
    assert well > math.radians(0.5)  # (the target, smoothed over up to 0.45 s, is already nearer the truth)


def test_refinement_is_deterministic_and_resumes_exactly(tmp_path):
    perturb_folder(data.demo_subject_path() / "train", tmp_path / "train", rotation_deg=5.0,
                   translation=0.03, seed=1)
    video = data.load_video_folder(tmp_path / "train", scale=0.5)
    config = _fit_config(iterations=60, max_train_frames=8, refine_poses_from=20, densify_from=20,
                         densify_every=20, densify_until=50, gaussian_only_steps=30, field_warmup_steps=10)
    whole = Trainer(video, config, tmp_path / "whole")
    whole.fit(progress=False)
    again = Trainer(video, config, tmp_path / "again")
    again.fit(progress=False)
    interrupted = Trainer(video, config, tmp_path / "parts")
    interrupted.fit(progress=False, stop_at=35)
    resumed = Trainer(video, config, tmp_path / "parts")
    resumed.fit(resume=True, progress=False)
    reference = whole.avatar.part("pose_refinement")
    assert reference.rotation.abs().max() > 1e-4  # it did refine
    for other in (again, resumed):
        part = other.avatar.part("pose_refinement")
        assert torch.allclose(part.rotation, reference.rotation, atol=1e-6)
        assert torch.allclose(part.translation, reference.translation, atol=1e-7)
        assert torch.allclose(other.gaussians.means, whole.gaussians.means, atol=1e-6)


def test_auto_follows_meta_json_and_the_avatar_file_keeps_the_refined_poses(tmp_path, noisy_fit):
    exact = data.load_video_folder(data.demo_subject_path() / "train", scale=0.5)
    config = _fit_config(iterations=1)
    assert Trainer(exact, config, tmp_path / "exact").avatar.part("pose_refinement") is None
    assert Trainer(exact, _fit_config(iterations=1, refine_poses="on"), tmp_path / "on").avatar.part(
        "pose_refinement") is not None
    trainer, _ = noisy_fit
    loaded = Avatar.load(trainer.output_dir / "avatar.pt")
    part, original = loaded.part("pose_refinement"), trainer.avatar.part("pose_refinement")
    assert torch.allclose(part.refined_poses(), original.refined_poses().cpu(), atol=1e-6)
    # a novel view of a training instant (the pose as given) is rendered in the refined pose
    with torch.no_grad():
        given = trainer.frames.bone_transforms[3].cpu()
        bones = loaded.pose_bones(given)
    assert torch.allclose(bones[: part.joint_count], part.refined_poses()[3], atol=1e-6)


def test_test_time_refinement_brings_a_perturbed_pose_back(noisy_fit):
    from warpavatar.evaluate import refine_frame_pose
    trainer, _ = noisy_fit
    avatar, part = trainer.avatar, trainer.avatar.part("pose_refinement")
    heads = torch.as_tensor(trainer.frames.skeleton.heads, dtype=torch.float32)
    index = 5
    target_pose = part.refined_poses()[index]  # the pose the avatar explains this frame's image with
    generator = torch.Generator().manual_seed(11)
    turn = torch.randn(part.joint_count, 3, generator=generator)
    turn = torch.deg2rad(torch.tensor(6.0)) * turn / turn.norm(dim=-1, keepdim=True)
    start = corrected_transforms(target_pose, heads, ancestor_jumps(part.parents.tolist()), turn,
                                 torch.tensor([0.03, -0.02, 0.0]))
    image, mask = trainer.frames.target(index)
    camera = trainer.frames.cameras[index]
    trainable = [parameter.requires_grad for parameter in avatar.parameters()]
    refined = refine_frame_pose(avatar, camera, start, image, mask=mask, background=trainer.frames.background,
                                steps=150)
    cameras = [camera]

    def pixel_error(pose):
        return (_projected(_pivots(pose, heads)[None], cameras)
                - _projected(_pivots(target_pose, heads)[None], cameras)).norm(dim=-1).mean()

    assert pixel_error(refined) < 0.5 * pixel_error(start), (pixel_error(refined), pixel_error(start))
    # the avatar was frozen only while refining: what trained before trains again
    assert [parameter.requires_grad for parameter in avatar.parameters()] == trainable and any(trainable)


def test_eval_rejects_a_negative_number_of_refinement_steps(tmp_path, capsys):
    from warpavatar.cli.eval import main
    assert main([str(tmp_path), str(tmp_path), "--refine-poses", "-3"]) != 0
    error = capsys.readouterr().err.strip()
    assert "--refine-poses" in error and "Traceback" not in error and len(error.splitlines()) == 1


def test_evaluation_reports_metrics_with_and_without_test_time_refinement(noisy_fit):
    from warpavatar.evaluate import evaluate_avatar
    trainer, _ = noisy_fit
    held_out = data.load_video_folder(data.demo_subject_path() / "novel_view" / "cam_090", scale=0.5,
                                      max_frames=2)
    result = evaluate_avatar(trainer.avatar, held_out, progress=False, refine_steps=3)
    assert result["refined"]["steps"] == 3
    for key in ("psnr", "ssim", "psnr_masked", "ssim_masked", "floater_share"):
        assert math.isfinite(result[key]) and math.isfinite(result["refined"][key])
        assert all(math.isfinite(frame[f"refined_{key}"]) for frame in result["frames"])
    assert "refined" not in evaluate_avatar(trainer.avatar, held_out, progress=False)


def test_poses_stay_fixed_after_the_last_refining_step(tmp_path):
    perturb_folder(data.demo_subject_path() / "train", tmp_path / "train", rotation_deg=5.0,
                   translation=0.03, seed=2)
    video = data.load_video_folder(tmp_path / "train", scale=0.5)
    config = _fit_config(iterations=50, max_train_frames=6, refine_poses_from=10, refine_poses_until=30,
                         densify_from=20, densify_every=20, densify_until=40, gaussian_only_steps=20,
                         field_warmup_steps=10)
    trainer = Trainer(video, config, tmp_path / "fit")
    trainer.fit(progress=False, stop_at=31)
    part = trainer.avatar.part("pose_refinement")
    at_the_last_step = part.rotation.detach().clone()
    assert at_the_last_step.abs().max() > 1e-4
    resumed = Trainer(video, config, tmp_path / "fit")
    resumed.fit(resume=True, progress=False)
    assert resumed.step == 50
    assert torch.equal(resumed.avatar.part("pose_refinement").rotation.detach(), at_the_last_step)


def test_refinement_stops_three_quarters_of_the_way_by_default():
    from warpavatar.extensions.pose_refinement import PoseRefinementOptions, refinement_last_step
    assert refinement_last_step(PoseRefinementOptions(refine_poses_from=1000), 8000) == 6250
    assert refinement_last_step(PoseRefinementOptions(refine_poses_from=400), 2000) == 1600
    assert refinement_last_step(PoseRefinementOptions(refine_poses_from=10, refine_poses_until=30), 50) == 30
    assert refinement_last_step(PoseRefinementOptions(refine_poses_from=10, refine_poses_until=50), 50) == 50


def test_vector_adam_keeps_each_vector_s_direction():
    """VectorAdam: with vectors of one component it is Adam, step for step; with 3-vectors its first step is each
    gradient's own direction, of root-mean-square length ``lr`` per vector (Adam's would be ``lr`` per component,
    whatever the gradient's direction); a bad learning rate is a clear error."""
    from warpavatar.extensions.pose_refinement import VectorAdam

    generator = torch.Generator().manual_seed(11)
    start = torch.randn(40, 1, generator=generator, dtype=torch.float64)
    weights = torch.rand(40, 1, generator=generator, dtype=torch.float64) + 0.1
    ours, theirs = start.clone().requires_grad_(), start.clone().requires_grad_()
    optimizers = VectorAdam([ours], lr=0.01), torch.optim.Adam([theirs], lr=0.01)
    for _ in range(25):
        for parameter, optimizer in zip((ours, theirs), optimizers):
            optimizer.zero_grad()
            (weights * (parameter - 0.3) ** 2).sum().backward()
            optimizer.step()
    torch.testing.assert_close(ours, theirs, rtol=1e-12, atol=1e-12)

    vectors = torch.randn(30, 3, generator=generator, dtype=torch.float64).requires_grad_()
    gradient = torch.randn(30, 3, generator=generator, dtype=torch.float64) * torch.tensor([1.0, 0.1, 0.01],
                                                                                         dtype=torch.float64)
    before = vectors.detach().clone()
    optimizer = VectorAdam([vectors], lr=0.02, eps=0.0)
    vectors.grad = gradient.clone()
    optimizer.step()
    step = vectors.detach() - before
    torch.testing.assert_close(step, -0.02 * gradient / gradient.square().mean(-1, keepdim=True).sqrt())
    with pytest.raises(ValueError, match="lr must be > 0"):
        VectorAdam([vectors], lr=0.0)


def test_vector_adam_takes_a_learning_rate_tensor_and_an_older_state():
    """A learning rate held in a tensor and changed in place between steps (what a captured step reads) moves the
    parameters as the same rates given as numbers; a state saved with its step count as a number (older
    checkpoints) goes on exactly where the tensor count would."""
    from warpavatar.extensions.pose_refinement import VectorAdam

    generator = torch.Generator().manual_seed(5)
    start = torch.randn(12, 3, generator=generator, dtype=torch.float64)
    gradients = [torch.randn(12, 3, generator=generator, dtype=torch.float64) for _ in range(6)]
    rates = [0.05 * 0.7 ** k for k in range(6)]

    def run(optimizer_of, parameter, begin=0):
        optimizer = optimizer_of(parameter)
        for k in range(begin, 6):
            group = optimizer.param_groups[0]
            if isinstance(group["lr"], torch.Tensor):
                group["lr"].fill_(rates[k])
            else:
                group["lr"] = rates[k]
            parameter.grad = gradients[k].clone()
            optimizer.step()
        return optimizer

    numbers = start.clone().requires_grad_()
    run(lambda q: VectorAdam([q], lr=rates[0]), numbers)
    tensors = start.clone().requires_grad_()
    run(lambda q: VectorAdam([q], lr=torch.tensor(rates[0], dtype=torch.float64)), tensors)
    torch.testing.assert_close(tensors, numbers, rtol=1e-13, atol=1e-13)

    halfway = start.clone().requires_grad_()
    partial = VectorAdam([halfway], lr=rates[0])
    for k in range(3):  # three steps, saved, loaded into a new optimizer, three more
        partial.param_groups[0]["lr"] = rates[k]
        halfway.grad = gradients[k].clone()
        partial.step()
    state = partial.state_dict()
    state["state"][0]["step"] = 3  # as an older version saved it
    again = VectorAdam([halfway], lr=rates[0])
    again.load_state_dict(state)
    run(lambda q: again, halfway, begin=3)
    torch.testing.assert_close(halfway, numbers, rtol=1e-13, atol=1e-13)
    assert isinstance(again.state[halfway]["step"], torch.Tensor) and float(again.state[halfway]["step"]) == 6


def _short_subject(folder, *, frame_count: int):
    """The demo subject with the first ``frame_count`` frames of each of its folders (train/, novel_view/cam_090,
    novel_pose/dance_cam000), written to ``folder``: the same subject, shorter to evaluate."""
    source = data.demo_subject_path()
    for name in ("train", "novel_view/cam_090", "novel_pose/dance_cam000"):
        write_video_folder(data.load_video_folder(source / name, max_frames=frame_count), folder / name)
    return folder


def test_fit_benchmark_reports_the_held_out_folders_after_test_time_refinement(tmp_path, capsys):
    tool = load_tool("fit_benchmark")
    out = tmp_path / "fit"
    subject = _short_subject(tmp_path / "subject", frame_count=6)
    assert tool.main([str(subject), "-o", str(out), "--preset", "quick", "--device", "cpu",
                      "--iterations", "20", "--max-train-frames", "3", "--image-scale", "0.25",
                      "--field-warmup-steps", "5", "--gaussian-only-steps", "5", "--eval-refine-poses", "2"]) == 0
    rows = json.loads((out / "benchmark.json").read_text())["rows"]
    assert [row["folder"] for row in rows] == ["train", "novel_view/cam_090", "novel_pose/dance_cam000"]
    assert rows[0]["refined_psnr_masked"] == "-"  # the fit's own frames are not refined again
    for row in rows[1:]:
        assert math.isfinite(row["refined_psnr_masked"]) and math.isfinite(row["refined_ssim_masked"])
        assert row["refined_psnr_masked"] != row["psnr_masked"]  # the poses moved
    assert all(line.count("|") == 12 for line in capsys.readouterr().out.splitlines() if line.startswith("|"))
    with pytest.raises(SystemExit) as stop:
        tool.main([str(subject), "-o", str(out), "--eval-refine-poses", "-1"])
    assert stop.value.code == 2
    assert "--eval-refine-poses must be >= 0, got -1" in capsys.readouterr().err
