"""How well the exported mesh stands in for the Gaussians it is made from: both scored against the ground truth,
and the mesh's silhouette against the Gaussians'.

    python tools/mesh_benchmark.py AVATAR_DIR VIDEO_FOLDER [-o FILE.json] [--frames N] [--device cuda]
        [--triangles N] [--texture-size S] [--view-count N] [--view-size S] [--shading texture|vertex-colors]
        [--supersample N] [--scale S] [--pixel-size M] [--stand-in]

AVATAR_DIR is a fit's output folder (or its avatar.pt); VIDEO_FOLDER a subject folder (train/, novel_view/*,
novel_pose/*: every folder is measured) or one video folder with masks. The mesh is built as ``warpavatar-export``
builds it (:func:`warpavatar.mesh.build.build_avatar_mesh`), posed per frame as an engine plays it (the rig's
skinning transforms plus per-frame offsets, :func:`warpavatar.mesh.skin.mesh_animation` and
:func:`~warpavatar.mesh.skin.lbs_vertices`) and ray cast with its texture (:func:`warpavatar.ops.render_mesh`);
the Gaussians are rendered as ``warpavatar-eval`` renders them. The fit's recorded training pixel width
(:func:`warpavatar.mesh.build.recorded_pixel_size`) blurs the mesh's renders as the export's, unless
``--pixel-size`` overrides it (0: no blur). Frames are read at the fit's image scale
(``--scale`` overrides it), ``--frames`` evenly spaced frames a folder. Per folder it prints one row:

* ``mesh PSNR`` / ``mesh SSIM`` and ``GS PSNR`` / ``GS SSIM``: masked PSNR [dB] and SSIM of the mesh's and the
  Gaussians' renders against the ground truth (inside its mask, :func:`warpavatar.metrics.image_scores`);
* ``IoU`` (mean over frames) and ``IoU min``: the mesh's silhouette (its 0/1 alpha; with ``--supersample``, its
  covered fraction >= 0.5) against the Gaussians' (alpha >= 0.5), intersection over union;
* ``mesh only`` and ``GS only``: the pixels only the mesh's silhouette covers, and those only the Gaussians'
  covers, each over the Gaussians' silhouette (:func:`silhouette_misses`: too wide, or too thin);
* ``IoU mask`` and ``GS IoU mask``: the mesh's and the Gaussians' silhouettes against the ground-truth mask
  (>= 0.5), what the masked PSNR's edges depend on;
* ``mesh ms`` and ``GS ms``: render time per frame (the mesh's includes building its BVH).

``--stand-in`` measures a stand-in mesh instead of the export's (the convex hull of the canonical Gaussians'
centres, coloured by the nearest Gaussian, skinned by the avatar's field): a check of the measurement itself,
apart from the export. ``-o FILE.json`` writes the rows, the mesh's size and the settings.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np
import torch

__all__ = ["IOU_TARGET", "ALPHA_THRESHOLD", "stand_in_mesh", "frame_subset", "silhouette_iou",
           "render_mesh_supersampled", "measure_folder", "main"]

IOU_TARGET = 0.95
"""Silhouette IoU the mesh should reach against the Gaussians on the training frames."""

ALPHA_THRESHOLD = 0.5
"""Gaussian alpha at and above which a pixel counts as inside the Gaussians' silhouette."""


def stand_in_mesh(avatar):
    """A skinned :class:`~warpavatar.mesh.mesh_data.AvatarMesh` without the export pipeline: the convex hull of the
    canonical Gaussians' centres, each vertex coloured like its nearest Gaussian (DC colour), skinned by the
    avatar's field (:func:`warpavatar.mesh.skin.skin_mesh`)."""
    import trimesh

    from warpavatar.mesh.skin import skin_mesh
    from warpavatar.mesh.mesh_data import AvatarMesh
    from warpavatar.model.gaussians import sh_dc_to_rgb

    with torch.no_grad():
        means = avatar.gaussians.means.detach().float().cpu()
        colours = sh_dc_to_rgb(avatar.gaussians.sh_dc.detach()[:, 0].float().cpu()).clamp(0, 1)
    hull = trimesh.convex.convex_hull(means.numpy().astype(np.float64))
    vertices = np.asarray(hull.vertices, dtype=np.float32)
    nearest = torch.cdist(torch.as_tensor(vertices), means).argmin(dim=1)
    mesh = AvatarMesh(vertices=vertices, faces=np.asarray(hull.faces, dtype=np.int32),
                      normals=np.asarray(hull.vertex_normals, dtype=np.float32),
                      vertex_colors=(colours[nearest].numpy() * 255).round().astype(np.uint8),
                      up=np.asarray(avatar.skeleton.up, dtype=np.float32))
    return skin_mesh(avatar, mesh)


