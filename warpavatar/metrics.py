"""Image metrics: PSNR, SSIM (value and differentiable map) and, when its weights are on disk, LPIPS.

Images are float RGB in [0, 1]. :func:`psnr` and :func:`ssim` take ``[H, W, C]`` numpy arrays or torch
tensors and return Python floats (evaluation); :func:`image_scores` gives both, over the full frame and inside
a mask, from one SSIM map (what an evaluation reports per frame); :func:`ssim_map` is plain torch,
differentiable and batched, for training losses (``1 - ssim_map(pred, target).mean()``). A mask restricts a
metric to the pixels where ``mask > 0.5`` (so 0/1 floats, booleans and 0/255 ``uint8`` masks all work).

SSIM follows Wang et al. 2004: an 11-tap Gaussian window with sigma 1.5, ``C1 = (0.01 L)^2`` and
``C2 = (0.03 L)^2`` with the data range ``L = 1``, computed per channel and averaged over the pixels whose
window lies inside the image (as ``skimage.metrics.structural_similarity(..., gaussian_weights=True,
sigma=1.5, use_sample_covariance=False, data_range=1)`` does). A frame smaller than the window has no
such pixel: :func:`ssim` refuses it, naming its size.

:func:`floater_share` measures what masked PSNR cannot see: the share of the rendered opacity that lies outside
the ground-truth mask dilated by a few pixels (Gaussians floating beside the figure, or a blur that spreads it).

LPIPS runs only from weights already on disk; without them :func:`lpips` returns None and
:func:`lpips_unavailable_reason` says why, for the caller to report (nothing is printed here).
"""

from __future__ import annotations

import functools
import importlib.util
import math
import os
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

__all__ = ["psnr", "ssim", "image_scores", "floater_share", "ssim_map", "lpips", "lpips_unavailable_reason",
           "image_loss_terms", "SSIM_WINDOW_SIZE", "SSIM_SIGMA", "FLOATER_DILATION_PX"]

SSIM_WINDOW_SIZE = 11
"""Taps of SSIM's Gaussian window (per axis)."""

SSIM_SIGMA = 1.5
"""Standard deviation of SSIM's Gaussian window [pixels]."""

FLOATER_DILATION_PX = 3
"""Radius [pixels] of the disc the ground-truth mask is dilated by before :func:`floater_share` counts opacity
outside it."""

_SSIM_K1 = 0.01
_SSIM_K2 = 0.03
_PADDINGS = ("valid", "reflect", "zeros")


def _as_tensor(value, name: str) -> torch.Tensor:
    if isinstance(value, torch.Tensor):
        return value
    if isinstance(value, np.ndarray):
        return torch.from_numpy(np.ascontiguousarray(value))
    raise TypeError(f"{name} must be a numpy array or a torch tensor, got {type(value).__name__}")


def _check_image_pair(pred, target) -> tuple[torch.Tensor, torch.Tensor]:
    """Both images as float tensors [H, W, C] on one device: float64 on CPU, at least float32 on GPU."""
    pred = _as_tensor(pred, "pred").detach()
    target = _as_tensor(target, "target").detach()
    for name, image in (("pred", pred), ("target", target)):
        if not image.is_floating_point():
            raise TypeError(f"{name} must be a floating-point image in [0, 1], got {image.dtype}")
        if image.dim() != 3:
            raise ValueError(f"{name} must have shape [H, W, C], got {list(image.shape)}")
    if pred.shape != target.shape:
        raise ValueError(f"pred and target must have the same shape, got {list(pred.shape)} and {list(target.shape)}")
    if pred.device != target.device:
        target = target.to(pred.device)
    dtype = torch.float64 if pred.device.type == "cpu" else torch.promote_types(
        torch.promote_types(pred.dtype, target.dtype), torch.float32)
    pred, target = pred.to(dtype), target.to(dtype)
    if not bool(torch.isfinite(pred).all()) or not bool(torch.isfinite(target).all()):
        raise ValueError("pred and target must be finite (no nan or inf)")
    return pred, target


