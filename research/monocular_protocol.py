"""Real footage measured honestly: fit one camera of a calibrated multi-view video, evaluate on the others.

    python -m research.monocular_protocol DEMO -o OUT [--train-camera cam01] [--preset default] [--device cuda]
        [--holdout-every 5] [--eval-refine-steps 0] [--eval-scale 1] [--refine-modes off,on]
        [--oracle [--oracle-modes off]] [fit flags...]

DEMO holds ``videos/*.mp4`` (synchronized) and ``calibration/`` (one ``.toml`` or ``.qca.txt``), as
``../shared/raw/pose2sim_demo`` does. What is done, and why it does not cheat:

1. ``warpavatar-prepare`` runs twice: on the training camera alone (monocular mode, as a user with one phone
   video would; its focal length from the calibration unless ``--focal-px``), and on all cameras with the
   calibration (the calibrated world, used only for evaluation).
2. The monocular world is aligned to the calibrated one by the similarity transform (scale, rotation,
   translation) that best maps the monocular skeleton's joints onto the calibrated skeleton's, over every frame
   (Umeyama's least squares). Only skeletons go into it, never images.
3. The evaluation subject (``OUT/subject``, docs/FORMAT.md) is made of the monocular training folder without
   every ``--holdout-every``-th frame (``train/``), those withheld instants (``novel_view/<train camera>_heldout``:
   poses as estimated, never fitted), and each other camera's frames at training instants
   (``novel_view/<camera>``: their images and masks, their calibrated cameras carried into the monocular world
   by the inverse alignment, and the monocular poses of those instants, so a fit renders them in its refined
   poses).
4. The subject is fitted with pose refinement off and on, and each fit is evaluated on every held-out folder
   (masked PSNR/SSIM; with ``--eval-refine-steps N`` also after N steps of test-time pose refinement).
5. With ``--oracle``, a bound on what better poses could buy: the same camera's same instants fitted in the
   calibrated world with the calibrated skeleton (triangulated from every camera, so its depth is seen;
   ``OUT/oracle``, refinement off; ``--oracle-modes off,on`` adds a fit that refines them too), evaluated on the
   same held-out instants and views in that world. Refinement from one camera cannot be expected to beat it on
   the other views: it is what poses that every camera agrees on give, not what the training camera's images can
   tell.

``--subject-scale`` writes both subjects' frames at that fraction of the prepared size (for transfer or speed).

Writes ``OUT/protocol_<modes>.json`` and prints a markdown table.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

__all__ = ["similarity_transform", "camera_into_monocular_world", "build_evaluation_subject", "protocol_runs"]


REFINE_MODES = ("off", "on", "auto")


def protocol_runs(subject_modes: str, oracle_modes: str, *, subject: Path, oracle: Path) -> list[tuple]:
    """The fits of the protocol, in order: ``(name, folder, --refine-poses value)`` for each of the
    comma-separated ``subject_modes`` (named by the mode) and ``oracle_modes`` (``oracle`` for ``off``, as the
    protocol has always named its oracle, else ``oracle_<mode>``).

    Raises:
        ValueError: a mode that ``--refine-poses`` does not take, one given twice, or no fit at all.
    """
    runs = []
    for modes, folder, prefix in ((subject_modes, subject, None), (oracle_modes, oracle, "oracle")):
        listed = [mode.strip() for mode in modes.split(",") if mode.strip()]
        for mode in listed:
            if mode not in REFINE_MODES:
                raise ValueError(f"refine mode {mode!r} is not one of {', '.join(REFINE_MODES)}")
        if len(set(listed)) != len(listed):
            raise ValueError(f"a refine mode is listed twice in {modes!r}")
        for mode in listed:
            name = mode if prefix is None else prefix if mode == "off" else f"{prefix}_{mode}"
            runs.append((name, folder, mode))
    if not runs:
        raise ValueError("nothing to fit: --refine-modes is empty and --oracle is not given")
    return runs


def similarity_transform(source: np.ndarray, target: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """The scale ``s``, rotation ``R`` [3,3] and translation ``t`` [3] minimizing ``sum |s R x + t - y|^2`` over
    corresponding points ``source`` x [N,3] and ``target`` y [N,3] (Umeyama 1991; a proper rotation).

    Raises:
        ValueError: fewer than 3 points, or points that do not span a plane.
    """
    source, target = np.asarray(source, dtype=np.float64), np.asarray(target, dtype=np.float64)
    if source.shape != target.shape or source.ndim != 2 or source.shape[1] != 3 or source.shape[0] < 3:
        raise ValueError(f"need matching [N>=3, 3] point sets, got {source.shape} and {target.shape}")
    mean_source, mean_target = source.mean(0), target.mean(0)
    centred_source, centred_target = source - mean_source, target - mean_target
    variance = (centred_source ** 2).sum() / source.shape[0]
    covariance = centred_target.T @ centred_source / source.shape[0]
    left, singular, right = np.linalg.svd(covariance)
    if variance <= 0 or singular[1] <= 1e-12 * max(singular[0], 1e-300):
        raise ValueError("the points do not span a plane: no unique similarity transform")
    sign = np.eye(3)
    sign[2, 2] = np.sign(np.linalg.det(left) * np.linalg.det(right)) or 1.0
    rotation = left @ sign @ right
    scale = float(np.trace(np.diag(singular) @ sign) / variance)
    return scale, rotation, mean_target - scale * rotation @ mean_source


def camera_into_monocular_world(world_to_camera: np.ndarray, scale: float, rotation: np.ndarray,
                                translation: np.ndarray) -> np.ndarray:
    """A calibrated camera's world-to-camera transform [4,4] expressed in the monocular world, where ``x_cal = s R
    x_mono + t``. Camera coordinates come out divided by ``s`` (a rigid transform again), which changes no
    projection."""
    cal_rotation, cal_translation = world_to_camera[:3, :3], world_to_camera[:3, 3]
    out = np.eye(4)
    out[:3, :3] = cal_rotation @ rotation
    out[:3, 3] = (cal_rotation @ translation + cal_translation) / scale
    return out


def _subset(video, rows):
    """The frames ``rows`` of ``video``, as a new VideoFolder."""
    rows = np.asarray(rows, dtype=np.int64)
    return replace(video, frame_ids=video.frame_ids[rows], images=video.images[rows],
                   masks=None if video.masks is None else video.masks[rows],
                   cameras=[video.cameras[i] for i in rows], bone_transforms=video.bone_transforms[rows],
                   joint_positions=None if video.joint_positions is None else video.joint_positions[rows])


def _held_out_rows(frame_ids, holdout_every: int) -> tuple[list[int], list[int]]:
    """Rows of the withheld instants (``id % n == n // 2``) and of the kept ones."""
    ids = np.asarray(frame_ids).tolist()
    held = [row for row, frame in enumerate(ids) if holdout_every > 1 and frame % holdout_every == holdout_every // 2]
    return held, sorted(set(range(len(ids))) - set(held))


def _protocol_folders(train, novel_views, *, train_camera: str, holdout_every: int, carry=None) -> tuple[dict, int]:
    """The folders of a protocol subject by relative path: ``train`` without its withheld instants, those instants
    as ``novel_view/<train camera>_heldout``, and each novel view at the training instants it has (passed through
    ``carry`` when given); and the number of withheld frames."""
    held, kept = _held_out_rows(train.frame_ids, holdout_every)
    folders = {"train": _subset(train, kept)}
    if held:
        folders[f"novel_view/{train_camera}_heldout"] = _subset(train, held)
    training_ids = set(train.frame_ids[kept].tolist())
    for name, view in novel_views.items():
        rows = [row for row, frame in enumerate(view.frame_ids.tolist()) if frame in training_ids]
        if rows:
            view = _subset(view, rows)
            folders[f"novel_view/{name}"] = view if carry is None else carry(view)
    return folders, len(held)


def _write_subject(folders: dict, output: Path, *, overwrite: bool) -> None:
    """Write the video folders ``{relative path: VideoFolder}`` under ``output`` (staged, then renamed)."""
    from warpavatar import data

    with data.staged_folder(output, overwrite=overwrite) as staging:
        for relative, video in folders.items():
            data.write_video_folder(video, staging / relative)


def build_oracle_subject(calibrated, output: Path, *, train_camera: str, holdout_every: int,
                         overwrite: bool = False) -> dict:
    """Write the oracle of the protocol (module docstring, step 5) to ``output``: the calibrated subject's training
    camera without its withheld instants (``train/``), those instants (``novel_view/<train camera>_heldout``) and
    the other cameras at training instants, all with the calibrated skeleton's poses and cameras.

    Returns:
        The folder names and the number of withheld frames.
    """
    folders, held = _protocol_folders(calibrated.train, calibrated.novel_view, train_camera=train_camera,
                                      holdout_every=holdout_every)
    _write_subject(folders, output, overwrite=overwrite)
    return {"folders": sorted(folders), "held_out_frames": held}


def build_evaluation_subject(mono_train, calibrated, output: Path, *, train_camera: str, holdout_every: int,
                             overwrite: bool = False) -> dict:
    """Write the evaluation subject of the protocol (module docstring, step 3) to ``output``.

    Args:
        mono_train: the monocular :class:`~warpavatar.data.VideoFolder` of the training camera.
        calibrated: the calibrated :class:`~warpavatar.data.Subject` (its train/ is the same camera).
        holdout_every: withhold every n-th training instant (the ones with ``id % n == n // 2``).

    Returns:
        ``{"scale", "rotation", "translation", "alignment_rms": [world units of the calibration]}`` and the
        folder names.
    """
    cal_train = calibrated.train
    shared = sorted(set(mono_train.frame_ids.tolist()) & set(cal_train.frame_ids.tolist()))
    if len(shared) < 3:
        raise ValueError("the monocular and calibrated folders share fewer than 3 frames")
    mono_rows = {frame: row for row, frame in enumerate(mono_train.frame_ids.tolist())}
    cal_rows = {frame: row for row, frame in enumerate(cal_train.frame_ids.tolist())}
    if mono_train.joint_positions is None or cal_train.joint_positions is None:
        raise ValueError("both folders need joint_positions in poses.npz (warpavatar-prepare writes them)")
    source = mono_train.joint_positions[[mono_rows[f] for f in shared]].reshape(-1, 3)
    target = cal_train.joint_positions[[cal_rows[f] for f in shared]].reshape(-1, 3)
    scale, rotation, translation = similarity_transform(source, target)
    residual = (scale * source @ rotation.T + translation) - target
    alignment_rms = float(np.sqrt((residual ** 2).sum(-1).mean()))

    def into_monocular_world(view):  # calibrated cameras carried over, the monocular poses of those instants
        cameras = [replace(camera, world_to_camera=camera_into_monocular_world(
            np.asarray(camera.world_to_camera, dtype=np.float64), scale, rotation, translation).astype(np.float32))
            for camera in view.cameras]
        poses = mono_train.bone_transforms[[mono_rows[f] for f in view.frame_ids.tolist()]]
        return replace(view, cameras=cameras, skeleton=mono_train.skeleton, bone_transforms=poses,
                       joint_positions=None, meta={**view.meta, "aligned_from_calibration": True,
                                                   "poses": "estimated" if mono_train.poses_estimated else "exact"})

    folders, held = _protocol_folders(mono_train, calibrated.novel_view, train_camera=train_camera,
                                      holdout_every=holdout_every, carry=into_monocular_world)
    _write_subject(folders, output, overwrite=overwrite)
    return {"scale": scale, "rotation": rotation.tolist(), "translation": translation.tolist(),
            "alignment_rms": alignment_rms, "folders": sorted(folders), "held_out_frames": held}


def _prepared(args) -> tuple[Path, Path] | None:
    """The monocular and calibrated subjects prepared from the demo's videos (``warpavatar-prepare``, once);
    None when the demo lacks the training camera's video or a calibration."""
    from warpavatar.prepare.calibration import match_cameras, read_calibration
    from warpavatar.prepare.pipeline import prepare_subject

    videos = sorted((args.demo / "videos").glob("*.mp4"))
    calibrations = sorted(p for p in (args.demo / "calibration").glob("*") if p.is_file())
    train_video = next((v for v in videos if v.stem == args.train_camera), None)
    if train_video is None or not calibrations:
        return None
    calibration = calibrations[0]

    licence = args.demo / "LICENSE.txt"
    licence = licence if licence.exists() else None
    focal = args.focal_px
    if focal is None:
        focal = float(match_cameras([train_video.stem], read_calibration(calibration))[0].K[0, 0])
    mono_folder, multi_folder = args.output / "mono", args.output / "calibrated"
    if not mono_folder.exists():
        prepare_subject([train_video], mono_folder, focal_px=focal, license_file=licence)
    if not multi_folder.exists():
        others = [v for v in videos if v != train_video]
        prepare_subject([train_video, *others], multi_folder, calibration=calibration,
                        novel_view_stride=args.holdout_every, license_file=licence)
    return mono_folder, multi_folder


def main(argv=None) -> int:
    import torch

    from warpavatar import data
    from warpavatar.fit.arguments import add_config_arguments, config_from_arguments

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("demo", type=Path, help="folder with videos/*.mp4 and calibration/ (a .toml or .qca.txt); "
                        "read only while OUT lacks the subjects made from it")
    parser.add_argument("-o", "--output", type=Path, required=True, help="working folder (prepared subjects, fits)")
    parser.add_argument("--train-camera", default="cam01", help="the video fitted (default: cam01)")
    parser.add_argument("--focal-px", type=float, default=None,
                        help="focal length [pixels of the original video] for the monocular prepare (default: "
                             "the calibrated one of the training camera)")
    parser.add_argument("--holdout-every", type=int, default=5,
                        help="withhold every n-th instant of the training camera from the fit (default: 5)")
    parser.add_argument("--eval-refine-steps", type=int, default=0,
                        help="also report metrics after this many test-time pose refinement steps (default: 0)")
    parser.add_argument("--eval-scale", type=float, default=1.0,
                        help="image scale of the evaluation (default: 1, the prepared frames' size)")
    parser.add_argument("--refine-modes", default="off,on",
                        help="the --refine-poses values to fit and compare, comma-separated (default: off,on)")
    parser.add_argument("--oracle", action="store_true",
                        help="also fit the oracle: the training camera with the calibrated poses (step 5)")
    parser.add_argument("--oracle-modes", default=None,
                        help="with --oracle: the --refine-poses values the oracle is fitted with, comma-separated "
                             "(default: off; 'off,on' also measures what refinement adds to poses that every "
                             "camera agrees on)")
    parser.add_argument("--subject-scale", type=float, default=1.0,
                        help="size of the written subjects' frames, a fraction of the prepared ones' (default: 1)")
    parser.add_argument("--preset", default="default", help="fit preset (default: default)")
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu", help="torch device")
    add_config_arguments(parser)
    args = parser.parse_args(argv)
    if args.holdout_every < 2:
        parser.error("--holdout-every must be at least 2")
    if not 0 < args.subject_scale <= 1:
        parser.error("--subject-scale must lie in (0, 1]")
    if args.oracle_modes is not None and not args.oracle:
        parser.error("--oracle-modes needs --oracle")
    subject_folder, oracle_folder = args.output / "subject", args.output / "oracle"
    try:
        runs = protocol_runs(args.refine_modes, (args.oracle_modes or "off") if args.oracle else "",
                             subject=subject_folder, oracle=oracle_folder)
    except ValueError as error:
        parser.error(str(error))
    from warpavatar.evaluate import evaluate_avatar, write_json_atomic
    from warpavatar.fit import Trainer, load_training_video

    recipe = {"holdout_every": args.holdout_every, "subject_scale": args.subject_scale}
    made = subject_folder / "alignment.json"
    alignment = json.loads(made.read_text()) if made.exists() else None
    remake = alignment is None or any(alignment.get(key) != value for key, value in recipe.items())
    if remake or (args.oracle and not oracle_folder.exists()):
        prepared = _prepared(args)
        if prepared is None:
            print(f"error: {args.demo}: needs videos/{args.train_camera}.mp4 and a calibration file", file=sys.stderr)
            return 2
        mono_folder, multi_folder = prepared
        calibrated = data.load_subject(multi_folder, scale=args.subject_scale)
        if remake:
            alignment = build_evaluation_subject(
                data.load_video_folder(mono_folder / "train", scale=args.subject_scale), calibrated,
                subject_folder, train_camera=args.train_camera, holdout_every=args.holdout_every, overwrite=True)
            write_json_atomic(made, {**alignment, **recipe})
        if args.oracle:
            build_oracle_subject(calibrated, oracle_folder, train_camera=args.train_camera,
                                 holdout_every=args.holdout_every, overwrite=True)
    print(f"alignment: scale {alignment['scale']:.4f}, joints {alignment['alignment_rms'] * 1000:.0f} mm rms apart")
    print("| refine poses | folder | masked PSNR | masked SSIM | after test-time refinement | frames | fit min |")
    print("|---|---|---|---|---|---|---|", flush=True)
    rows = []
    for name, folder, refine in runs:
        args.refine_poses = refine
        config = config_from_arguments(args, args.preset)
        video = load_training_video(folder / "train", config)
        start = time.time()
        trainer = Trainer(video, config, args.output / f"fit_{name}", device=args.device)
        trainer.fit(progress=False)
        minutes = (time.time() - start) / 60
        full = data.load_subject(folder, scale=args.eval_scale)
        for view, video in full.novel_view.items():
            result = evaluate_avatar(trainer.avatar, video, progress=False, refine_steps=args.eval_refine_steps)
            refined = result.get("refined") or {}
            rows.append({"refine_poses": name, "folder": view, "psnr_masked": result["psnr_masked"],
                         "ssim_masked": result["ssim_masked"], "psnr_masked_test_refined": refined.get("psnr_masked"),
                         "frames": result["frame_count"], "fit_min": minutes})
            refined = rows[-1]["psnr_masked_test_refined"]
            print(f"| {name} | {view} | {result['psnr_masked']:.2f} | {result['ssim_masked']:.3f} | "
                  f"{'' if refined is None else f'{refined:.2f}'} | {result['frame_count']} | {minutes:.1f} |",
                  flush=True)
    names = "_".join(name for name, _, _ in runs)
    write_json_atomic(args.output / f"protocol_{names}.json", {"alignment": alignment, "rows": rows,
                                                               "preset": args.preset, "device": args.device})
    return 0


if __name__ == "__main__":
    sys.exit(main())
