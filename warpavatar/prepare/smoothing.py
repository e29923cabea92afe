"""Temporal smoothing of pose tracks that keeps real motion: a confidence-gated one-euro filter.

The one-euro filter (Casiez, Roussel and Vogel, CHI 2012) is an exponential smoother whose cut-off frequency
rises with the signal's speed: ``cutoff = min_cutoff + beta * |speed|``. Slow signals are smoothed hard (jitter
disappears), fast ones barely (real motion is kept, with little lag). Two additions for offline use:

* confidence gating: a sample of confidence c in [0, 1] moves the estimate only ``c`` times as far as a fully
  trusted one, so a low-visibility landmark holds the previous pose instead of jerking it;
* zero phase: the filter runs forward and backward in time and the two passes are averaged, which cancels
  the causal filter's lag to first order (the whole video is known in advance).

Vector-valued samples (a position, a quaternion) share one speed: the norm of their derivative.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

__all__ = [
    "OneEuroSettings",
    "one_euro_filter",
    "smooth_positions",
    "smooth_quaternions",
    "align_quaternion_signs",
]


@dataclasses.dataclass(frozen=True)
class OneEuroSettings:
    """Parameters of a one-euro filter.

    Attributes:
        min_cutoff_hz: cut-off frequency at rest [Hz]; lower smooths more.
        beta: growth of the cut-off with speed [Hz per (signal unit / s)]; higher follows fast motion better.
        derivative_cutoff_hz: cut-off of the low-pass filter on the speed estimate [Hz].
        zero_phase: average a forward and a backward pass (no lag); else a causal forward pass.
    """

    min_cutoff_hz: float = 1.0
    beta: float = 0.5
    derivative_cutoff_hz: float = 1.0
    zero_phase: bool = True

    def __post_init__(self):
        for name in ("min_cutoff_hz", "beta", "derivative_cutoff_hz"):
            value = getattr(self, name)
            if not math.isfinite(value) or value < 0 or (name != "beta" and value == 0):
                raise ValueError(f"OneEuroSettings.{name} must be a finite positive number, got {value}")


def _smoothing_factor(cutoff_hz, sample_period_s: float):
    # Exponential smoothing factor of a first-order low-pass filter with this cut-off.
    time_constant = 1.0 / (2.0 * math.pi * cutoff_hz)
    return 1.0 / (1.0 + time_constant / sample_period_s)


def _forward_pass(signal: np.ndarray, confidence: np.ndarray, rate_hz: float, settings: OneEuroSettings) -> np.ndarray:
    # signal: [T, G, C]; confidence: [T, G]. Returns the filtered signal, same shape.
    sample_period = 1.0 / rate_hz
    derivative_alpha = _smoothing_factor(settings.derivative_cutoff_hz, sample_period)
    output = np.empty_like(signal)
    estimate = signal[0].copy()
    speed_estimate = np.zeros(signal.shape[1])
    output[0] = estimate
    for frame in range(1, signal.shape[0]):
        gate = confidence[frame][:, None]
        raw_speed = np.linalg.norm(signal[frame] - estimate, axis=-1) * rate_hz
        speed_estimate = speed_estimate + derivative_alpha * confidence[frame] * (raw_speed - speed_estimate)
        cutoff = settings.min_cutoff_hz + settings.beta * speed_estimate
        alpha = _smoothing_factor(cutoff, sample_period)[:, None]
        estimate = estimate + alpha * gate * (signal[frame] - estimate)
        output[frame] = estimate
    return output


def one_euro_filter(
    signal: np.ndarray,
    *,
    rate_hz: float,
    settings: OneEuroSettings = OneEuroSettings(),
    confidence: np.ndarray | None = None,
) -> np.ndarray:
    """Smooth a sampled signal with a (confidence-gated, optionally zero-phase) one-euro filter.

    Args:
        signal: samples over time, shape [T, G, C] float (G independent groups of C components that share one
            speed, e.g. G joints of C=3 coordinates). Must be finite.
        rate_hz: sampling rate [Hz] (the video's frame rate).
        settings: filter parameters; ``beta`` is per unit of ``signal`` per second.
        confidence: trust in each sample, shape [T, G], values in [0, 1]; default all ones. The first sample of
            a pass is taken as is.

    Returns:
        The filtered signal, shape [T, G, C], float64.
    """
    signal = np.asarray(signal, dtype=np.float64)
    if signal.ndim != 3:
        raise ValueError(f"signal must have shape [T, G, C], got {signal.shape}")
    if not np.isfinite(signal).all():
        raise ValueError("signal must be finite (fill gaps before smoothing)")
    if not (math.isfinite(rate_hz) and rate_hz > 0):
        raise ValueError(f"rate_hz must be positive, got {rate_hz}")
    if confidence is None:
        confidence = np.ones(signal.shape[:2])
    confidence = np.asarray(confidence, dtype=np.float64)
    if confidence.shape != signal.shape[:2]:
        raise ValueError(f"confidence must have shape {signal.shape[:2]}, got {confidence.shape}")
    if not np.isfinite(confidence).all():
        raise ValueError("confidence must be finite")
    confidence = np.clip(confidence, 0.0, 1.0)
    if signal.shape[0] < 2:
        return signal.copy()
    forward = _forward_pass(signal, confidence, rate_hz, settings)
    if not settings.zero_phase:
        return forward
    backward = _forward_pass(signal[::-1], confidence[::-1], rate_hz, settings)[::-1]
    return 0.5 * (forward + backward)


def smooth_positions(
    positions: np.ndarray,
    *,
    rate_hz: float,
    settings: OneEuroSettings = OneEuroSettings(),
    confidence: np.ndarray | None = None,
) -> np.ndarray:
    """One-euro smoothing of point tracks.

    Args:
        positions: shape [T, P, 3] (or [T, 3] for one track), metres.
        rate_hz: frame rate [Hz].
        settings: filter parameters (``beta`` per m/s).
        confidence: shape [T, P] (or [T]), in [0, 1].

    Returns:
        Smoothed positions, same shape, float64.
    """
    positions = np.asarray(positions, dtype=np.float64)
    single = positions.ndim == 2
    if single:
        positions = positions[:, None]
        confidence = None if confidence is None else np.asarray(confidence)[:, None]
    if positions.ndim != 3 or positions.shape[-1] != 3:
        raise ValueError(f"positions must have shape [T, P, 3] or [T, 3], got {positions.shape}")
    smoothed = one_euro_filter(positions, rate_hz=rate_hz, settings=settings, confidence=confidence)
    return smoothed[:, 0] if single else smoothed


def align_quaternion_signs(quaternions: np.ndarray) -> np.ndarray:
    """Flip quaternion signs along time so consecutive samples lie in the same hemisphere (q and -q agree).

    Args:
        quaternions: shape [T, J, 4].

    Returns:
        A copy where ``dot(q[t], q[t - 1]) >= 0`` for every t and joint.
    """
    aligned = np.array(quaternions, dtype=np.float64, copy=True)
    for frame in range(1, aligned.shape[0]):
        flip = np.sum(aligned[frame] * aligned[frame - 1], axis=-1) < 0
        aligned[frame, flip] *= -1.0
    return aligned


def smooth_quaternions(
    quaternions: np.ndarray,
    *,
    rate_hz: float,
    settings: OneEuroSettings = OneEuroSettings(),
    confidence: np.ndarray | None = None,
) -> np.ndarray:
    """One-euro smoothing of rotation tracks given as unit quaternions (any component order).

    Signs are aligned over time first; the filtered 4-vectors are renormalized. For small steps the norm of a
    quaternion difference is half the rotation angle, so ``beta`` is per (rad/2)/s.

    Args:
        quaternions: shape [T, J, 4], unit norm.
        rate_hz: frame rate [Hz].
        settings: filter parameters.
        confidence: shape [T, J], in [0, 1].

    Returns:
        Smoothed unit quaternions, shape [T, J, 4], float64, sign-aligned with the input's first frame.
    """
    quaternions = np.asarray(quaternions, dtype=np.float64)
    if quaternions.ndim != 3 or quaternions.shape[-1] != 4:
        raise ValueError(f"quaternions must have shape [T, J, 4], got {quaternions.shape}")
    aligned = align_quaternion_signs(quaternions)
    smoothed = one_euro_filter(aligned, rate_hz=rate_hz, settings=settings, confidence=confidence)
    norm = np.linalg.norm(smoothed, axis=-1, keepdims=True)
    return smoothed / np.maximum(norm, 1e-12)
