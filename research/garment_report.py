"""Garment detection on a fitted avatar, offline: what ``--garment auto`` would find in it, and where it would hang.

    python -m research.garment_report AVATAR VIDEO_FOLDER [--max-train-frames N] [--band LOW HIGH] [--json PATH]

``AVATAR`` is a fit's ``avatar.pt`` (or its folder); ``VIDEO_FOLDER`` the folder it was fitted on, whose
training motion the detection reads (give the fit's ``--max-train-frames``). The rule and its defaults are the
extension's (``warpavatar/extensions/garment_detection.py``). Prints one line per garment: its Gaussians and
their fraction of all, its height range (fractions of the Gaussians' extent along the skeleton's up axis,
0 = lowest), the joint it hangs from, the joints its weights split between, its cloth nodes, the attached ones
(their height range, and how many of 12 sectors around the attachment joint they fill: a waistband is a closed
ring), and with ``--band`` the fraction of the Gaussians between those two heights (same fractions; arms left
out: farther from the root joint's vertical axis than a quarter of the height) that the garment holds.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import torch

from warpavatar import data
from warpavatar.extensions.garment import GarmentExtension, GarmentOptions, body_detection_options
from warpavatar.extensions.garment_detection import detect_garments
from warpavatar.extensions.graph import voxel_downsample
from warpavatar.model import Avatar

__all__ = ["garment_report"]


@torch.no_grad()
def garment_report(avatar: Avatar, video, *, band: tuple[float, float] | None = None) -> dict:
    """Detect the garments of ``avatar`` over the training motion of ``video`` with the extension's defaults.

    Returns:
        ``{"gaussians": N, "garments": [{...}, ...]}`` (keys as the module docstring lists them).
    """
    options = GarmentOptions()
    skeleton, field = video.skeleton, avatar.field
    means = avatar.gaussians.means.detach()
    groups = avatar.skinning_groups()
    weights = field.weights(means)
    weights = weights if groups is None else weights @ groups
    body = body_detection_options(skeleton, field)
    found = detect_garments(means, weights, skeleton.parents, torch.as_tensor(video.bone_transforms).float(),
                            threshold=options.garment_threshold, min_fraction=options.garment_min_fraction, **body)
    up = body["up"] / body["up"].norm()
    height = means @ up
    low, span = float(height.min()), max(float(height.max() - height.min()), 1e-12)
    relative = (height - low) / span
    report = {"gaussians": int(means.shape[0]), "garments": []}
    for region in found:
        ids = region.gaussian_ids
        garment = torch.zeros(means.shape[0], dtype=torch.bool)
        garment[ids] = True
        voxel = options.garment_voxel * float((field.bbox_max - field.bbox_min).max())
        nodes = voxel_downsample(means[ids], voxel)
        node_weights = field.weights(nodes)
        node_weights = node_weights if groups is None else node_weights @ groups
        held = GarmentExtension._attached(means, weights, garment, nodes, node_weights, skeleton.parents,
                                          region.joint, voxel, up=up)
        across = torch.eye(3)[int(up.abs().argmin())]  # two axes across the up axis
        across = across - (across @ up) * up
        across = across / across.norm()
        around = nodes[held] - body["heads"][region.joint]
        angle = torch.atan2(around @ torch.linalg.cross(up, across), around @ across)
        sectors = torch.unique(((angle + math.pi) / (2 * math.pi) * 12).long().clamp(0, 11)).numel()
        held_height = (nodes[held] @ up - low) / span
        entry = {"gaussians": int(ids.numel()), "fraction": round(ids.numel() / means.shape[0], 3),
                 "heights": [round(float(relative[ids].min()), 3), round(float(relative[ids].max()), 3)],
                 "joint": skeleton.names[region.joint], "split": [skeleton.names[j] for j in region.split_joints],
                 "nodes": int(nodes.shape[0]), "attached": int(held.numel()),
                 "attached_heights": [round(float(held_height.min()), 3), round(float(held_height.max()), 3)],
                 "attached_sectors_of_12": int(sectors)}
        if band is not None:
            offset = means - body["heads"][0]
            lateral = (offset - (offset @ up)[:, None] * up).norm(dim=1)
            inside = (relative >= band[0]) & (relative <= band[1]) & (lateral <= 0.25 * span)
            entry["band_held"] = round(float((inside & garment).sum()) / max(1, int(inside.sum())), 3)
        report["garments"].append(entry)
    return report


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("avatar", type=Path, help="a fit's avatar.pt, or the fit's folder")
    parser.add_argument("video", type=Path, help="the video folder the avatar was fitted on")
    parser.add_argument("--max-train-frames", type=int, default=0, metavar="INT",
                        help="the fit's --max-train-frames: the training motion detection reads (default: 0, all)")
    parser.add_argument("--band", type=float, nargs=2, metavar=("LOW", "HIGH"), default=None,
                        help="report the fraction of the Gaussians between these heights (fractions of the "
                             "height, 0-1) that the garment holds (default: none)")
    parser.add_argument("--json", type=Path, default=None, metavar="PATH", help="also write the report there")
    args = parser.parse_args(argv)
    path = args.avatar / "avatar.pt" if args.avatar.is_dir() else args.avatar
    if not path.is_file():
        print(f"error: {path}: no such avatar file", file=sys.stderr)
        return 2
    try:
        video = data.load_video_folder(args.video, max_frames=args.max_train_frames)
    except (OSError, ValueError) as error:
        print(f"error: {args.video}: {error}", file=sys.stderr)
        return 2
    report = garment_report(Avatar.load(path), video, band=None if args.band is None else tuple(args.band))
    print(f"{report['gaussians']} Gaussians, {len(report['garments'])} garment(s)")
    for garment in report["garments"]:
        print("  " + ", ".join(f"{key} {value}" for key, value in garment.items()))
    if args.json is not None:
        args.json.write_text(json.dumps(report, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
