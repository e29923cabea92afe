"""Tests of warpavatar.metrics: PSNR, SSIM (against an independent scipy reference and scikit-image), the
differentiable SSIM map (gradients against finite differences), masks, bad input and LPIPS's offline fallback."""

import math
import warnings

import numpy as np
import pytest
import torch
from scipy import ndimage

from warpavatar import metrics
from warpavatar.metrics import lpips, psnr, ssim, ssim_map


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


def test_lpips_returns_none_without_local_weights(monkeypatch, tmp_path):
    monkeypatch.setattr(torch.hub, "get_dir", lambda: str(tmp_path))  # an empty hub cache
    metrics._lpips_network.cache_clear()
    pred, target = _random_pair(0, height=32, width=32)
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            assert lpips(pred, target) is None
        assert any("never downloaded" in str(warning.message) for warning in caught)
    finally:
        metrics._lpips_network.cache_clear()
