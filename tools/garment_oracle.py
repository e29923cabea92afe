"""Is a simulated garment's error its geometry? Fit one instant's cloth nodes to the images and see what follows.

    python tools/garment_oracle.py AVATAR SUBJECT --frames 20 55 80 [--steps 150] [--appearance] [--scale 1.0]
        [--height-band 0.28 0.76] [--device cpu] [--json PATH]

``AVATAR`` is a fit's ``avatar.pt`` (or its folder) with a garment (``--garment auto`` found one); ``SUBJECT`` the
subject folder it was fitted on (``train/`` and ``novel_view/*`` of the same instants). For every training frame
id given, the garment's node positions at that instant (everything else of the avatar frozen: its Gaussians,
their colours and their offsets on the nodes) are

* ``rollout``: as the avatar draws them (the training rollout of the simulation);
* ``training view``: fitted to the training image of that instant alone (Adam on the positions, L1 over the
  image, ``--steps`` steps from the rollout) -- what one camera can tell;
* ``every view``: fitted to the training image and every novel view of that instant, in turn, for the same number
  of steps each -- an **oracle**: it reads the held-out images, so its numbers are not an evaluation, only a
  bound on what the avatar's appearance allows once the cloth is where the images say;
* ``every view + appearance`` (``--appearance``): the same oracle, with the garment's Gaussians' colours (SH),
  opacities and scales fitted too (theirs only; the avatar's values are put back afterwards) -- a bound on what
  the garment's Gaussians could draw with the cloth in place and a texture learned where it is.

Each row gives the masked PSNR (dB) of the training view and of every novel view of the instant, whole mask and
the slab between ``--height-band`` heights (as ``tools/error_breakdown.py --height-band``). If the oracle rows are
high in every view while the training-view rows lift only the training view, the texture is good enough and the
cloth's 3D shape per instant is what is missing, which the one camera does not determine. If only the appearance
oracle is high, the texture learned on the fit's cloth is what holds the nodes' oracle back; if neither is, the
garment's Gaussians themselves (their number and cover) are.
"""

from __future__ import annotations

import argparse
import sys
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_common import markdown_table  # noqa: E402
from error_breakdown import height_band_mask, masked_psnr  # noqa: E402

from warpavatar import data  # noqa: E402
from warpavatar.evaluate import write_json_atomic  # noqa: E402
from warpavatar.geometry import match_pose  # noqa: E402
from warpavatar.model import Avatar  # noqa: E402

__all__ = ["oracle_rows", "slab_of", "garment_tool_parser", "load_garment_tool_inputs"]

MODES = ("rollout", "training view", "every view", "every view + appearance")

# The garment Gaussians' parameters the appearance fits learn, with Adam steps as in 3DGS's defaults.
_APPEARANCE_STEPS = {"sh_dc": 2.5e-3, "sh_rest": 1.25e-4, "opacity_logits": 0.05, "log_scales": 5e-3}


@contextmanager
def garment_appearance(avatar: Avatar, garment, *, trainable: bool = True):
    """For the ``with`` block: the avatar's parameters frozen, but for Adam parameter groups (``[{"params",
    "lr"}]``) of the garment Gaussians' colours (SH), opacity logits and log scales, whose gradients reach the
    garment's Gaussians only; on exit their values (every Gaussian's) and every parameter's ``requires_grad`` flag
    are put back. With ``trainable=False`` the groups are empty: everything stays frozen."""
    looks = {name: getattr(avatar.gaussians, name) for name in _APPEARANCE_STEPS}
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
                groups.append({"params": [tensor], "lr": _APPEARANCE_STEPS[name]})
        yield groups
    finally:
        for hook in hooks:
            hook.remove()
        with torch.no_grad():
            for name, tensor in looks.items():
                tensor.copy_(kept[name])
        for parameter, flag in flags.items():
            parameter.requires_grad_(flag)


def _views_of(subject: data.Subject, frame_id: int) -> list[tuple[str, data.VideoFolder, int]]:
    """(name, folder, index) of the training view and of every novel view that holds ``frame_id``."""
    views = []
    for name, video in [("train", subject.train), *subject.novel_view.items()]:
        ids = [int(i) for i in video.frame_ids]
        if frame_id in ids:
            views.append((name, video, ids.index(frame_id)))
    return views


def slab_of(video: data.VideoFolder, index: int, band: tuple[float, float]) -> np.ndarray:
    """The pixels [H,W] (bool) of frame ``index`` between heights ``band`` (``tools/error_breakdown.py
    --height-band``, measured at the posed root joint's depth)."""
    root = video.bone_transforms[index][0].astype(np.float64) @ np.append(video.skeleton.heads[0], 1.0)
    return height_band_mask(video.cameras[index], root[:3], video.skeleton.up, low=band[0], high=band[1])


def _psnrs(image: torch.Tensor, video: data.VideoFolder, index: int, band: tuple[float, float]) -> tuple[float, float]:
    """Masked PSNR of the whole mask and of the height band (dB)."""
    prediction = image.detach().clamp(0, 1).cpu().numpy().astype(np.float64)
    truth = video.images[index].astype(np.float64) / 255.0
    mask = video.masks[index].astype(np.float64) / 255.0
    return masked_psnr(prediction, truth, mask), masked_psnr(prediction, truth, mask * slab_of(video, index, band))