def _check_mask(mask, height: int, width: int, device: torch.device) -> torch.Tensor:
    """The mask as a bool tensor [H, W] (``mask > 0.5``)."""
    mask = _as_tensor(mask, "mask").detach().to(device)
    if mask.dim() == 3 and mask.shape[-1] == 1:
        mask = mask[..., 0]
    if mask.shape != (height, width):
        raise ValueError(f"mask must have shape [{height}, {width}] (or [{height}, {width}, 1]), "
                         f"got {list(mask.shape)}")
    if mask.dtype == torch.bool:
        return mask
    if mask.is_floating_point() and not bool(torch.isfinite(mask).all()):
        raise ValueError("mask must be finite")
    return mask > 0.5


def psnr(pred, target, *, mask=None) -> float:
    """Peak signal-to-noise ratio [dB] of two images in [0, 1]: ``10 log10(1 / MSE)``.

    Args:
        pred: image, shape [H, W, C], floating point (numpy or torch, any device).
        target: reference image, same shape.
        mask: optional [H, W] (or [H, W, 1]); the squared error is then averaged over the pixels with
            ``mask > 0.5`` and all channels.

    Returns:
        PSNR in dB; ``inf`` when the images are equal (on the mask).

    Raises:
        TypeError: non-floating images or non-array inputs.
        ValueError: shape mismatch, non-finite values, or a mask that selects no pixel.
    """
    pred, target = _check_image_pair(pred, target)
    selected = None if mask is None else _check_mask(mask, pred.shape[0], pred.shape[1], pred.device)
    return _psnr_of_checked(pred, target, selected)


def _psnr_of_checked(pred: torch.Tensor, target: torch.Tensor, selected: torch.Tensor | None) -> float:
    """:func:`psnr` of checked images, over the pixels of the bool mask ``selected`` [H, W] (None: all)."""
    squared_error = (pred - target).square()
    if selected is not None:
        if not bool(selected.any()):
            raise ValueError("psnr: the mask selects no pixel")
        squared_error = squared_error[selected]
    mse = float(squared_error.mean()) if squared_error.numel() else float("nan")
    if math.isnan(mse):
        raise ValueError("psnr: the images are empty")
    return math.inf if mse == 0.0 else -10.0 * math.log10(mse)


@functools.lru_cache(maxsize=32)
def _gaussian_window(window_size: int, sigma: float, groups: int, device: torch.device,
                     dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor]:
    """Separable, normalized Gaussian window as grouped conv2d weights: [groups, 1, K, 1] and [groups, 1, 1, K].

    Built once per device and dtype (on the device itself: no host-to-device copy in the training loop).
    """
    offsets = torch.arange(window_size, dtype=torch.float64, device=device) - (window_size - 1) / 2.0
    taps = torch.exp(-0.5 * (offsets / sigma) ** 2)
    taps = (taps / taps.sum()).to(dtype)
    vertical = taps.view(1, 1, window_size, 1).repeat(groups, 1, 1, 1)
    horizontal = taps.view(1, 1, 1, window_size).repeat(groups, 1, 1, 1)
    return vertical, horizontal


@functools.lru_cache(maxsize=32)
def _gaussian_taps(window_size: int, sigma: float) -> tuple[float, ...]:
    """The ``window_size`` weights of a normalized 1D Gaussian of standard deviation ``sigma`` [pixels] (those of
    :func:`_gaussian_window` on the CPU, as Python floats)."""
    offsets = torch.arange(window_size, dtype=torch.float64) - (window_size - 1) / 2.0
    taps = torch.exp(-0.5 * (offsets / sigma) ** 2)
    return tuple(float(tap) for tap in taps / taps.sum())


def _filter_valid(stacked: torch.Tensor, window_size: int, sigma: float) -> torch.Tensor:
    """Every channel of ``stacked`` [B, N, H, W] filtered by the separable Gaussian window, valid pixels only:
    [B, N, H - K + 1, W - K + 1].

    Two grouped ``conv2d`` calls, except on the CPU without gradients (evaluation), where ``K`` shifted
    multiply-adds per axis do the same sums in the same order of taps: float64 grouped convolutions on the CPU
    take a slow path, 2-3 times slower than these memory-bound passes.
    """
    if stacked.device.type != "cpu" or (torch.is_grad_enabled() and stacked.requires_grad):
        groups = stacked.shape[1]
        vertical, horizontal = _gaussian_window(window_size, sigma, groups, stacked.device, stacked.dtype)
        return F.conv2d(F.conv2d(stacked, vertical, groups=groups), horizontal, groups=groups)
    taps = _gaussian_taps(window_size, sigma)
    height, width = stacked.shape[2] - window_size + 1, stacked.shape[3] - window_size + 1
    rows = stacked[:, :, 0:height] * taps[0]
    for offset in range(1, window_size):
        rows.add_(stacked[:, :, offset:offset + height], alpha=taps[offset])
    filtered = rows[..., 0:width] * taps[0]
    for offset in range(1, window_size):
        filtered.add_(rows[..., offset:offset + width], alpha=taps[offset])
    return filtered


