"""tools/error_breakdown.py: the height-band region split, the ground-truth baselines and the needed-PSNR arithmetic."""

import importlib.util
import math
from pathlib import Path

import numpy as np
import pytest

from warpavatar import data

_TOOL = Path(__file__).resolve().parents[1] / "tools" / "error_breakdown.py"


@pytest.fixture(scope="module")
def tool():
    spec = importlib.util.spec_from_file_location("error_breakdown", _TOOL)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _camera(width=40, height=30, rotation=np.eye(3), translation=(0.1, -0.2, 3.0)):
    world_to_camera = np.eye(4, dtype=np.float32)
    world_to_camera[:3, :3] = rotation
    world_to_camera[:3, 3] = translation
    intrinsics = np.array([[50.0, 0, 19.5], [0, 55.0, 14.5], [0, 0, 1]], np.float32)
    return data.Camera(K=intrinsics, world_to_camera=world_to_camera, width=width, height=height)


def test_height_band_holds_the_pixels_whose_ray_crosses_the_slab_at_the_root_depth(tool):
    # a camera looking along world +y, with world z up (image rows grow downwards, so height falls with the row)
    rotation = np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]])
    camera = _camera(rotation=rotation, translation=(0.0, 0.3, 2.5))
    root = np.array([0.05, 0.4, 0.2])
    up = np.array([0.0, 0.0, 2.0])  # not normalized on purpose
    band = tool.height_band_mask(camera, root, up, low=0.1, high=0.25)
    # brute force: unproject each pixel centre to the root's camera depth, read its world height
    world_to_camera = camera.world_to_camera.astype(np.float64)
    depth = (world_to_camera[:3, :3] @ root + world_to_camera[:3, 3])[2]
    expected = np.zeros_like(band)
    inverse = np.linalg.inv(world_to_camera)
    for row in range(camera.height):
        for column in range(camera.width):
            point = np.array([(column - 19.5) / 50.0 * depth, (row - 14.5) / 55.0 * depth, depth, 1.0])
            height = (inverse @ point)[2]
            expected[row, column] = 0.1 < height < 0.25
    assert np.array_equal(band, expected)
    assert 0 < band.sum() < band.size
    # whole rows: the slab is horizontal and the camera level
    assert np.array_equal(band.all(axis=1), band.any(axis=1))


def test_references_blur_and_mean_fill(tool):
    rng = np.random.default_rng(3)
    truth = rng.uniform(0.1, 0.9, size=(24, 32, 3))
    mask = np.zeros((24, 32))
    mask[5:20, 8:25] = 1.0
    mean = tool.reference_image(truth, mask, "mean")
    assert np.allclose(mean[mask > 0.5], truth[mask > 0.5].mean(0))
    assert np.all(mean[mask < 0.5] == 0.0)
    blurred = tool.reference_image(truth, mask, "blur", blur_sigma=2.0)
    assert blurred.shape == truth.shape and blurred.std() < 0.5 * truth.std()
    with pytest.raises(ValueError, match="unknown reference"):
        tool.reference_image(truth, mask, "median")


def test_band_needed_inverts_the_pooled_psnr(tool):
    share, target = 0.45, 23.0
    needed = tool.band_needed(share, target)
    pooled = -10 * math.log10(share * 10 ** (-needed / 10))
    assert pooled == pytest.approx(target)
    outside = 27.0
    needed = tool.band_needed(share, target, outside_db=outside)
    pooled = -10 * math.log10(share * 10 ** (-needed / 10) + (1 - share) * 10 ** (-outside / 10))
    assert pooled == pytest.approx(target)
    # an outside region that alone already misses the target leaves no band PSNR that reaches it
    assert math.isnan(tool.band_needed(share, target, outside_db=19.0))
    assert math.isnan(tool.band_needed(0.0, target))


def test_breakdown_of_the_mean_fill_reference_on_the_demo(tool):
    video = data.load_video_folder(data.demo_subject_path() / "train", scale=0.5)
    values = tool.breakdown(None, video, stride=7, band=(0.3, 0.8), reference="mean")
    assert 0.0 < values["band share"] < 1.0
    # the two regions partition the mask: their share-weighted MSEs add up to the MSE pooled over every
    # masked pixel of the frames used, computed here directly
    error = count = 0.0
    for t in range(0, video.frame_count, 7):
        truth = video.images[t].astype(np.float64) / 255.0
        mask = video.masks[t].astype(np.float64) / 255.0
        prediction = tool.reference_image(truth, mask, "mean")
        error += float((((prediction - truth) ** 2).sum(-1) * mask).sum())
        count += float(mask.sum()) * 3
    mse = {key: 10 ** (-values[key] / 10) for key in ("band", "outside")}
    pooled = values["band share"] * mse["band"] + (1 - values["band share"]) * mse["outside"]
    assert -10 * math.log10(pooled) == pytest.approx(-10 * math.log10(error / count), abs=1e-6)
    assert 8.0 < -10 * math.log10(pooled) < 25.0
    assert all(math.isfinite(values[key]) for key in ("masked", "gain", "inner", "gain+inner"))


def test_shifted_image_moves_the_pixels_and_fills_with_the_background(tool):
    rng = np.random.default_rng(5)
    image = rng.uniform(0.1, 0.9, size=(12, 17, 3))
    fill = np.array([0.2, 0.4, 0.6])
    for columns, rows in ((3, 0), (-2, 0), (0, 4), (0, -1), (2, -3)):
        moved = tool.shifted_image(image, columns, rows, fill)
        for row in range(12):
            for column in range(17):
                source = (row - rows, column - columns)
                expected = image[source] if 0 <= source[0] < 12 and 0 <= source[1] < 17 else fill
                assert np.array_equal(moved[row, column], expected)
    assert np.array_equal(tool.shifted_image(image, 20, 0, fill), np.broadcast_to(fill, image.shape))


def test_the_shift_reference_loses_with_every_pixel_moved(tool):
    video = data.load_video_folder(data.demo_subject_path() / "train", scale=0.5)
    truth = video.images[0].astype(np.float64) / 255.0
    mask = video.masks[0].astype(np.float64) / 255.0
    moved = tool.reference_images(truth, mask, "shift", shift_px=3, background=video.background)
    assert len(moved) == 4 and all(m.shape == truth.shape for m in moved)
    assert np.array_equal(moved[0][:, 3:], truth[:, :-3]) and np.array_equal(moved[3][:-3], truth[3:])
    scores = [tool.breakdown(None, video, stride=5, band=(0.3, 0.8), reference="shift", shift_px=px)
              for px in (1, 2, 4)]
    for key in ("masked", "band", "outside"):
        assert scores[0][key] > scores[1][key] > scores[2][key], key
    # each frame's error is the mean of its four moves' errors
    frames = range(0, video.frame_count, 5)
    expected = []
    for t in frames:
        truth = video.images[t].astype(np.float64) / 255.0
        mask = video.masks[t].astype(np.float64) / 255.0
        errors = [10 ** (-tool.masked_psnr(m, truth, mask) / 10)
                  for m in tool.reference_images(truth, mask, "shift", shift_px=2, background=video.background)]
        expected.append(-10 * math.log10(np.mean(errors)))
    assert scores[1]["masked"] == pytest.approx(np.mean(expected), abs=1e-9)
    with pytest.raises(SystemExit):
        tool.main(["--reference", "shift", "--shift-px", "0", str(data.demo_subject_path() / "train")])
