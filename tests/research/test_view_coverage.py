"""research/view_coverage.py: which surface points a camera sees, and the seen share of a novel view's region."""

import dataclasses
import math
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from conftest import small_avatar
from research import view_coverage
from warpavatar import data

pytestmark = pytest.mark.research


@pytest.fixture(scope="module")
def tool():
    return view_coverage


def _camera(width=40, height=30, world_to_camera=None):
    intrinsics = np.array([[50.0, 0, 19.5], [0, 55.0, 14.5], [0, 0, 1]], np.float32)
    matrix = np.eye(4, dtype=np.float32) if world_to_camera is None else world_to_camera.astype(np.float32)
    return data.Camera(K=intrinsics, world_to_camera=matrix, width=width, height=height)


def test_surface_points_lie_behind_their_pixels_at_their_depth(tool):
    rng = np.random.default_rng(2)
    rotation, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    rotation *= np.sign(np.linalg.det(rotation))
    world_to_camera = np.eye(4)
    world_to_camera[:3, :3] = rotation
    world_to_camera[:3, 3] = rng.normal(size=3)
    camera = _camera(world_to_camera=world_to_camera)
    rows, columns = rng.integers(0, 30, size=50), rng.integers(0, 40, size=50)
    depth = rng.uniform(0.5, 4.0, size=50)
    points = tool.surface_points(camera, depth, rows, columns)
    pixels, back = camera.project(points)
    assert np.allclose(pixels, np.stack([columns, rows], 1), atol=1e-4)
    assert np.allclose(back, depth, atol=1e-5)


def test_seen_from_keeps_the_points_on_the_drawn_surface_only(tool):
    camera = _camera()
    surface = np.full((30, 40), 2.0)
    surface[:, 30:] = np.nan  # nothing drawn on the right
    rows, columns = np.meshgrid(np.arange(0, 30, 3), np.arange(0, 30, 3), indexing="ij")
    rows, columns = rows.ravel(), columns.ravel()
    on = tool.surface_points(camera, np.full(rows.shape, 2.0), rows, columns)
    assert tool.seen_from(on, camera, surface, tolerance=0.05).all()
    behind = tool.surface_points(camera, np.full(rows.shape, 2.2), rows, columns)
    assert not tool.seen_from(behind, camera, surface, tolerance=0.05).any()
    assert tool.seen_from(behind, camera, surface, tolerance=0.3).all()  # within a looser tolerance
    blank = tool.surface_points(camera, np.full(5, 2.0), np.arange(5), np.full(5, 33))
    assert not tool.seen_from(blank, camera, surface, tolerance=0.5).any()
    outside = np.array([[5.0, 0.0, 2.0], [0.0, -5.0, 2.0], [0.0, 0.0, -2.0]])  # beyond the frame, behind the camera
    assert not tool.seen_from(outside, camera, surface, tolerance=10.0).any()


def _turned(video, degrees):
    """The video's fixed camera moved round the vertical axis through the root's mean posed position."""
    root = video.joint_positions[:, 0].mean(0).astype(np.float64)
    angle = math.radians(degrees)
    turn = np.eye(4)
    turn[:2, :2] = [[math.cos(angle), -math.sin(angle)], [math.sin(angle), math.cos(angle)]]
    to_root, back = np.eye(4), np.eye(4)
    to_root[:3, 3], back[:3, 3] = -root, root
    camera = video.cameras[0]
    moved = data.Camera(K=camera.K, world_to_camera=(camera.world_to_camera @ back @ turn @ to_root).astype(np.float32),
                        width=camera.width, height=camera.height)
    return dataclasses.replace(video, cameras=[moved] * video.frame_count)


class _Sphere:
    """A stand-in avatar: an opaque sphere, ray-cast exactly (what ``coverage_rows`` uses of an avatar)."""

    def __init__(self, centre, radius):
        self.centre, self.radius = np.asarray(centre, np.float64), radius
        self.gaussians = SimpleNamespace(means=torch.zeros(1, 3))
        self.field = SimpleNamespace(grid_weights=lambda: torch.zeros(1))

    def prepare_sequence(self, *args, **kwargs):
        pass

    def render(self, camera, bones, *, frame_index, grid, background):
        world_to_camera = camera.world_to_camera.astype(np.float64)
        rows, columns = np.mgrid[0:camera.height, 0:camera.width].astype(np.float64)
        pixels = np.stack([columns, rows, np.ones_like(rows)]).reshape(3, -1)
        rays = np.linalg.solve(camera.K.astype(np.float64), pixels)
        centre = world_to_camera[:3, :3] @ self.centre + world_to_camera[:3, 3]  # camera space
        # |t * ray - centre| = radius for the nearest t > 0; depth = t (rays have z = 1)
        a, b = (rays**2).sum(0), (rays * centre[:, None]).sum(0)
        disc = b**2 - a * ((centre**2).sum() - self.radius**2)
        hit = disc > 0
        depth = np.where(hit, (b - np.sqrt(np.maximum(disc, 0.0))) / a, 0.0).reshape(rows.shape)
        alpha = hit.reshape(rows.shape).astype(np.float64)
        image = np.stack([alpha * 0.5, alpha * 0.25, alpha * 0.75], -1)
        return (torch.as_tensor(image, dtype=torch.float32), torch.as_tensor(alpha, dtype=torch.float32),
                torch.as_tensor(depth * alpha, dtype=torch.float32))