def frame_subset(frame_count: int, count: int) -> np.ndarray:
    """Indices of ``count`` frames evenly spaced over ``frame_count`` (first and last included; all for 0)."""
    if count <= 0 or count >= frame_count:
        return np.arange(frame_count)
    return np.unique(np.linspace(0, frame_count - 1, count).round().astype(np.int64))


def silhouette_iou(mesh_alpha: torch.Tensor, gaussian_alpha: torch.Tensor) -> float:
    """Intersection over union of the mesh's silhouette and the Gaussians', each the pixels of [H,W] alpha >=
    :data:`ALPHA_THRESHOLD` (the mesh's alpha is 0/1, or a covered fraction when supersampled); 1 when both are
    empty."""
    mesh_inside = mesh_alpha >= ALPHA_THRESHOLD
    gaussian_inside = gaussian_alpha >= ALPHA_THRESHOLD
    union = int((mesh_inside | gaussian_inside).sum())
    return 1.0 if union == 0 else int((mesh_inside & gaussian_inside).sum()) / union


def silhouette_misses(mesh_alpha: torch.Tensor, gaussian_alpha: torch.Tensor) -> tuple[float, float]:
    """Where the silhouettes of :func:`silhouette_iou` disagree, as shares of the Gaussians' silhouette: (pixels
    only the mesh covers, pixels only the Gaussians cover); (0, 0) when the Gaussians cover nothing. The first says
    the mesh is too wide, the second that it is too thin or has lost a part."""
    mesh_inside = mesh_alpha >= ALPHA_THRESHOLD
    gaussian_inside = gaussian_alpha >= ALPHA_THRESHOLD
    area = int(gaussian_inside.sum())
    if area == 0:
        return 0.0, 0.0
    return int((mesh_inside & ~gaussian_inside).sum()) / area, int((gaussian_inside & ~mesh_inside).sum()) / area


def render_mesh_supersampled(vertices: torch.Tensor, faces, camera, *, supersample: int, background: torch.Tensor,
                             **colouring) -> tuple[torch.Tensor, torch.Tensor]:
    """``(image [H,W,3], alpha [H,W])`` of the posed mesh through ``camera`` (a :class:`warpavatar.data.Camera`),
    ray cast at ``supersample`` times the resolution along each axis and box-filtered down (an engine's
    antialiasing and texture filtering, roughly): alpha is then the covered fraction of each pixel."""
    from warpavatar import ops

    width, height = int(camera.width), int(camera.height)
    fine = camera if supersample == 1 else camera.resized(width * supersample, height * supersample)
    image, alpha, _ = ops.render_mesh(vertices, faces, fine.K, fine.world_to_camera, int(fine.width),
                                      int(fine.height), background=background, **colouring)
    if supersample > 1:
        image = torch.nn.functional.avg_pool2d(image.permute(2, 0, 1)[None], supersample)[0].permute(1, 2, 0)
        alpha = torch.nn.functional.avg_pool2d(alpha[None, None], supersample)[0, 0]
    return image, alpha