def ssim_map(pred: torch.Tensor, target: torch.Tensor, *, padding: str = "valid", window_size: int = SSIM_WINDOW_SIZE,
             sigma: float = SSIM_SIGMA, data_range: float = 1.0) -> torch.Tensor:
    """Per-pixel, per-channel SSIM of two images (differentiable; gradients flow to both inputs).

    The five local statistics (means, variances, covariance) of all channels and images are filtered together
    by one separable Gaussian filter (two grouped ``conv2d`` calls; without gradients on the CPU, shifted
    multiply-adds, see :func:`_filter_valid`), so the cost is a handful of kernels on GPU.

    Args:
        pred: ``[H, W, C]`` (channels last, as the video folder's images) or ``[B, C, H, W]`` (channels
            first, torch's batch layout); floating point.
        target: same shape, dtype and device as ``pred``.
        padding: ``"valid"``: only pixels whose window lies inside the image (the map shrinks by
            ``window_size - 1`` per axis; the standard SSIM value is its mean); ``"reflect"`` or
            ``"zeros"``: pad the image so the map keeps the image's size (handy with masks; zeros biases the
            border, as in 3D Gaussian splatting's training loss).
        window_size: taps of the Gaussian window per axis, odd.
        sigma: standard deviation of the window [pixels].
        data_range: ``L`` in ``C1 = (0.01 L)^2`` and ``C2 = (0.03 L)^2`` (1 for images in [0, 1]).

    Returns:
        SSIM values in the layout of the input: ``[H', W', C]`` or ``[B, C, H', W']``, with ``H' = H``
        unless ``padding="valid"`` (``H' = H - window_size + 1``).
    """
    if not isinstance(pred, torch.Tensor) or not isinstance(target, torch.Tensor):
        raise TypeError("ssim_map: pred and target must be torch tensors")
    if not pred.is_floating_point() or pred.dtype != target.dtype:
        raise TypeError(f"ssim_map: pred and target must share one floating dtype, got {pred.dtype} and {target.dtype}")
    if pred.shape != target.shape:
        raise ValueError(f"ssim_map: pred and target must have the same shape, got {list(pred.shape)} and "
                         f"{list(target.shape)}")
    if pred.device != target.device:
        raise ValueError(f"ssim_map: pred and target must be on one device, got {pred.device} and {target.device}")
    if padding not in _PADDINGS:
        raise ValueError(f"ssim_map: padding must be one of {_PADDINGS}, got {padding!r}")
    if isinstance(window_size, bool) or not isinstance(window_size, int) or window_size < 1 or window_size % 2 == 0:
        raise ValueError(f"ssim_map: window_size must be a positive odd integer, got {window_size!r}")
    if not (sigma > 0 and math.isfinite(sigma)) or not (data_range > 0 and math.isfinite(data_range)):
        raise ValueError(f"ssim_map: sigma and data_range must be positive, got {sigma} and {data_range}")
    channels_last = pred.dim() == 3
    if channels_last:
        x = pred.permute(2, 0, 1).unsqueeze(0)
        y = target.permute(2, 0, 1).unsqueeze(0)
    elif pred.dim() == 4:
        x, y = pred, target
    else:
        raise ValueError(f"ssim_map: images must be [H, W, C] or [B, C, H, W], got {list(pred.shape)}")
    batch, channels, height, width = x.shape
    radius = window_size // 2
    if padding == "valid" and (height < window_size or width < window_size):
        raise ValueError(f"ssim_map: images of {height}x{width} pixels are smaller than the {window_size}-pixel "
                         "window; use padding='reflect' or 'zeros'")
    if padding == "reflect" and (height <= radius or width <= radius):
        raise ValueError(f"ssim_map: reflect padding needs images larger than {radius} pixels, got {height}x{width}")
    if batch == 0 or channels == 0 or height == 0 or width == 0:
        raise ValueError(f"ssim_map: empty images, shape {list(pred.shape)}")

    # Statistics to filter, stacked on the channel axis: [B, 5C, H, W].
    stacked = torch.cat([x, y, x * x, y * y, x * y], dim=1)
    if padding == "reflect":
        stacked = F.pad(stacked, (radius, radius, radius, radius), mode="reflect")
    elif padding == "zeros":
        stacked = F.pad(stacked, (radius, radius, radius, radius))
    filtered = _filter_valid(stacked, window_size, float(sigma))
    mean_x, mean_y, mean_xx, mean_yy, mean_xy = filtered.split(channels, dim=1)

    c1 = (_SSIM_K1 * data_range) ** 2
    c2 = (_SSIM_K2 * data_range) ** 2
    mean_x_mean_y = mean_x * mean_y
    mean_x_sq = mean_x * mean_x
    mean_y_sq = mean_y * mean_y
    variance_x = mean_xx - mean_x_sq
    variance_y = mean_yy - mean_y_sq
    covariance = mean_xy - mean_x_mean_y
    values = ((2.0 * mean_x_mean_y + c1) * (2.0 * covariance + c2)) / (
        (mean_x_sq + mean_y_sq + c1) * (variance_x + variance_y + c2))
    if channels_last:
        return values[0].permute(1, 2, 0)
    return values


