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
