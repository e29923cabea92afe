"""How much of what a novel view shows does the one training camera see at the same instant?

    python -m research.view_coverage AVATAR SUBJECT [--height-band 0.28 0.76] [--depth-tolerance 0.03]
        [--target 18] [--stride 1] [--scale 1.0] [--device cpu] [--json PATH]

``AVATAR`` is a fit's ``avatar.pt`` (or its folder), ``SUBJECT`` the subject folder it was fitted on (``train/``
and ``novel_view/*`` of the same instants). A novel view of a training instant can only be as good as what the
training frame of that instant says about the surface it shows; the rest must come from other instants (a rigid
body part, seen from another side as the subject turns) or from a prediction (cloth that has moved since).

For every novel-view frame, the region is the ground truth's mask within the ``--height-band`` slab (as
``tools/error_breakdown.py --height-band``; a band wider than the body gives the whole mask).
The avatar's geometry stands in for the subject's: each region pixel the avatar covers (rendered alpha > 0.5) is
taken to the surface point at the avatar's rendered depth there, and counts as **seen** when that point, projected
into the training camera of the same instant, lands on a pixel of the training frame's mask that the avatar also
covers, at the avatar's rendered depth there within ``--depth-tolerance`` (world units): the training camera looks
at that very point. Region pixels the avatar leaves uncovered are not seen (their surface is unknown).

Per novel view, pooled over its frames: the seen share of the region's pixels, the avatar's masked PSNR (dB) on the
seen and on the other pixels, and what the other pixels would have to score for the region to reach ``--target``
dB: with the seen pixels perfect (``needed, seen perfect``) and as the avatar draws them (``needed, seen as is``;
``-`` when no score can). The avatar's geometry is an estimate, so the seen share is too: run it with a few
tolerances.
"""

from __future__ import annotations

import math
import sys

import numpy as np
import torch

from research.common import band_needed, garment_tool_parser, load_garment_tool_inputs, markdown_table, slab_of
from warpavatar import data
from warpavatar.evaluate import write_json_atomic
from warpavatar.model import Avatar

__all__ = ["surface_points", "seen_from", "coverage_rows"]


def surface_points(camera: data.Camera, depth: np.ndarray, rows: np.ndarray, columns: np.ndarray) -> np.ndarray:
    """World points [N,3] (float64) at camera-space depth ``depth`` [N] behind pixels (``rows``, ``columns``) [N]
    (OpenCV camera: pixel centres at integers)."""
    intrinsics = np.asarray(camera.K, dtype=np.float64)
    pixels = np.stack([columns, rows, np.ones_like(columns)], axis=0).astype(np.float64)
    rays = np.linalg.solve(intrinsics, pixels)  # [3,N], z = 1
    camera_points = rays * np.asarray(depth, dtype=np.float64)[None]
    world_to_camera = np.asarray(camera.world_to_camera, dtype=np.float64)
    return (world_to_camera[:3, :3].T @ (camera_points - world_to_camera[:3, 3:4])).T


def seen_from(points: np.ndarray, camera: data.Camera, surface_depth: np.ndarray, *, tolerance: float) -> np.ndarray:
    """Which world points [N,3] a camera sees: bool [N], true where the point projects in front of the camera onto
    a pixel (nearest centre) whose ``surface_depth`` [H,W] (world units; NaN where nothing is seen) is within
    ``tolerance`` of the point's own depth."""
    pixels, depth = camera.project(points)
    height, width = surface_depth.shape
    with np.errstate(invalid="ignore"):
        columns = np.rint(pixels[:, 0])
        rows = np.rint(pixels[:, 1])
        inside = (depth > 0) & (columns >= 0) & (columns < width) & (rows >= 0) & (rows < height)
    seen = np.zeros(points.shape[0], dtype=bool)
    at = surface_depth[rows[inside].astype(int), columns[inside].astype(int)]
    with np.errstate(invalid="ignore"):
        seen[inside] = np.abs(depth[inside] - at) < tolerance  # (NaN compares false: nothing seen there)
    return seen