def image_loss_terms(image: torch.Tensor, target: torch.Tensor, *, lambda_ssim: float,
                     alpha: torch.Tensor | None = None, mask: torch.Tensor | None = None,
                     lambda_mask: float = 0.0) -> dict[str, tuple[float, torch.Tensor]]:
    """The image terms a fit minimizes, ``{name: (weight, value)}``: ``l1`` (weight ``1 - lambda_ssim``) and
    ``dssim`` (1 - SSIM, weight ``lambda_ssim``) of ``image`` against ``target`` [H,W,3], and ``mask`` (L1 of the
    rendered ``alpha`` against ``mask`` [H,W], weight ``lambda_mask``) when both are given and the weight is
    positive. Differentiable."""
    terms = {"l1": (1.0 - lambda_ssim, (image - target).abs().mean()),
             "dssim": (lambda_ssim, 1.0 - ssim_map(image, target).mean())}
    if alpha is not None and mask is not None and lambda_mask > 0:
        terms["mask"] = (lambda_mask, (alpha - mask).abs().mean())
    return terms


def ssim(pred, target, *, mask=None) -> float:
    """Structural similarity of two images in [0, 1] (standard SSIM: Gaussian window 11, sigma 1.5).

    Args:
        pred: image, shape [H, W, C] with H, W >= 11, floating point (numpy or torch, any device).
        target: reference image, same shape.
        mask: optional [H, W] (or [H, W, 1]); the SSIM map (valid pixels only, see :func:`ssim_map`) is then
            averaged over the pixels with ``mask > 0.5`` (the mask cropped like the map) and all channels.
            An all-ones mask gives the unmasked value.

    Returns:
        Mean SSIM, at most 1 (equal images give exactly 1).

    Raises:
        TypeError: non-floating images or non-array inputs.
        ValueError: shape mismatch, a frame smaller than the window (the message gives its size), non-finite
            values, or a mask that selects no valid pixel.
    """
    pred, target = _check_image_pair(pred, target)
    values = _valid_ssim_map(pred, target)
    if mask is None:
        return float(values.mean())
    return _masked_ssim(values, _check_mask(mask, pred.shape[0], pred.shape[1], pred.device))


def image_scores(pred, target, *, mask=None) -> dict[str, float | None]:
    """PSNR and SSIM of one frame over the full frame and, with ``mask``, inside it: the values of :func:`psnr`
    and :func:`ssim`, with the inputs checked once and one SSIM map for both SSIM means.

    Args:
        pred, target: images as for :func:`ssim` ([H, W, C], H, W >= 11).
        mask: optional [H, W] (or [H, W, 1]), as for :func:`psnr` and :func:`ssim`.

    Returns:
        ``{"psnr": dB, "ssim": value, "psnr_masked": dB or None, "ssim_masked": value or None}`` (None without
        a mask).

    Raises:
        TypeError, ValueError: as :func:`psnr` and :func:`ssim`.
    """
    pred, target = _check_image_pair(pred, target)
    values = _valid_ssim_map(pred, target)
    scores = {"psnr": _psnr_of_checked(pred, target, None), "ssim": float(values.mean()), "psnr_masked": None,
              "ssim_masked": None}
    if mask is not None:
        selected = _check_mask(mask, pred.shape[0], pred.shape[1], pred.device)
        scores["psnr_masked"] = _psnr_of_checked(pred, target, selected)
        scores["ssim_masked"] = _masked_ssim(values, selected)
    return scores


