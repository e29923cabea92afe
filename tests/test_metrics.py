"""Tests of warpavatar.metrics: PSNR, SSIM (against an independent scipy reference, scikit-image and the
implementation before evaluation's SSIM was made cheap), the differentiable SSIM map (gradients against finite
differences), masks, frames smaller than the window, bad input and LPIPS's offline fallback."""

import math
import warnings

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from scipy import ndimage

from warpavatar import metrics
from warpavatar.metrics import floater_share, image_scores, lpips, psnr, ssim, ssim_map


def _random_pair(seed, height=24, width=20, channels=3, noise=0.1):
    rng = np.random.default_rng(seed)
    target = rng.random((height, width, channels))
    pred = np.clip(target + noise * rng.standard_normal(target.shape), 0.0, 1.0)
    return pred, target


def _reference_ssim_map(pred, target):
    """SSIM map with scipy's Gaussian filter (truncate 3.5 -> 11 taps at sigma 1.5), cropped to valid pixels."""
    def blur(image):
        return np.stack([ndimage.gaussian_filter(image[..., c], sigma=1.5, truncate=3.5, mode="reflect")
                         for c in range(image.shape[-1])], axis=-1)
    mean_x, mean_y = blur(pred), blur(target)
    variance_x = blur(pred * pred) - mean_x ** 2
    variance_y = blur(target * target) - mean_y ** 2
    covariance = blur(pred * target) - mean_x * mean_y
    c1, c2 = 0.01 ** 2, 0.03 ** 2
    values = ((2 * mean_x * mean_y + c1) * (2 * covariance + c2)) / (
        (mean_x ** 2 + mean_y ** 2 + c1) * (variance_x + variance_y + c2))
    return values[5:-5, 5:-5]


def test_psnr_of_known_mse(device):
    target = torch.rand(16, 12, 3, device=device)
    for mse in (1e-2, 1e-3, 0.25):
        # A constant offset of sqrt(mse) gives exactly that MSE (no clipping needed: values may leave [0, 1]).
        pred = target + math.sqrt(mse)
        assert psnr(pred, target) == pytest.approx(-10 * math.log10(mse), abs=1e-4)
    assert psnr(target, target) == math.inf


def test_psnr_masked_averages_over_mask_pixels(device):
    target = torch.rand(10, 8, 3, device=device, dtype=torch.float64)
    pred = target.clone()
    mask = torch.zeros(10, 8, device=device)
    mask[2:5, 3:7] = 1.0
    pred[2:5, 3:7] += 0.1   # error only inside the mask
    pred[8:, :] += 0.5      # a large error outside the mask, which must not count
    assert psnr(pred, target, mask=mask) == pytest.approx(20.0, abs=1e-9)
    assert psnr(pred, target) < 20.0
    # uint8 0/255 masks, boolean masks and [H, W, 1] masks mean the same.
    mask_u8 = (mask * 255).to(torch.uint8)
    assert psnr(pred, target, mask=mask_u8) == pytest.approx(20.0, abs=1e-9)
    assert psnr(pred, target, mask=mask.bool()[..., None]) == pytest.approx(20.0, abs=1e-9)


def test_psnr_numpy_and_torch_agree():
    pred, target = _random_pair(0)
    value = psnr(pred, target)
    assert value == pytest.approx(psnr(torch.from_numpy(pred), torch.from_numpy(target)), abs=1e-9)
    assert value == pytest.approx(-10 * math.log10(np.mean((pred - target) ** 2)), abs=1e-9)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_ssim_matches_scipy_reference(seed):
    pred, target = _random_pair(seed)
    reference = _reference_ssim_map(pred, target)
    values = ssim_map(torch.from_numpy(pred), torch.from_numpy(target)).numpy()
    np.testing.assert_allclose(values, reference, atol=1e-10)
    assert ssim(pred, target) == pytest.approx(reference.mean(), abs=1e-10)


