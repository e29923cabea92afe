"""Is a simulated garment's error its geometry? Fit one instant's cloth nodes to the images and see what follows.

    python -m research.garment_oracle AVATAR SUBJECT --frames 20 55 80 [--steps 150] [--appearance] [--scale 1.0]
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

import sys

import numpy as np
import torch

from research.common import (garment_appearance, garment_of, garment_tool_parser, load_garment_tool_inputs,
                             markdown_table, masked_psnr, slab_of)
from warpavatar import data
from warpavatar.evaluate import write_json_atomic
from warpavatar.geometry import match_pose
from warpavatar.model import Avatar

__all__ = ["oracle_rows"]


def _views_of(subject: data.Subject, frame_id: int) -> list[tuple[str, data.VideoFolder, int]]:
    """(name, folder, index) of the training view and of every novel view that holds ``frame_id``."""
    views = []
    for name, video in [("train", subject.train), *subject.novel_view.items()]:
        ids = [int(i) for i in video.frame_ids]
        if frame_id in ids:
            views.append((name, video, ids.index(frame_id)))
    return views


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
    garment = garment_of(avatar)
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