def floater_share(alpha, mask, *, dilation_px: int = FLOATER_DILATION_PX) -> float:
    """Share of the rendered opacity outside the ground-truth mask dilated by ``dilation_px`` pixels.

    ``sum(alpha outside the dilated mask) / sum(alpha)``. The mask (``mask > 0.5``) is dilated by a disc of
    radius ``dilation_px``: a pixel is inside the dilated mask when a mask pixel lies within Euclidean distance
    ``dilation_px`` of it (pixel centres), so opacity up to ``dilation_px`` pixels beside the silhouette does not
    count (a mask boundary off by a pixel or two, anti-aliasing). A render whose opacity is all within the
    figure scores 0; one whose opacity is all elsewhere scores 1. Masked PSNR and SSIM look only inside the mask,
    so a misplaced or blurred figure that leaves the mask's pixels plausible shows up here instead.

    Args:
        alpha: rendered opacity, shape [H, W] (or [H, W, 1]), floating point in [0, 1] (numpy or torch).
        mask: ground-truth mask, shape [H, W] (or [H, W, 1]), as for :func:`psnr`.
        dilation_px: radius of the dilation disc [pixels], >= 0 (0: the mask itself).

    Returns:
        The share in [0, 1]; 0 when the render has no opacity at all.

    Raises:
        TypeError: a non-floating alpha or non-array inputs.
        ValueError: shape mismatch, non-finite alpha, or a negative ``dilation_px``.
    """
    alpha = _as_tensor(alpha, "alpha").detach()
    if not alpha.is_floating_point():
        raise TypeError(f"alpha must be a floating-point opacity in [0, 1], got {alpha.dtype}")
    if alpha.dim() == 3 and alpha.shape[-1] == 1:
        alpha = alpha[..., 0]
    if alpha.dim() != 2:
        raise ValueError(f"alpha must have shape [H, W] (or [H, W, 1]), got {list(alpha.shape)}")
    if isinstance(dilation_px, bool) or not isinstance(dilation_px, int) or dilation_px < 0:
        raise ValueError(f"floater_share: dilation_px must be an integer >= 0, got {dilation_px!r}")
    alpha = alpha.to(torch.float64 if alpha.device.type == "cpu" else torch.promote_types(alpha.dtype, torch.float32))
    if not bool(torch.isfinite(alpha).all()):
        raise ValueError("alpha must be finite (no nan or inf)")
    selected = _check_mask(mask, alpha.shape[0], alpha.shape[1], alpha.device)
    total = float(alpha.sum())
    if total <= 0.0:
        return 0.0
    dilated = _dilate_disc(selected, dilation_px)
    return float(alpha[~dilated].sum()) / total


def _dilate_disc(selected: torch.Tensor, radius: int) -> torch.Tensor:
    """The bool mask ``selected`` [H, W] dilated by a disc of ``radius`` pixels (Euclidean distance between pixel
    centres at most ``radius``): one convolution with the disc's 0/1 taps."""
    if radius == 0 or not bool(selected.any()):
        return selected
    offsets = torch.arange(-radius, radius + 1, device=selected.device, dtype=torch.float32)
    disc = ((offsets[:, None] ** 2 + offsets[None, :] ** 2) <= radius * radius + 1e-6).float()
    counts = F.conv2d(selected.float()[None, None], disc[None, None], padding=radius)[0, 0]
    return counts > 0.5