@pytest.mark.parametrize("seed", [0, 1])
def test_ssim_matches_skimage(seed):
    skimage_metrics = pytest.importorskip("skimage.metrics")
    pred, target = _random_pair(seed, height=32, width=28, noise=0.2)
    expected = skimage_metrics.structural_similarity(pred, target, gaussian_weights=True, sigma=1.5,
                                                     use_sample_covariance=False, data_range=1.0, channel_axis=-1)
    assert ssim(pred, target) == pytest.approx(expected, abs=1e-3)


def test_ssim_identity_symmetry_and_noise(device):
    pred, target = _random_pair(3, noise=0.05)
    pred_t = torch.from_numpy(pred).to(device)
    target_t = torch.from_numpy(target).to(device)
    assert ssim(target_t, target_t) == pytest.approx(1.0, abs=1e-12)
    assert ssim(pred_t, target_t) == pytest.approx(ssim(target_t, pred_t), abs=1e-12)
    noisier, _ = _random_pair(3, noise=0.3)
    assert ssim(noisier, target) < ssim(pred, target) < 1.0


def test_ssim_masked(device):
    pred, target = _random_pair(4)
    pred_t = torch.from_numpy(pred).to(device)
    target_t = torch.from_numpy(target).to(device)
    full = torch.ones(pred.shape[:2], device=device)
    assert ssim(pred_t, target_t, mask=full) == pytest.approx(ssim(pred_t, target_t), abs=1e-12)
    mask = np.zeros(pred.shape[:2])
    mask[6:14, 5:12] = 1.0
    expected = _reference_ssim_map(pred, target)[mask[5:-5, 5:-5] > 0.5].mean()
    assert ssim(pred_t, target_t, mask=torch.from_numpy(mask).to(device)) == pytest.approx(expected, abs=1e-10)
    # A mask that only covers the border (where the valid map has no pixel) is an error.
    border = np.zeros(pred.shape[:2])
    border[:3] = 1.0
    with pytest.raises(ValueError, match="mask selects no pixel"):
        ssim(pred, target, mask=border)


@pytest.mark.parametrize("padding", ["valid", "reflect", "zeros"])
def test_ssim_map_layouts_and_padding(device, padding):
    batch = torch.rand(2, 3, 16, 14, device=device)
    other = torch.rand(2, 3, 16, 14, device=device)
    values = ssim_map(batch, other, padding=padding)
    expected_size = (6, 4) if padding == "valid" else (16, 14)
    assert values.shape == (2, 3) + expected_size
    # [H, W, C] input gives the same numbers in channels-last layout.
    single = ssim_map(batch[1].permute(1, 2, 0), other[1].permute(1, 2, 0), padding=padding)
    torch.testing.assert_close(single, values[1].permute(1, 2, 0), atol=1e-6, rtol=1e-6)
    if padding == "reflect":
        # Reflect padding matches scipy's 'reflect' filter on every pixel, border included.
        pred = batch[0].permute(1, 2, 0).double().cpu().numpy()
        target = other[0].permute(1, 2, 0).double().cpu().numpy()
        full_map = ssim_map(torch.from_numpy(pred), torch.from_numpy(target), padding="reflect").numpy()
        np.testing.assert_allclose(full_map[5:-5, 5:-5], _reference_ssim_map(pred, target), atol=1e-10)


@pytest.mark.parametrize("seed", [0, 1])
def test_ssim_map_gradients_match_finite_differences(seed):
    generator = torch.Generator().manual_seed(seed)
    # Full Jacobian check on the smallest valid image (a 2-pixel map), both inputs.
    pred = torch.rand(1, 1, 11, 12, dtype=torch.float64, generator=generator, requires_grad=True)
    target = torch.rand(1, 1, 11, 12, dtype=torch.float64, generator=generator, requires_grad=True)
    assert torch.autograd.gradcheck(lambda a, b: ssim_map(a, b), (pred, target))
    # Padded maps: random directional derivatives against central differences (gradcheck's fast mode).
    pred = torch.rand(1, 2, 12, 13, dtype=torch.float64, generator=generator, requires_grad=True)
    target = torch.rand(1, 2, 12, 13, dtype=torch.float64, generator=generator, requires_grad=True)
    for padding in ("reflect", "zeros"):
        assert torch.autograd.gradcheck(lambda a, b: ssim_map(a, b, padding=padding), (pred, target),
                                        fast_mode=True)


