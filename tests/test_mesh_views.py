"""The mesh export's inputs from the fit: the training pixel width it records, the 3D blur that reproduces the fit's
screen-space blur in the canonical renders, and skin weights blended from the Gaussians around each vertex."""

from types import SimpleNamespace

import numpy as np
import pytest
import torch

from warpavatar.data.types import Camera
from warpavatar.fit.outputs import PIXEL_SIZE_KEY, training_pixel_size, write_training_motion
from warpavatar.geometry import quat_to_matrix
from warpavatar.mesh.build import recorded_pixel_size
from warpavatar.mesh.skin import gaussian_blended_weights
from warpavatar.mesh.views import SCREEN_BLUR_PX2, training_blur


def _camera(distance: float, focal: float) -> Camera:
    world_to_camera = np.eye(4)
    world_to_camera[2, 3] = distance  # the world's origin `distance` in front of the camera
    return Camera(np.array([[focal, 0, 31.5], [0, focal, 31.5], [0, 0, 1]]), world_to_camera, 64, 64)


def test_the_blur_is_the_rasterizers():
    assert SCREEN_BLUR_PX2 == pytest.approx(0.3)  # (the rasterizer's own constant: its 2D blur)
    assert training_blur(None) == 0.0
    assert training_blur(0.02) == pytest.approx(np.sqrt(0.3) * 0.02)
    # the views' own screen blur is taken off, and never below nothing
    assert training_blur(0.05, 0.03) == pytest.approx(np.sqrt(0.3 * (0.05 ** 2 - 0.03 ** 2)))
    assert training_blur(0.01, 0.03) == 0.0
    with pytest.raises(ValueError, match="training pixel size"):
        training_blur(float("nan"))


def test_training_pixel_size_is_depth_over_focal():
    skeleton = SimpleNamespace(heads=np.array([[0.0, 0.0, 0.0], [0.0, 0.5, 0.2], [0.0, -0.5, -0.2]]))
    bones = np.tile(np.eye(4), (3, 3, 1, 1))
    bones[2, :, 2, 3] = 1.0  # the third frame's subject a metre further away
    cameras = [_camera(3.0, 100.0), _camera(3.0, 50.0), _camera(3.0, 100.0)]
    # per frame the joints' median depth over the focal: 0.03, 0.06, 0.04 m; their median
    assert training_pixel_size(cameras, bones, skeleton) == pytest.approx(0.04)
    with pytest.raises(ValueError, match="one camera a pose"):
        training_pixel_size(cameras[:2], bones, skeleton)


def test_the_fit_records_the_pixel_size_and_the_export_reads_it(tmp_path):
    skeleton = SimpleNamespace(heads=np.zeros((2, 3)))
    video = SimpleNamespace(fps=25.0, skeleton=skeleton, cameras=[_camera(2.0, 100.0), _camera(4.0, 100.0),
                                                                  _camera(9.0, 100.0)])
    frames = SimpleNamespace(video=video, indices=np.array([0, 1]), frame_ids=np.array([3, 4]),
                             bone_transforms=torch.eye(4).expand(2, 2, 4, 4))
    assert recorded_pixel_size(tmp_path) is None  # no training motion
    write_training_motion(frames, tmp_path / "training_poses.npz",
                          pixel_size=training_pixel_size([video.cameras[int(i)] for i in frames.indices],
                                                         frames.bone_transforms.numpy(), skeleton))
    assert recorded_pixel_size(tmp_path) == pytest.approx(0.03)  # the median of 0.02 and 0.04 (frame 2 unused)
    assert recorded_pixel_size(tmp_path / "avatar.pt") == pytest.approx(0.03)
    np.savez(tmp_path / "training_poses.npz", bone_transforms=np.zeros((1, 2, 4, 4)), frame_ids=[0])
    assert recorded_pixel_size(tmp_path) is None  # a fit from before the record
    np.savez(tmp_path / "training_poses.npz", **{PIXEL_SIZE_KEY: -1.0})
    with pytest.raises(ValueError, match="pixel_size must be a positive"):
        recorded_pixel_size(tmp_path)


class _TwoJointField:
    """A skinning field stub: joint 0 where x < 0, joint 1 elsewhere."""

    def grid_weights(self):
        return None

    def weights(self, points, grid):
        right = (points[:, 0] >= 0).float()
        return torch.stack([1.0 - right, right], dim=1)


def test_blended_weights_follow_the_gaussians_densities():
    means = torch.tensor([[-0.1, 0.0, 0.0], [0.1, 0.0, 0.0], [0.3, 0.0, 0.0]])
    scales = torch.tensor([[0.05, 0.1, 0.1], [0.1, 0.05, 0.05], [0.1, 0.1, 0.1]])
    quats = torch.nn.functional.normalize(torch.tensor([[1.0, 0.0, 0.0, 0.0], [0.9, 0.3, 0.1, 0.2],
                                                        [1.0, 0.0, 0.0, 0.0]]), dim=1)
    opacities = torch.tensor([0.9, 0.6, 0.01])  # the third below the floor: it carries no weight
    gaussians = SimpleNamespace(means=means, scales=scales, normalized_quats=quats, opacities=opacities[:, None])
    avatar = SimpleNamespace(gaussians=gaussians, field=_TwoJointField())
    points = torch.tensor([[0.0, 0.0, 0.0], [-0.12, 0.02, 0.0], [0.02, 0.05, -0.03], [40.0, 0.0, 0.0]])
    blended = gaussian_blended_weights(avatar, points)
    # by hand: each solid Gaussian's opacity times exp(-d^2 / 2), d the Mahalanobis distance in its own frame
    local = torch.einsum("kji,pkj->pki", quat_to_matrix(quats[:2]), points[:, None] - means[None, :2]) / scales[:2]
    density = opacities[:2] * torch.exp(-0.5 * local.square().sum(-1))
    expected = density / density.sum(1, keepdim=True)
    torch.testing.assert_close(blended[:3], expected[:3], atol=1e-5, rtol=1e-5)
    # a point no Gaussian reaches blends them by inverse squared distance
    inverse = 1.0 / (points[3] - means[:2]).square().sum(-1)
    torch.testing.assert_close(blended[3], inverse / inverse.sum(), atol=1e-5, rtol=1e-5)


