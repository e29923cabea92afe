"""What the research diagnostics share: the garment tools' arguments and inputs, the slab of a frame, the garment
Gaussians' appearance as a fittable copy, and the measures and tables they print.

The measures (:func:`masked_psnr`, :func:`height_band_mask`, :func:`band_needed`) are those of
``tools/error_breakdown.py`` and the table is ``tools/bench_common.py``'s, imported from there so that a slab or a
masked PSNR means the same thing in every table.
"""

from __future__ import annotations

import argparse
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import torch

from tools.bench_common import markdown_table
from tools.error_breakdown import band_needed, height_band_mask, masked_psnr
from warpavatar import data
from warpavatar.model import Avatar

__all__ = ["APPEARANCE_LEARNING_RATES", "band_needed", "garment_appearance", "garment_of", "garment_tool_parser",
           "height_band_mask", "load_garment_tool_inputs", "markdown_table", "masked_psnr", "slab_of"]

APPEARANCE_LEARNING_RATES = {"sh_dc": 2.5e-3, "sh_rest": 1.25e-4, "opacity_logits": 0.05, "log_scales": 5e-3}
"""Adam steps of the garment Gaussians' appearance parameters when a diagnostic fits them (3DGS's defaults)."""


def garment_of(avatar: Avatar):
    """The avatar's simulated garment part.

    Raises:
        ValueError: the avatar has none, or one without cloth nodes.
    """
    garment = avatar.part("garment")
    if garment is None or garment.node_count == 0:
        raise ValueError("the avatar has no simulated garment (fit with --garment auto on a subject that has one)")
    return garment


@contextmanager
def garment_appearance(avatar: Avatar, garment, *, trainable: bool = True):
    """For the ``with`` block: the avatar's parameters frozen, but for Adam parameter groups (``[{"params",
    "lr"}]``) of the garment Gaussians' colours (SH), opacity logits and log scales, whose gradients reach the
    garment's Gaussians only; on exit their values (every Gaussian's) and every parameter's ``requires_grad`` flag
    are put back. With ``trainable=False`` the groups are empty: everything stays frozen."""
    looks = {name: getattr(avatar.gaussians, name) for name in APPEARANCE_LEARNING_RATES}
    member = torch.zeros(avatar.gaussians.means.shape[0], dtype=torch.bool, device=avatar.gaussians.means.device)
    member[garment.gaussian_ids] = True
    kept = {name: tensor.detach().clone() for name, tensor in looks.items()}
    flags = {parameter: parameter.requires_grad for parameter in avatar.parameters()}
    hooks, groups = [], []
    try:
        for parameter in flags:
            parameter.requires_grad_(False)
        for name, tensor in looks.items():
            if trainable:
                tensor.requires_grad_(True)
                shape = (-1,) + (1,) * (tensor.dim() - 1)
                hooks.append(tensor.register_hook(lambda grad, keep=member.view(shape): grad * keep))
                groups.append({"params": [tensor], "lr": APPEARANCE_LEARNING_RATES[name]})
        yield groups
    finally:
        for hook in hooks:
            hook.remove()
        with torch.no_grad():
            for name, tensor in looks.items():
                tensor.copy_(kept[name])
        for parameter, flag in flags.items():
            parameter.requires_grad_(flag)


def slab_of(video: data.VideoFolder, index: int, band: tuple[float, float]) -> np.ndarray:
    """The pixels [H,W] (bool) of frame ``index`` between heights ``band`` [world units along the skeleton's up
    axis], measured at the posed root joint's depth (``tools/error_breakdown.py --height-band``)."""
    root = video.bone_transforms[index][0].astype(np.float64) @ np.append(video.skeleton.heads[0], 1.0)
    return height_band_mask(video.cameras[index], root[:3], video.skeleton.up, low=band[0], high=band[1])


def garment_tool_parser(description: str) -> argparse.ArgumentParser:
    """The arguments the avatar-and-subject diagnostics share: AVATAR, SUBJECT, ``--scale``, ``--height-band``,
    ``--device`` and ``--json`` (:func:`load_garment_tool_inputs` reads them)."""
    parser = argparse.ArgumentParser(description=description, formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    parser.add_argument("avatar", help="a fit's avatar.pt, or its folder")
    parser.add_argument("subject", help="the subject folder (train/ and novel_view/*)")
    parser.add_argument("--scale", type=float, default=1.0, help="image scale of the folders (the fit's "
                        "--image-scale)")
    parser.add_argument("--height-band", type=float, nargs=2, default=(0.28, 0.76), metavar=("LOW", "HIGH"),
                        help="the slab's heights [world units along the skeleton's up axis]")
    parser.add_argument("--device", default="cpu", help="torch device")
    parser.add_argument("--json", default=None, help="also write the rows to this JSON file")
    return parser


def load_garment_tool_inputs(parser: argparse.ArgumentParser, args) -> tuple[data.Subject, Avatar]:
    """The subject and the avatar that :func:`garment_tool_parser`'s arguments name (the band checked first).

    Raises:
        data.VideoFolderError, ValueError, FileNotFoundError: unreadable inputs (the tools print them on one line).
    """
    if not args.height_band[0] < args.height_band[1]:
        parser.error("--height-band LOW HIGH needs LOW < HIGH")
    path = Path(args.avatar)
    path = path / "avatar.pt" if path.is_dir() else path
    return data.load_subject(args.subject, scale=args.scale), Avatar.load(path, device=args.device)