def test_ssim_map_gradient_on_device_matches_cpu(device):
    generator = torch.Generator().manual_seed(5)
    pred = torch.rand(1, 3, 20, 18, generator=generator)
    target = torch.rand(1, 3, 20, 18, generator=generator)
    cotangent = torch.rand(1, 3, 20, 18, generator=generator)
    grads = []
    for where in ("cpu", device):
        a = pred.to(where).requires_grad_(True)
        loss = (ssim_map(a, target.to(where), padding="zeros") * cotangent.to(where)).sum()
        grads.append(torch.autograd.grad(loss, a)[0].cpu())
    torch.testing.assert_close(grads[1], grads[0], atol=1e-5, rtol=1e-4)
    # The loss gradient is not trivially zero.
    assert grads[0].abs().max() > 1e-3


def test_bad_inputs():
    pred, target = _random_pair(0)
    with pytest.raises(ValueError, match="same shape"):
        psnr(pred, target[:-1])
    with pytest.raises(TypeError, match="floating-point"):
        psnr((pred * 255).astype(np.uint8), target)
    with pytest.raises(TypeError, match="numpy array or a torch tensor"):
        psnr(pred.tolist(), target)
    with pytest.raises(ValueError, match=r"\[H, W, C\]"):
        ssim(pred[..., 0], target[..., 0])
    with pytest.raises(ValueError, match="finite"):
        bad = pred.copy()
        bad[0, 0, 0] = np.nan
        psnr(bad, target)
    with pytest.raises(ValueError, match="mask must have shape"):
        psnr(pred, target, mask=np.ones((3, 3)))
    with pytest.raises(ValueError, match="selects no pixel"):
        psnr(pred, target, mask=np.zeros(pred.shape[:2]))
    with pytest.raises(ValueError, match="smaller than"):
        ssim(pred[:8], target[:8])
    with pytest.raises(ValueError, match="padding"):
        ssim_map(torch.rand(12, 12, 3), torch.rand(12, 12, 3), padding="same")
    with pytest.raises(TypeError, match="dtype"):
        ssim_map(torch.rand(12, 12, 3), torch.rand(12, 12, 3, dtype=torch.float64))


def test_lpips_returns_none_without_local_weights_and_says_why_without_warning(monkeypatch, tmp_path):
    monkeypatch.setattr(torch.hub, "get_dir", lambda: str(tmp_path))  # an empty hub cache
    metrics._lpips_setup.cache_clear()
    metrics._lpips_network.cache_clear()
    pred, target = _random_pair(0, height=32, width=32)
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            assert lpips(pred, target) is None
            reason = metrics.lpips_unavailable_reason()
        assert caught == []  # the caller reports the reason: nothing goes through warnings (no source path)
        assert reason.endswith("; weights are never downloaded") and "\n" not in reason
        assert "metrics.py" not in reason
    finally:
        metrics._lpips_setup.cache_clear()
        metrics._lpips_network.cache_clear()


# ----------------------------------------------------------------------------------------------------------
# Evaluation's SSIM against the implementation it replaced