def test_posed_views_show_the_motions_frames_at_the_training_pixel(export_avatar, export_motion):
    from warpavatar.mesh.views import body_gaussians, posed_frames, render_posed_views

    frames = posed_frames(export_motion.frame_count, 3)
    assert list(frames) == [0, 2, 4] and list(posed_frames(2, 3)) == [0, 1]
    views, view_frames = render_posed_views(export_avatar, export_motion, frames, pixel_size=0.02, cameras=2)
    assert len(views) == 6 and list(view_frames) == [0, 0, 1, 1, 2, 2]
    assert len({view.width for view in views}) == 1
    keep = body_gaussians(export_avatar)
    footprints = []
    with torch.no_grad():
        for view, position in zip(views, view_frames):
            t = int(frames[position])
            bones = torch.as_tensor(export_motion.bone_transforms[t])
            posed = export_avatar.pose(bones, frame_index=t, sh_degree=0)
            centre = ((posed["means"][keep].quantile(0.002, dim=0) + posed["means"][keep].quantile(0.998, dim=0)) / 2)
            z = float(torch.as_tensor(view.world_to_camera)[2, :3] @ centre.double().float()
                      + float(view.world_to_camera[2, 3]))
            footprints.append(z / float(view.K[0, 0]))
            assert view.alpha.max() > 0.9 and view.alpha[0].max() < 0.5  # the figure whole inside the frame
            if bool(keep.all()):  # the same image as rendering that frame's pose through the view's camera
                _, alpha, _ = export_avatar.render(view, bones, background=torch.zeros(3))
                np.testing.assert_allclose(view.alpha, alpha.numpy(), atol=1e-5)
    # the largest frame's box is seen at the training pixel, the others a little finer
    assert max(footprints) == pytest.approx(0.02, rel=0.02) and min(footprints) > 0.015
    with pytest.raises(ValueError, match="pixel size must be a positive"):
        render_posed_views(export_avatar, export_motion, frames, pixel_size=0.0)


def _posed_iou(avatar, mesh, motion, views, view_frames, frames) -> float:
    """Mean silhouette IoU of the skinned ``mesh`` (animated by ``motion``) against the Gaussians' ``views``."""
    from warpavatar import ops
    from warpavatar.mesh.skin import lbs_vertices, mesh_animation

    animation = mesh_animation(avatar, mesh, motion)
    scores = []
    for view, position in zip(views, view_frames):
        t = int(frames[position])
        offsets = None if animation.vertex_offsets is None else animation.vertex_offsets[t]
        vertices = torch.as_tensor(lbs_vertices(mesh, animation.joint_transforms[t], offsets))
        _, alpha, _ = ops.render_mesh(vertices, mesh.faces, torch.as_tensor(view.K),
                                      torch.as_tensor(view.world_to_camera), view.width, view.height)
        ours, theirs = alpha.numpy() >= 0.5, view.alpha >= 0.5
        scores.append((ours & theirs).sum() / max((ours | theirs).sum(), 1))
    return float(np.mean(scores))


def test_the_export_fits_the_skinned_mesh_to_the_gaussians_in_the_training_motion(export_avatar, export_motion):
    from conftest import small_avatar

    from warpavatar.mesh.build import build_avatar_mesh
    from warpavatar.mesh.surface import SILHOUETTE_ROUNDS
    from warpavatar.mesh.views import posed_frames, render_posed_views

    # denser Gaussians and a field distilled longer than the module's avatar: skin weights that a mesh's four
    # influences can follow, so that only the shape differs
    avatar = small_avatar(export_avatar.skeleton, seed=5, per_bone=12, cells=12, distill_steps=200)

    options = dict(triangles=4000, view_count=24, view_size=96, training_pixel_size=0.02, texture=False,
                   vertex_colors=False)
    plain_settings, fitted_settings = {}, {}
    plain = build_avatar_mesh(avatar, settings=plain_settings, **options)
    fitted = build_avatar_mesh(avatar, training_motion=export_motion, settings=fitted_settings, **options)
    assert plain_settings["silhouette_rounds"] == 0 and fitted_settings["silhouette_rounds"] == SILHOUETTE_ROUNDS
    assert np.array_equal(plain.faces, fitted.faces)  # only the vertices move
    # held-out views: other cameras than the export's (4 a frame, not 6), in the motion's frames
    frames = posed_frames(export_motion.frame_count)
    views, view_frames = render_posed_views(avatar, export_motion, frames, pixel_size=0.02, cameras=4)
    before = _posed_iou(avatar, plain, export_motion, views, view_frames, frames)
    after = _posed_iou(avatar, fitted, export_motion, views, view_frames, frames)
    assert after > before + 0.05 and after > 0.85, (before, after)  # 0.763 -> 0.887 when written