def _synchronize(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _mesh_shading(mesh, shading: str) -> dict:
    """The ``render_mesh`` colour arguments of ``mesh`` for ``--shading`` (the texture where asked and present,
    else the vertex colours)."""
    if shading == "texture" and mesh.uvs is not None and mesh.texture is not None:
        return {"uvs": mesh.uvs, "texture": mesh.texture}
    if mesh.vertex_colors is not None:
        return {"vertex_colors": mesh.vertex_colors}
    raise ValueError("the mesh has neither a texture nor vertex colours to render")


@torch.no_grad()
def measure_folder(avatar, mesh, video, *, frames: int, shading: str = "texture", supersample: int = 1) -> dict:
    """The mesh and the Gaussians of ``avatar`` measured on ``frames`` evenly spaced frames of ``video`` (see the
    module docstring), the mesh rendered at ``supersample`` times the resolution and box-filtered down; the means
    over those frames and one record per frame."""
    from warpavatar import metrics
    from warpavatar.io.exporters import ExportMotion
    from warpavatar.mesh.skin import lbs_vertices, mesh_animation

    if video.masks is None:
        raise ValueError(f"{video.root}: has no masks/, so no masked PSNR can be measured")
    if video.skeleton.joint_count != avatar.joint_count:
        raise ValueError(f"{video.root}: its skeleton has {video.skeleton.joint_count} joints but the avatar's has "
                         f"{avatar.joint_count}")
    device = avatar.gaussians.means.device
    background = torch.as_tensor(video.background, dtype=torch.float32, device=device)
    colouring = _mesh_shading(mesh, shading)
    # colours as float32 0..1 on the device once, not converted again for every frame
    colouring = {name: torch.as_tensor(np.asarray(value), device=device) for name, value in colouring.items()}
    colouring = {name: value.float() / 255.0 if value.dtype == torch.uint8 else value.float()
                 for name, value in colouring.items()}
    faces = torch.as_tensor(np.asarray(mesh.faces), dtype=torch.int32)
    # the whole folder's motion, so that parts with state over time roll it out as the evaluation does (this also
    # prepares the avatar's own sequence for the Gaussians' renders)
    motion = ExportMotion(np.asarray(video.bone_transforms, dtype=np.float32), np.asarray(video.frame_ids),
                          float(video.fps), float(video.fps))
    animation = mesh_animation(avatar, mesh, motion)
    grid = avatar.field.grid_weights()
    records = []
    seconds = {"mesh": 0.0, "gaussians": 0.0}
    for t in frame_subset(video.frame_count, frames):
        camera = video.cameras[t]
        offsets = None if animation.vertex_offsets is None else animation.vertex_offsets[t]
        vertices = torch.as_tensor(lbs_vertices(mesh, animation.joint_transforms[t], offsets), device=device)
        _synchronize(device)
        start = time.perf_counter()
        mesh_image, mesh_alpha = render_mesh_supersampled(vertices, faces, camera, supersample=supersample,
                                                          background=background, **colouring)
        _synchronize(device)
        seconds["mesh"] += time.perf_counter() - start
        start = time.perf_counter()
        bones = torch.as_tensor(video.bone_transforms[t], dtype=torch.float32, device=device)
        gaussian_image, gaussian_alpha, _ = avatar.render(camera, bones, background=background, grid=grid)
        _synchronize(device)
        seconds["gaussians"] += time.perf_counter() - start
        truth = torch.as_tensor(video.images[t], device=device).float() / 255.0
        mask = torch.as_tensor(video.masks[t], device=device).float() / 255.0
        mesh_scores = metrics.image_scores(mesh_image.clamp(0, 1), truth, mask=mask)
        gaussian_scores = metrics.image_scores(gaussian_image.clamp(0, 1), truth, mask=mask)
        records.append({"frame_id": int(video.frame_ids[t]),
                        "mesh_psnr_masked": mesh_scores["psnr_masked"], "mesh_ssim_masked": mesh_scores["ssim_masked"],
                        "gaussians_psnr_masked": gaussian_scores["psnr_masked"],
                        "gaussians_ssim_masked": gaussian_scores["ssim_masked"],
                        "iou": silhouette_iou(mesh_alpha, gaussian_alpha),
                        **dict(zip(("mesh_only", "gaussians_only"), silhouette_misses(mesh_alpha, gaussian_alpha))),
                        "iou_mask": silhouette_iou(mesh_alpha, mask),
                        "gaussians_iou_mask": silhouette_iou(gaussian_alpha, mask)})
    count = max(1, len(records))
    means = {key: float(np.mean([record[key] for record in records])) for key in records[0] if key != "frame_id"}
    return {"folder": str(video.root), "resolution": f"{video.width}x{video.height}", "frame_count": len(records),
            **means, "iou_min": float(min(record["iou"] for record in records)),
            "mesh_render_ms": 1000 * seconds["mesh"] / count,
            "gaussians_render_ms": 1000 * seconds["gaussians"] / count, "frames": records}


def _folders(path: Path, scale: float):
    """(label, VideoFolder) pairs of a subject folder (train, then its held-out folders) or of one video folder,
    read at ``scale``."""
    from warpavatar import data

    if (path / "train").is_dir():
        subject = data.load_subject(path, scale=scale)
        yield "train", subject.train
        for kind, folders in (("novel_view", subject.novel_view), ("novel_pose", subject.novel_pose)):
            for name in folders:
                yield f"{kind}/{name}", folders[name]
    else:
        yield path.name, data.load_video_folder(path, scale=scale)


def _build_parser() -> argparse.ArgumentParser:
    from warpavatar.mesh.build import DEFAULT_TEXTURE_SIZE, DEFAULT_TRIANGLES, DEFAULT_VIEW_COUNT, DEFAULT_VIEW_SIZE

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("avatar", type=Path, help="fit output folder (or its avatar.pt)")
    parser.add_argument("video_folder", type=Path, help="subject folder (train/, novel_view/, novel_pose/) or one "
                        "video folder with masks")
    parser.add_argument("-o", "--output", type=Path, default=None, help="write the results here (JSON)")
    parser.add_argument("--frames", type=int, default=8, help="evenly spaced frames measured a folder (0: all; "
                        "default %(default)s)")
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu", help="torch device")
    parser.add_argument("--triangles", type=int, default=DEFAULT_TRIANGLES,
                        help="triangles of the exported mesh (default %(default)s)")
    parser.add_argument("--texture-size", type=int, default=DEFAULT_TEXTURE_SIZE,
                        help="width and height of its texture atlas [px] (default %(default)s)")
    parser.add_argument("--view-count", type=int, default=DEFAULT_VIEW_COUNT,
                        help="renders of the canonical avatar the mesh is made from (default %(default)s)")
    parser.add_argument("--view-size", type=int, default=DEFAULT_VIEW_SIZE,
                        help="width and height of each of those renders [px] (default %(default)s)")
    parser.add_argument("--max-voxels", type=int, default=None,
                        help="most voxels of the fused grid (default: the export's, "
                             "warpavatar.mesh.surface.MAX_VOXELS)")
    parser.add_argument("--silhouette-rounds", type=int, default=None,
                        help="rounds fitting the skinned mesh's silhouettes to the Gaussians' in frames of the "
                             "training motion (default: the export's, warpavatar.mesh.surface.SILHOUETTE_ROUNDS; "
                             "0: none)")
    parser.add_argument("--shading", choices=("texture", "vertex-colors"), default="texture",
                        help="colour the mesh from its texture or its vertex colours (default %(default)s)")
    parser.add_argument("--supersample", type=int, default=1,
                        help="ray cast the mesh at this many times the resolution along each axis and box-filter it "
                             "down (antialiased edges and texture; default %(default)s: one ray a pixel)")
    parser.add_argument("--scale", type=float, default=None,
                        help="image scale of the frames (default: the fit's image_scale from its config.json)")
    parser.add_argument("--pixel-size", type=float, default=None,
                        help="training pixel width at the subject [m] the mesh's renders are blurred by (default: what "
                             "the fit recorded, none where it recorded none; 0: no blur)")
    parser.add_argument("--stand-in", action="store_true",
                        help="measure a stand-in mesh (the convex hull of the Gaussians) instead of the export's")
    return parser


def _table(rows: dict[str, dict]) -> str:
    header = ["folder", "frames", "mesh PSNR", "mesh SSIM", "GS PSNR", "GS SSIM", "IoU", "IoU min", "mesh only",
              "GS only", "IoU mask", "GS IoU mask", "mesh ms", "GS ms"]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for label, row in rows.items():
        cells = [label, str(row["frame_count"]), f"{row['mesh_psnr_masked']:.2f}", f"{row['mesh_ssim_masked']:.4f}",
                 f"{row['gaussians_psnr_masked']:.2f}", f"{row['gaussians_ssim_masked']:.4f}", f"{row['iou']:.4f}",
                 f"{row['iou_min']:.4f}", f"{row['mesh_only']:.4f}", f"{row['gaussians_only']:.4f}",
                 f"{row['iou_mask']:.4f}", f"{row['gaussians_iou_mask']:.4f}",
                 f"{row['mesh_render_ms']:.1f}", f"{row['gaussians_render_ms']:.1f}"]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _run(args) -> int:
    from warpavatar.cli.common import check_output_path, cpu_torch_settings, resolve_device
    from warpavatar.cli.eval import fit_image_scale
    from warpavatar.io.output_files import write_json_atomic
    from warpavatar.model import Avatar

    if args.output is not None:
        check_output_path(args.output, "-o", folder=False)
    if not args.video_folder.is_dir():
        raise ValueError(f"{args.video_folder}: is not a folder")
    device = resolve_device(args.device)
    scale = args.scale if args.scale is not None else fit_image_scale(args.avatar)
    from warpavatar.mesh.build import recorded_pixel_size

    pixel_size = args.pixel_size if args.pixel_size is not None else recorded_pixel_size(args.avatar)
    with cpu_torch_settings(device):
        avatar = Avatar.load(args.avatar, device=device)
        start = time.perf_counter()
        timings: dict[str, float] = {}
        chosen: dict = {}
        if args.stand_in:
            mesh = stand_in_mesh(avatar)
        else:
            from warpavatar.mesh.build import build_avatar_mesh, recorded_training_motion

            mesh = build_avatar_mesh(avatar, triangles=args.triangles, texture_size=args.texture_size,
                                     view_count=args.view_count, view_size=args.view_size,
                                     training_pixel_size=pixel_size or None,
                                     training_motion=recorded_training_motion(args.avatar, avatar.skeleton),
                                     max_voxels=args.max_voxels,
                                     silhouette_rounds=args.silhouette_rounds, progress=False, timings=timings,
                                     settings=chosen)
        build_seconds = time.perf_counter() - start
        shading = "texture" if args.shading == "texture" else "vertex_colors"
        rows = {label: measure_folder(avatar, mesh, video, frames=args.frames, shading=shading,
                                      supersample=args.supersample)
                for label, video in _folders(args.video_folder, scale)}
    textured = shading == "texture" and mesh.texture is not None and mesh.uvs is not None
    summary = {"avatar": str(args.avatar), "video_folder": str(args.video_folder), "device": str(device),
               "scale": scale, "frames_per_folder": args.frames, "stand_in": bool(args.stand_in),
               "settings": {"triangles": args.triangles, "texture_size": args.texture_size,
                            "view_count": args.view_count, "view_size": args.view_size, "shading": args.shading,
                            "supersample": args.supersample, "pixel_size": pixel_size},
               "mesh": {"vertices": mesh.vertex_count, "faces": mesh.face_count,
                        "texture_size": None if mesh.texture is None else list(mesh.texture.shape[:2]),
                        "shading": "texture" if textured else "vertex_colors", "build_seconds": build_seconds,
                        "stage_seconds": timings, **chosen},
               "iou_target": IOU_TARGET, "rows": rows}
    print(f"mesh: {mesh.vertex_count} vertices, {mesh.face_count} triangles, "
          f"{'textured' if textured else 'vertex colours'}, built in {build_seconds:.1f} s"
          f"{' (stand-in)' if args.stand_in else ''}; frames at scale {scale:g} on {device}; renders blurred for a "
          f"training pixel of {'none' if not pixel_size else f'{1000 * pixel_size:.1f} mm'}"
          + (f"; {chosen['view_size']} px renders, {1000 * chosen['voxel_size']:.1f} mm voxels" if chosen else ""))
    print(_table(rows))
    train = rows.get("train")
    if train is not None:
        verdict = "meets" if train["iou"] >= IOU_TARGET else "misses"
        print(f"training-frame silhouette IoU {train['iou']:.4f} {verdict} the target {IOU_TARGET}")
    if args.output is not None:
        write_json_atomic(args.output, summary)
    return 0


def main(argv=None) -> int:
    from warpavatar.cli.common import friendly_errors

    args = _build_parser().parse_args(argv)
    for flag, value, low in (("--frames", args.frames, 0), ("--triangles", args.triangles, 4),
                             ("--texture-size", args.texture_size, 8), ("--view-count", args.view_count, 1),
                             ("--view-size", args.view_size, 8), ("--supersample", args.supersample, 1),
                             ("--max-voxels", args.max_voxels, 1)):
        if value is not None and value < low:
            print(f"error: {flag} must be at least {low}, got {value}", file=sys.stderr)
            return 2
    if args.pixel_size is not None and not (math.isfinite(args.pixel_size) and args.pixel_size >= 0):
        print(f"error: --pixel-size must be a number of metres >= 0, got {args.pixel_size}", file=sys.stderr)
        return 2
    if args.scale is not None and not (math.isfinite(args.scale) and args.scale > 0):
        print(f"error: --scale must be a positive number, got {args.scale}", file=sys.stderr)
        return 2
    return friendly_errors(lambda _argv: _run(args))(None)


if __name__ == "__main__":
    sys.exit(main())