def _previous_ssim_map(pred, target, *, padding="valid", window_size=11, sigma=1.5, data_range=1.0):
    """The SSIM map as it was computed before (two grouped conv2d calls on every device), kept as the reference;
    the input checks are left out."""
    channels_last = pred.dim() == 3
    if channels_last:
        x = pred.permute(2, 0, 1).unsqueeze(0)
        y = target.permute(2, 0, 1).unsqueeze(0)
    else:
        x, y = pred, target
    channels = x.shape[1]
    radius = window_size // 2
    if padding == "valid" and (x.shape[2] < window_size or x.shape[3] < window_size):
        raise ValueError(f"ssim_map: images of {x.shape[2]}x{x.shape[3]} pixels are smaller than the "
                         f"{window_size}-pixel window; use padding='reflect' or 'zeros'")
    stacked = torch.cat([x, y, x * x, y * y, x * y], dim=1)
    if padding == "reflect":
        stacked = F.pad(stacked, (radius, radius, radius, radius), mode="reflect")
    elif padding == "zeros":
        stacked = F.pad(stacked, (radius, radius, radius, radius))
    groups = 5 * channels
    offsets = torch.arange(window_size, dtype=torch.float64, device=x.device) - (window_size - 1) / 2.0
    taps = torch.exp(-0.5 * (offsets / sigma) ** 2)
    taps = (taps / taps.sum()).to(x.dtype)
    vertical = taps.view(1, 1, window_size, 1).repeat(groups, 1, 1, 1)
    horizontal = taps.view(1, 1, 1, window_size).repeat(groups, 1, 1, 1)
    filtered = F.conv2d(F.conv2d(stacked, vertical, groups=groups), horizontal, groups=groups)
    mean_x, mean_y, mean_xx, mean_yy, mean_xy = filtered.split(channels, dim=1)
    c1, c2 = (0.01 * data_range) ** 2, (0.03 * data_range) ** 2
    mean_x_mean_y = mean_x * mean_y
    mean_x_sq, mean_y_sq = mean_x * mean_x, mean_y * mean_y
    values = ((2.0 * mean_x_mean_y + c1) * (2.0 * (mean_xy - mean_x_mean_y) + c2)) / (
        (mean_x_sq + mean_y_sq + c1) * ((mean_xx - mean_x_sq) + (mean_yy - mean_y_sq) + c2))
    return values[0].permute(1, 2, 0) if channels_last else values


def _previous_ssim(pred, target, *, mask=None):
    """:func:`ssim` as it was: the checked images' valid map, its mean over the cropped mask."""
    pred, target = metrics._check_image_pair(pred, target)
    values = _previous_ssim_map(pred, target)
    if mask is None:
        return float(values.mean())
    selected = metrics._check_mask(mask, pred.shape[0], pred.shape[1], pred.device)[5:-5, 5:-5]
    return float(values[selected].mean())