def oracle_rows(avatar: Avatar, subject: data.Subject, frame_ids: list[int], *, steps: int = 150,
                band: tuple[float, float] = (0.28, 0.76), learning_rate: float = 0.05,
                appearance: bool = False) -> list[dict]:
    """The rows of the module docstring: one per (frame id, mode), with ``psnr`` and ``band`` dicts by view.

    Args:
        avatar: a fitted avatar with a ``garment`` part (left as it was).
        subject: its subject (the training folder and the novel views of the same instants).
        frame_ids: training frame ids to look at.
        steps: Adam steps of each fit (per view for the oracles).
        band: low and high heights of the slab [world units along the skeleton's up axis].
        learning_rate: Adam's step for the node positions, as a fraction of the node spacing.
        appearance: also the ``every view + appearance`` oracle.

    Raises:
        ValueError: the avatar has no garment, or a frame id is not among the training frames.
    """
    garment = avatar.part("garment")
    if garment is None or garment.node_count == 0:
        raise ValueError("the avatar has no simulated garment (fit with --garment auto on a subject that has one)")
    device = avatar.gaussians.means.device
    background = torch.as_tensor(subject.train.background, dtype=torch.float32, device=device)
    grid = avatar.field.grid_weights().detach()
    spacing = garment.hyper["voxel_size"]

    def render(video, index, positions):
        bones = torch.as_tensor(video.bone_transforms[index], dtype=torch.float32, device=device)
        return avatar.render(video.cameras[index], bones, background=background, grid=grid,
                             inputs={garment.name: positions})[0]

    def scored(positions, views):
        with torch.no_grad():
            return {name: _psnrs(render(video, index, positions), video, index, band) for name, video, index in views}

    def fitted(start, views, fitted_views, *, with_appearance=False):
        """The positions fitted to ``fitted_views`` from ``start``, and every view's scores with the appearance
        fitted along (put back when the block ends)."""
        positions = start.clone().requires_grad_()
        targets = [(video, index, torch.as_tensor(video.images[index], device=device).float() / 255.0)
                   for _, video, index in fitted_views]
        with garment_appearance(avatar, garment, trainable=with_appearance) as looks:
            optimizer = torch.optim.Adam([{"params": [positions], "lr": learning_rate * spacing}, *looks])
            for _ in range(steps):
                for video, index, truth in targets:
                    loss = (render(video, index, positions) - truth).abs().mean()
                    optimizer.zero_grad()
                    loss.backward()
                    optimizer.step()
            return positions.detach(), scored(positions.detach(), views)

    rows = []
    for frame_id in frame_ids:
        start = garment.frame_positions[_training_instant(subject, garment.frame_poses, frame_id)].detach()
        views = _views_of(subject, frame_id)
        fits = [("rollout", lambda: (start, scored(start, views))),
                ("training view", lambda: fitted(start, views, views[:1])),
                ("every view", lambda: fitted(start, views, views))]
        if appearance:
            fits.append(("every view + appearance", lambda: fitted(start, views, views, with_appearance=True)))
        for mode, fit in fits:
            positions, psnrs = fit()
            rows.append({"frame": frame_id, "mode": mode, "psnr": {n: v[0] for n, v in psnrs.items()},
                         "band": {n: v[1] for n, v in psnrs.items()},
                         "moved": float((positions - start).norm(dim=1).mean() / spacing)})
    return rows


def _training_instant(subject: data.Subject, fitted_poses: torch.Tensor, frame_id: int) -> int:
    """The row of the garment's training rollout (poses ``fitted_poses`` [T,J,4,4]) at training frame ``frame_id``."""
    ids = [int(i) for i in subject.train.frame_ids]
    if frame_id in ids and fitted_poses.shape[0]:
        pose = torch.as_tensor(subject.train.bone_transforms[ids.index(frame_id)], dtype=torch.float32,
                               device=fitted_poses.device)
        row, matched = match_pose(fitted_poses, pose, tolerance=1e-5)
        if float(matched):
            return int(row)
    raise ValueError(f"frame id {frame_id} is not one of the fit's training frames in {subject.train.root}")


def garment_tool_parser(description: str) -> argparse.ArgumentParser:
    """The arguments the garment diagnostics share: AVATAR, SUBJECT, ``--scale``, ``--height-band``, ``--device``
    and ``--json`` (:func:`load_garment_tool_inputs` reads them)."""
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


def main(argv=None) -> int:
    parser = garment_tool_parser(__doc__.split("\n\n")[0])
    parser.add_argument("--frames", type=int, nargs="+", required=True, help="training frame ids to look at")
    parser.add_argument("--steps", type=int, default=150, help="Adam steps of each fit (per view for the oracles; "
                        "default: %(default)s)")
    parser.add_argument("--appearance", action="store_true", help="also the oracle that fits the garment Gaussians' "
                        "colours, opacities and scales with the nodes, to every view (default: off)")
    args = parser.parse_args(argv)
    if args.steps < 1:
        parser.error(f"--steps must be >= 1, got {args.steps}")
    try:
        subject, avatar = load_garment_tool_inputs(parser, args)
        rows = oracle_rows(avatar, subject, args.frames, steps=args.steps, band=tuple(args.height_band),
                           appearance=args.appearance)
    except (data.VideoFolderError, ValueError, FileNotFoundError) as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    names = list(rows[0]["psnr"])
    print(markdown_table([
        {"frame": row["frame"], "nodes": row["mode"],
         **{f"{n} mask / slab": f"{row['psnr'][n]:.2f} / {row['band'][n]:.2f}" for n in names if n in row["psnr"]},
         "moved (node spacings)": f"{row['moved']:.2f}"} for row in rows]))
    if args.json:
        write_json_atomic(args.json, rows)
    return 0


if __name__ == "__main__":
    sys.exit(main())