def _valid_ssim_map(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """The valid SSIM map of two checked [H, W, C] images; a frame smaller than the window is refused."""
    height, width = pred.shape[0], pred.shape[1]
    if height < SSIM_WINDOW_SIZE or width < SSIM_WINDOW_SIZE:
        raise ValueError(f"ssim: the frame is {width}x{height} pixels, smaller than SSIM's {SSIM_WINDOW_SIZE}x"
                         f"{SSIM_WINDOW_SIZE}-pixel window (SSIM needs frames of at least {SSIM_WINDOW_SIZE}x"
                         f"{SSIM_WINDOW_SIZE})")
    return ssim_map(pred, target, padding="valid")


def _masked_ssim(values: torch.Tensor, selected: torch.Tensor) -> float:
    """Mean of the valid SSIM map ``values`` [H', W', C] over the pixels of the bool mask ``selected`` [H, W]
    (cropped like the map)."""
    radius = SSIM_WINDOW_SIZE // 2
    selected = selected[radius:selected.shape[0] - radius, radius:selected.shape[1] - radius]
    if not bool(selected.any()):
        raise ValueError(f"ssim: the mask selects no pixel at least {radius} pixels from the border")
    return float(values[selected].mean())


# ----------------------------------------------------------------------------------------------------------
# LPIPS, only from weights already on disk: nothing is ever downloaded.


def _alexnet_checkpoint() -> Path | None:
    """torchvision's ImageNet AlexNet weights in torch hub's cache, if present."""
    try:
        from torchvision.models import AlexNet_Weights

        file_name = os.path.basename(AlexNet_Weights.IMAGENET1K_V1.url)
    except Exception:  # older or missing torchvision
        file_name = "alexnet-owt-7be5be79.pth"
    path = Path(torch.hub.get_dir()) / "checkpoints" / file_name
    return path if path.is_file() else None


def lpips_unavailable_reason() -> str | None:
    """Why :func:`lpips` cannot run here, as one line (e.g. "the 'lpips' package is not installed"), or None
    when its package and both weight files are on disk."""
    return _lpips_setup()[1]


@functools.lru_cache(maxsize=None)
def _lpips_setup() -> tuple[Path | None, str | None]:
    """(torchvision's AlexNet checkpoint, None) when LPIPS can run, else (None, the reasons as one line)."""
    reasons = []
    if importlib.util.find_spec("lpips") is None:
        reasons.append("the 'lpips' package is not installed")
    if importlib.util.find_spec("torchvision") is None:
        reasons.append("torchvision is not installed")
    checkpoint = _alexnet_checkpoint() if not reasons else None
    if not reasons and checkpoint is None:
        reasons.append(f"torchvision's AlexNet weights are not in torch hub's cache ({torch.hub.get_dir()})")
    if not reasons:
        spec = importlib.util.find_spec("lpips")
        linear_weights = Path(spec.origin).parent / "weights" / "v0.1" / "alex.pth"
        if not linear_weights.is_file():
            reasons.append("the lpips package has no bundled weights (weights/v0.1/alex.pth)")
    if reasons:
        return None, "; ".join(reasons) + "; weights are never downloaded"
    return checkpoint, None


@functools.lru_cache(maxsize=None)
def _lpips_network(device: str):
    """The ``lpips`` package's AlexNet LPIPS with local weights, or None if any is missing."""
    checkpoint, reason = _lpips_setup()
    if reason is not None:
        return None
    import lpips as lpips_package

    # pnet_rand=True builds the AlexNet trunk without asking torchvision for (downloadable) weights; the
    # trunk's weights are then copied from the cached checkpoint: features.<i>.* -> slice<k>.<i>.*.
    network = lpips_package.LPIPS(net="alex", pretrained=True, pnet_rand=True, verbose=False)
    trunk_state = torch.load(checkpoint, map_location="cpu", weights_only=True)
    own_state = network.net.state_dict()
    for key in own_state:
        _, index, parameter = key.split(".", 2)
        own_state[key] = trunk_state[f"features.{index}.{parameter}"]
    network.net.load_state_dict(own_state)
    return network.eval().requires_grad_(False).to(device)


def lpips(pred, target) -> float | None:
    """LPIPS (AlexNet, v0.1) of two [H, W, 3] images in [0, 1]; lower is more similar.

    Only runs when the ``lpips`` package (with its bundled linear weights) and torchvision's AlexNet
    weights in torch hub's cache are already present; otherwise it returns None, quietly
    (:func:`lpips_unavailable_reason` says why).
    """
    pred, target = _check_image_pair(pred, target)
    if pred.shape[-1] != 3:
        raise ValueError(f"lpips: images must be RGB [H, W, 3], got {list(pred.shape)}")
    network = _lpips_network(str(pred.device))
    if network is None:
        return None
    to_network = lambda image: (image.float().permute(2, 0, 1).unsqueeze(0) * 2.0 - 1.0)  # noqa: E731
    with torch.no_grad():
        return float(network(to_network(pred), to_network(target)).mean())