@pytest.mark.parametrize("height, width", [(11, 11), (11, 40), (23, 12), (64, 48), (131, 97)])
def test_ssim_equals_the_previous_implementation(device, height, width):
    generator = torch.Generator().manual_seed(height * 1000 + width)
    target = torch.rand(height, width, 3, generator=generator)
    pred = (target + 0.2 * torch.randn(height, width, 3, generator=generator)).clamp(0, 1)
    mask = torch.zeros(height, width)
    mask[height // 4:, : max(6, width * 3 // 4)] = 1.0
    pred, target, mask = pred.to(device), target.to(device), mask.to(device)
    expected_full = _previous_ssim(pred, target)
    expected_masked = _previous_ssim(pred, target, mask=mask)
    assert ssim(pred, target) == pytest.approx(expected_full, abs=1e-6)
    assert ssim(pred, target, mask=mask) == pytest.approx(expected_masked, abs=1e-6)
    scores = image_scores(pred, target, mask=mask)
    assert scores["ssim"] == pytest.approx(expected_full, abs=1e-6)
    assert scores["ssim_masked"] == pytest.approx(expected_masked, abs=1e-6)
    assert scores["psnr"] == psnr(pred, target) and scores["psnr_masked"] == psnr(pred, target, mask=mask)
    if pred.device.type == "cpu":  # float64 on the CPU: the same sums, far below the tolerance
        assert abs(ssim(pred, target) - expected_full) < 1e-12
    assert image_scores(pred, target) == {**scores, "psnr_masked": None, "ssim_masked": None}


@pytest.mark.parametrize("padding", ["valid", "reflect", "zeros"])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_ssim_map_without_gradients_on_cpu_equals_the_convolution(padding, dtype):
    # Without gradients the CPU filters by shifted multiply-adds; with them, by the convolution of before.
    generator = torch.Generator().manual_seed(7)
    pred = torch.rand(2, 3, 17, 29, generator=generator, dtype=dtype)
    target = torch.rand(2, 3, 17, 29, generator=generator, dtype=dtype)
    with torch.no_grad():
        fast = ssim_map(pred, target, padding=padding)
    with torch.enable_grad():
        convolved = ssim_map(pred.clone().requires_grad_(True), target, padding=padding)
    reference = _previous_ssim_map(pred, target, padding=padding)
    tolerance = 1e-12 if dtype == torch.float64 else 1e-5
    torch.testing.assert_close(fast, reference, atol=tolerance, rtol=0)
    torch.testing.assert_close(convolved.detach(), reference, atol=0, rtol=0)  # the training path is unchanged


@pytest.mark.parametrize("height, width", [(1, 1), (5, 5), (10, 30), (30, 10)])
def test_ssim_of_a_frame_smaller_than_its_window_is_one_line_naming_the_size(height, width):
    pred, target = _random_pair(0, height=height, width=width)
    message = f"ssim: the frame is {width}x{height} pixels, smaller than SSIM's 11x11-pixel window"
    for call in (lambda: ssim(pred, target), lambda: ssim(pred, target, mask=np.ones((height, width))),
                 lambda: image_scores(pred, target)):
        with pytest.raises(ValueError) as caught:
            call()
        assert str(caught.value).startswith(message) and "\n" not in str(caught.value)
        assert "padding" not in str(caught.value)  # ssim has no padding option to suggest
    # PSNR of such a frame stays defined.
    assert math.isfinite(psnr(pred, target))


def _square_mask(height=40, width=40, top=10, left=10, size=12):
    mask = torch.zeros(height, width)
    mask[top:top + size, left:left + size] = 1.0
    return mask


def test_floater_share_is_zero_for_opacity_inside_the_mask(device):
    mask = _square_mask().to(device)
    alpha = mask * torch.rand(40, 40, device=device)
    assert floater_share(alpha, mask) == 0.0
    assert floater_share(torch.zeros(40, 40, device=device), mask) == 0.0  # no opacity: nothing floats


def test_floater_share_of_a_blob_far_outside_the_mask_is_its_share(device):
    mask = _square_mask().to(device)
    alpha = mask * 0.5  # 144 pixels x 0.5 = 72 inside
    alpha[10:14, 32:36] = 1.0  # 16 pixels of opacity 10 px right of the mask (its last column is 21)
    assert floater_share(alpha, mask) == pytest.approx(16.0 / (72.0 + 16.0), abs=1e-6)
    assert floater_share(alpha.cpu().numpy(), mask.cpu().numpy()[..., None]) == pytest.approx(16.0 / 88.0, abs=1e-6)
    assert floater_share(alpha[..., None], mask > 0.5) == pytest.approx(16.0 / 88.0, abs=1e-6)


def test_floater_share_ignores_opacity_within_the_dilation_disc(device):
    mask = _square_mask().to(device)
    alpha = mask.clone()
    alpha[10:22, 22:25] = 1.0  # 1-3 px right of the mask's right edge (column 21)
    alpha[22:24, 22:24] = 1.0  # diagonally off the corner: at most sqrt(2^2 + 2^2) = 2.8 px from it
    assert floater_share(alpha, mask) == 0.0
    # a disc, not a square: the pixel 3 px right and 3 px below the corner (4.2 px away) counts
    alpha[24, 24] = 1.0
    assert floater_share(alpha, mask) == pytest.approx(1.0 / float(alpha.sum()), abs=1e-6)
    # 4 px right counts at the default radius, and not with a radius of 4
    alpha = mask.clone()
    alpha[10:22, 25] = 1.0
    assert floater_share(alpha, mask) == pytest.approx(12.0 / 156.0, abs=1e-6)
    assert floater_share(alpha, mask, dilation_px=4) == 0.0
    assert floater_share(alpha, mask, dilation_px=0) == pytest.approx(12.0 / 156.0, abs=1e-6)


def test_floater_share_refuses_bad_input():
    mask = _square_mask()
    with pytest.raises(ValueError, match="alpha must have shape"):
        floater_share(torch.zeros(40, 40, 3), mask)
    with pytest.raises(ValueError, match=r"mask must have shape \[40, 40\]"):
        floater_share(torch.zeros(40, 40), mask[:20])
    with pytest.raises(ValueError, match="dilation_px must be an integer >= 0"):
        floater_share(torch.zeros(40, 40), mask, dilation_px=-1)
    with pytest.raises(TypeError, match="floating-point opacity"):
        floater_share(torch.zeros(40, 40, dtype=torch.uint8), mask)