def test_a_sphere_is_seen_whole_from_its_camera_in_part_from_the_side_and_not_from_behind(tool):
    video = data.load_video_folder(data.demo_subject_path() / "train", max_frames=2, scale=0.5)
    # a fixed camera 3 units from the origin along -y, looking along +y (world z up), and a sphere at the origin
    looking = np.array([[1.0, 0, 0, 0], [0, 0, -1, 0], [0, 1, 0, 3.0], [0, 0, 0, 1]])
    camera = data.Camera(K=np.array([[250.0, 0, 79.5], [0, 250.0, 79.5], [0, 0, 1]]), world_to_camera=looking,
                         width=160, height=160)  # (a pixel: 1.2 cm at the sphere)
    truth = np.full((2, 160, 160, 3), 128, np.uint8)
    train = dataclasses.replace(video, images=truth, masks=np.full((2, 160, 160), 255, np.uint8),
                                cameras=[camera] * 2, joint_positions=np.zeros((2, 1, 3), np.float32))
    subject = SimpleNamespace(train=train, novel_view={name: _turned(train, angle) for name, angle in
                                                       (("same", 0.0), ("side", 90.0), ("behind", 180.0))})
    rows = {row["view"]: row for row in tool.coverage_rows(_Sphere([0, 0, 0], 0.6), subject, band=(-10.0, 10.0),
                                                             tolerance=0.05)}
    seen = {name: row["seen share"] / (1.0 - row["uncovered share"]) for name, row in rows.items()}
    assert all(row["frames"] == 2 and row["pixels"] == 2 * 160 * 160 for row in rows.values())
    assert rows["same"]["uncovered share"] == pytest.approx(rows["behind"]["uncovered share"], abs=1e-3)
    assert seen["same"] == 1.0
    assert seen["behind"] < 0.03  # a thin ring at the rim, within the tolerance
    # From 3 units a camera sees the cap within acos(0.6 / 3) of its axis; the side camera's disk shows the
    # training camera's cap where x > 0.2 (x across the disk, in units of its radius, towards the training
    # camera): (acos(0.2) - 0.2 sqrt(0.96)) / pi = 0.373 of it, a little less where depth steepens at the rim.
    assert 0.28 < seen["side"] < 0.38
    assert rows["same"]["psnr seen"] == pytest.approx(rows["side"]["psnr seen"])  # the same colours drawn


def test_the_same_camera_sees_every_pixel_it_covers_on_a_fitted_like_avatar(tool):
    video = data.load_video_folder(data.demo_subject_path() / "train", max_frames=4, scale=0.5)
    avatar = small_avatar(video.skeleton, seed=7, per_bone=40, cells=10, distill_steps=20)
    subject = SimpleNamespace(train=video, novel_view={"same": video, "behind": _turned(video, 180.0)})
    rows = {row["view"]: row for row in tool.coverage_rows(avatar, subject, band=(-10.0, 10.0), tolerance=0.03)}
    same = rows["same"]
    assert same["frames"] == 4 and same["pixels"] > 0
    assert same["seen share"] > 0.9 * (1.0 - same["uncovered share"])  # but for depth blends at the edges
    assert rows["behind"]["seen share"] < same["seen share"]
    # the pooled PSNR splits into its seen and unseen parts
    for row in rows.values():
        share = row["seen share"]
        pooled = share * 10 ** (-row["psnr seen"] / 10) + (1 - share) * 10 ** (-row["psnr unseen"] / 10)
        assert -10 * math.log10(pooled) == pytest.approx(row["psnr"], abs=1e-6)
    # the 'needed' arithmetic: the unseen pixels at that score, the seen ones perfect, give the target
    needed = tool._needed(same, 18.0)
    assert -10 * math.log10((1 - same["seen share"]) * 10 ** (-needed / 10)) == pytest.approx(18.0)
    with pytest.raises(ValueError, match="not one of the training frames"):
        later = dataclasses.replace(video, frame_ids=video.frame_ids + 1000)
        tool.coverage_rows(avatar, SimpleNamespace(train=video, novel_view={"later": later}), band=(-10.0, 10.0))


def test_bad_arguments_are_one_line_errors(tool, tmp_path, capsys):
    assert tool.main([str(tmp_path / "none.pt"), str(tmp_path / "nowhere")]) == 2
    error = capsys.readouterr().err.strip()
    assert "nowhere" in error and "\n" not in error
    with pytest.raises(SystemExit):
        tool.main([str(tmp_path / "none.pt"), str(tmp_path), "--depth-tolerance", "0"])