def _render_surface(avatar: Avatar, camera: data.Camera, bones: torch.Tensor, frame_index: int, grid: torch.Tensor,
                    background: torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
    """The avatar's image [H,W,3] in 0..1 and its surface depth [H,W] (NaN where its alpha is under one half)."""
    image, alpha, depth = avatar.render(camera, bones, frame_index=frame_index, grid=grid, background=background)
    alpha = alpha.cpu().numpy().astype(np.float64)
    surface = depth.cpu().numpy().astype(np.float64) / np.maximum(alpha, 1e-6)
    surface[alpha < 0.5] = np.nan
    return image.clamp(0, 1).cpu().numpy().astype(np.float64), surface


def coverage_rows(avatar: Avatar, subject: data.Subject, *, band: tuple[float, float] = (0.28, 0.76),
                  tolerance: float = 0.03, stride: int = 1) -> list[dict]:
    """One row per novel view of the training instants (the module docstring's values).

    Args:
        avatar: a fitted avatar (left as it was).
        subject: its subject (the training folder and the novel views of the same instants).
        band: low and high heights of the region [world units along the skeleton's up axis].
        tolerance: how far a surface point may lie from the training camera's rendered depth and count as seen
            [world units].
        stride: use every ``stride``-th frame of each novel view.

    Returns:
        dicts with ``view``, ``frames``, ``pixels`` (region pixels pooled), ``seen share``, ``uncovered share``,
        ``psnr`` (the whole region), ``psnr seen``, ``psnr unseen`` (dB; NaN where no pixel).

    Raises:
        ValueError: a novel view shows an instant that is not one of the training frames, or has no masks.
    """
    train = subject.train
    device = avatar.gaussians.means.device
    training_ids = {int(frame_id): index for index, frame_id in enumerate(train.frame_ids)}
    avatar.prepare_sequence(train.bone_transforms, frame_ids=train.frame_ids, fps=train.fps)
    grid = avatar.field.grid_weights().detach()
    background = torch.as_tensor(train.background, dtype=torch.float32, device=device)
    training_views: dict[int, np.ndarray] = {}
    rows = []
    with torch.no_grad():
        for name, video in subject.novel_view.items():
            if video.masks is None:
                raise ValueError(f"{video.root}: has no masks/, so its region cannot be measured")
            pooled = {"seen": [0.0, 0], "unseen": [0.0, 0]}
            uncovered = frames = 0
            for index in range(0, video.frame_count, stride):
                frame_id = int(video.frame_ids[index])
                if frame_id not in training_ids:
                    raise ValueError(f"{video.root}: frame {frame_id} is not one of the training frames")
                instant = training_ids[frame_id]
                bones = torch.as_tensor(video.bone_transforms[index], dtype=torch.float32, device=device)
                if instant not in training_views:  # (a novel view's pose is its training instant's)
                    _, training_surface = _render_surface(avatar, train.cameras[instant], bones, instant, grid,
                                                          background)
                    if train.masks is not None:
                        training_surface[train.masks[instant] < 128] = np.nan
                    training_views[instant] = training_surface
                image, surface = _render_surface(avatar, video.cameras[index], bones, instant, grid, background)
                region = (video.masks[index] > 127) & slab_of(video, index, band)
                covered = region & np.isfinite(surface)
                row_ids, column_ids = np.nonzero(covered)
                points = surface_points(video.cameras[index], surface[row_ids, column_ids], row_ids, column_ids)
                seen = np.zeros(region.shape, dtype=bool)
                seen[row_ids, column_ids] = seen_from(points, train.cameras[instant], training_views[instant],
                                                      tolerance=tolerance)
                error = ((image - video.images[index].astype(np.float64) / 255.0) ** 2).mean(-1)
                for key, pixels in (("seen", seen), ("unseen", region & ~seen)):
                    pooled[key][0] += float(error[pixels].sum())
                    pooled[key][1] += int(pixels.sum())
                uncovered += int((region & ~covered).sum())
                frames += 1
            total = pooled["seen"][1] + pooled["unseen"][1]
            rows.append({"view": name, "frames": frames, "pixels": total,
                         "seen share": pooled["seen"][1] / max(total, 1),
                         "uncovered share": uncovered / max(total, 1),
                         "psnr": _pooled_psnr(pooled["seen"][0] + pooled["unseen"][0], total),
                         "psnr seen": _pooled_psnr(*pooled["seen"]), "psnr unseen": _pooled_psnr(*pooled["unseen"])})
    return rows


def _pooled_psnr(error_sum: float, count: int) -> float:
    """PSNR [dB] of a squared error summed over ``count`` pixels (NaN for none)."""
    return -10.0 * math.log10(max(error_sum / count, 1e-12)) if count else math.nan


def _needed(row: dict, target: float, *, seen_db: float = math.inf) -> float:
    """PSNR [dB] the unseen pixels must reach for the region to reach ``target`` with the seen ones at ``seen_db``
    (NaN, where no pixel is seen, counts as perfect: those pixels cost nothing)."""
    return band_needed(1.0 - row["seen share"], target, outside_db=math.inf if math.isnan(seen_db) else seen_db)


def main(argv=None) -> int:
    parser = garment_tool_parser(__doc__.split("\n\n")[0])
    parser.add_argument("--depth-tolerance", type=float, default=0.03,
                        help="how far [world units] a point may lie from the training camera's rendered surface "
                             "and count as seen")
    parser.add_argument("--target", type=float, default=18.0, help="region PSNR [dB] the 'needed' columns aim at")
    parser.add_argument("--stride", type=int, default=1, help="use every N-th frame of each novel view")
    args = parser.parse_args(argv)
    if args.depth_tolerance <= 0:
        parser.error(f"--depth-tolerance must be > 0, got {args.depth_tolerance}")
    if args.stride < 1:
        parser.error(f"--stride must be >= 1, got {args.stride}")
    try:
        subject, avatar = load_garment_tool_inputs(parser, args)
        rows = coverage_rows(avatar, subject, band=tuple(args.height_band), tolerance=args.depth_tolerance,
                             stride=args.stride)
    except (data.VideoFolderError, ValueError, FileNotFoundError) as error:
        print(f"view_coverage: {error}", file=sys.stderr)
        return 2

    def cell(value: float) -> str:
        return f"{value:.2f}" if math.isfinite(value) else "-"

    table = [{"view": row["view"], "frames": row["frames"], "seen share": f"{row['seen share']:.2f}",
              "uncovered share": f"{row['uncovered share']:.2f}", "region dB": cell(row["psnr"]),
              "seen dB": cell(row["psnr seen"]), "unseen dB": cell(row["psnr unseen"]),
              "needed, seen perfect": cell(_needed(row, args.target)),
              "needed, seen as is": cell(_needed(row, args.target, seen_db=row["psnr seen"]))}
             for row in rows]
    print(markdown_table(table))
    if args.json:
        write_json_atomic(args.json, {"args": vars(args), "rows": rows})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
