"""Do the simulated garment's global physics or its rest shape hold its novel views back? Roll the training motion
out again under changed parameters and score every view of the training instants.

    python -m research.garment_sweep AVATAR SUBJECT [--variant SPEC ...] [--skinned] [--retexture STEPS]
        [--stride 3] [--scale 1.0] [--height-band 0.28 0.76] [--device cpu] [--json PATH]

``AVATAR`` is a fit's ``avatar.pt`` (or its folder) with a garment (``--garment auto`` found one); ``SUBJECT`` the
subject folder it was fitted on (``train/`` and ``novel_view/*`` of the same instants). The first row is the
fitted garment; each ``--variant`` changes some of the cloth's learned values for the whole rollout (the settle at
the first training pose, then every frame), everything else of the avatar as fitted (its Gaussians, their
colours and their places on the nodes). A SPEC is comma-separated ``key=value`` pairs:

* ``stiffness=F``: every spring's stiffness times ``F`` (raised at most to 0.999 of its stability bound);
* ``damping=F``, ``drag=F``: the edge damping and the air drag as fractions of their bounds, in (0, 1);
* ``mass=S``: the cloth's mass scale (the fitted one is reported), within the model's range;
* ``flare=F``: the rest shape's free nodes pushed away from the vertical axis through the attachment ring, by
  ``F`` at the lowest node and in proportion to the drop below the ring above it (an A-line cut; 1 = as fitted);
* ``strain=R``: strain limiting at ``R`` (> 1) times the rest lengths after every substep (with the cloth's own
  number of Jacobi passes when it was fitted with strain limiting, else 8), which keeps the cloth from sagging
  under its own weight.

``--skinned`` adds a row without any simulation: the rest shape posed by skinning alone, frame by frame.

The appearance of the garment's Gaussians was learned on the fitted cloth, so a variant that moves the cloth is
scored with a texture learned elsewhere. ``--retexture STEPS`` first re-learns, for every row, the garment
Gaussians' colours, opacities and scales on the training frames alone (``STEPS`` Adam steps, a random training
frame each, L1; the cloth frozen as that row rolls it out; the fitted values put back after): rows then compare
what each cloth motion allows once the texture is learned where it puts the cloth, and the training view's score
is a fair criterion (no held-out image is read).

Each row gives, per view and averaged over that view's training instants (every ``--stride``-th), the slab's
silhouette IoU (rendered alpha > 0.5 against the mask, within the ``--height-band`` slab as
``tools/error_breakdown.py --height-band``) and the slab's masked PSNR (dB). Physics that moved the cloth where
the video has it would raise the training view's IoU; if no variant lifts the novel views either, the global
parameters are not what the garment lacks.
"""

from __future__ import annotations

import math
import sys
from contextlib import contextmanager

import numpy as np
import torch

from research.common import (garment_appearance, garment_of, garment_tool_parser, load_garment_tool_inputs,
                             markdown_table, masked_psnr, slab_of)
from warpavatar.data import VideoFolderError
from warpavatar.evaluate import write_json_atomic
from warpavatar.model import Avatar
from warpavatar.model.parts import frame_intervals

__all__ = ["parse_variant", "changed_cloth", "fitted_values", "sweep_rows"]

KEYS = ("stiffness", "damping", "drag", "mass", "flare", "strain")

STRAIN_ITERATIONS = 8
"""Jacobi passes of strain limiting per substep that ``strain=R`` uses when the fitted cloth has none."""

STIFFNESS_CAP = 0.999
"""The largest fraction of its stability bound that ``stiffness=F`` raises a spring to."""


def parse_variant(spec: str) -> dict[str, float]:
    """The changes of one ``--variant`` SPEC (module docstring) as ``{key: value}``.

    Raises:
        ValueError: an unknown or repeated key, a value that is not a number, or one out of its range.
    """
    variant = {}
    for item in (part.strip() for part in spec.split(",")):
        key, equals, text = item.partition("=")
        key = key.strip()
        if not equals or key not in KEYS:
            raise ValueError(f"variant {spec!r}: {item!r} is not key=value with a key among {', '.join(KEYS)}")
        if key in variant:
            raise ValueError(f"variant {spec!r}: {key} is given twice")
        try:
            value = float(text)
        except ValueError:
            raise ValueError(f"variant {spec!r}: {key}={text.strip()!r} is not a number") from None
        if key in ("damping", "drag") and not 0.0 < value < 1.0:
            raise ValueError(f"variant {spec!r}: {key} is a fraction of its bound in (0, 1), got {value}")
        if key == "strain" and not (math.isfinite(value) and value > 1.0):
            raise ValueError(f"variant {spec!r}: strain is a limit above 1 (times the rest length), got {value}")
        if key in ("stiffness", "mass", "flare") and not (math.isfinite(value) and value > 0.0):
            raise ValueError(f"variant {spec!r}: {key} must be a positive number, got {value}")
        variant[key] = value
    return variant


def _logit(fraction: torch.Tensor | float) -> torch.Tensor:
    fraction = torch.as_tensor(fraction, dtype=torch.float32)
    return torch.log(fraction) - torch.log1p(-fraction)


@contextmanager
def changed_cloth(part, variant: dict[str, float]):
    """The garment ``part``'s cloth with ``variant``'s changes (:func:`parse_variant`) for the ``with`` block; its
    values are put back after.

    Raises:
        ValueError: a mass scale outside the model's range.
    """
    cloth = part.cloth
    saved = {name: tensor.detach().clone() for name, tensor in [*cloth.named_parameters(), *cloth.named_buffers()]}
    strain = (cloth.strain_limit, cloth.strain_iterations)
    try:
        if "strain" in variant:
            cloth.strain_limit = variant["strain"]
            cloth.strain_iterations = cloth.strain_iterations or STRAIN_ITERATIONS
        with torch.no_grad():
            if "stiffness" in variant and variant["stiffness"] != 1.0:
                fraction = torch.sigmoid(cloth.stiffness_logit)
                target = (fraction * variant["stiffness"]).clamp(1e-30, STIFFNESS_CAP)
                # a spring already past the cap (or saturated) keeps its own value where the factor would raise it
                changed = target < fraction if variant["stiffness"] < 1.0 else target > fraction
                cloth.stiffness_logit.copy_(torch.where(changed, _logit(target), cloth.stiffness_logit))
            for key, logit in (("damping", cloth.damping_logit), ("drag", cloth.drag_logit)):
                if key in variant:
                    logit.copy_(_logit(variant[key]))
            if "mass" in variant:
                exponent = math.log(variant["mass"]) / math.log(cloth.mass_range)
                if not -1.0 < exponent < 1.0:
                    raise ValueError(f"mass scale {variant['mass']} is outside the cloth's range "
                                     f"({1 / cloth.mass_range:g}, {cloth.mass_range:g})")
                cloth.mass_logit.fill_(math.atanh(exponent))
            if variant.get("flare", 1.0) != 1.0:
                rest = cloth.initial_rest_positions
                up = torch.as_tensor(part.hyper["up"], dtype=rest.dtype, device=rest.device)
                up = up / up.norm()
                ring = rest.index_select(0, cloth.attached).mean(0)
                height = (rest - ring) @ up
                drop = (height / height.min()).clamp(0.0, 1.0) if float(height.min()) < 0.0 else height * 0.0
                radial = rest - ring - height[:, None] * up
                widened = ring + height[:, None] * up + radial * (1.0 + (variant["flare"] - 1.0) * drop)[:, None]
                free = torch.ones(rest.shape[0], dtype=torch.bool, device=rest.device)
                free[cloth.attached] = False
                rest.copy_(torch.where(free[:, None], widened, rest))
                if cloth.rest_offset_logit is None:  # the rest lengths are then the rest shape's, kept as a buffer
                    pairs = cloth.pairs
                    cloth.rest_length.copy_((rest[pairs[:, 0]] - rest[pairs[:, 1]]).norm(dim=1))
        # the fused rollout frame keys its coefficients on the parameters' versions: say they changed
        torch.autograd.graph.increment_version(list(cloth.parameters()))
        yield cloth
    finally:
        cloth.strain_limit, cloth.strain_iterations = strain
        with torch.no_grad():
            for name, tensor in [*cloth.named_parameters(), *cloth.named_buffers()]:
                tensor.copy_(saved[name])
        torch.autograd.graph.increment_version(list(cloth.parameters()))


def fitted_values(part) -> dict[str, float]:
    """The fitted cloth's global values in the units of a SPEC (stiffness: the mean fraction of the bound)."""
    cloth = part.cloth
    with torch.no_grad():
        return {"stiffness": float(torch.sigmoid(cloth.stiffness_logit).mean()),
                "damping": float(torch.sigmoid(cloth.damping_logit)), "drag": float(torch.sigmoid(cloth.drag_logit)),
                "mass": float(cloth.mass_range ** math.tanh(float(cloth.mass_logit)))}


def sweep_rows(avatar: Avatar, subject, variants: list[dict[str, float]], *, stride: int = 3,
               band: tuple[float, float] = (0.28, 0.76), skinned: bool = False, retexture_steps: int = 0,
               seed: int = 0) -> list[dict]:
    """One row per variant (the fitted garment first, as ``{}``; with ``skinned`` a last row, ``None``, of the
    rest shape posed by skinning alone): ``{"variant", "iou": {view: mean}, "psnr": {view: mean}}`` over each
    view's training instants (every ``stride``-th frame of the view). With ``retexture_steps`` > 0 each row is
    scored after that many Adam steps re-learning the garment Gaussians' appearance on the training frames
    (module docstring; random frames drawn with ``seed``); the avatar's appearance is put back after each row.

    Raises:
        ValueError: the avatar has no garment, or a variant's value is outside the model's range.
    """
    part = garment_of(avatar)
    if retexture_steps < 0:
        raise ValueError(f"retexture_steps must be >= 0, got {retexture_steps}")
    device = avatar.gaussians.means.device
    train = subject.train
    background = torch.as_tensor(train.background, dtype=torch.float32, device=device)
    grid = avatar.field.grid_weights().detach()
    poses = [torch.as_tensor(pose, dtype=torch.float32, device=device) for pose in train.bone_transforms]
    bones = torch.stack([avatar.pose_bones(pose) for pose in poses])
    seconds = frame_intervals(train.frame_ids, train.fps).tolist()
    training_ids = [int(i) for i in train.frame_ids]
    # what every variant is scored against, read once: (camera, pose, training instant, slab, mask, truth) of each
    # scored frame of each view
    targets = {}
    for name, video in [("train", train), *subject.novel_view.items()]:
        frames = []
        for index in range(0, len(video.frame_ids), stride):
            frame_id = int(video.frame_ids[index])
            if frame_id in training_ids:
                frames.append((video.cameras[index],
                               torch.as_tensor(video.bone_transforms[index], dtype=torch.float32, device=device),
                               training_ids.index(frame_id), slab_of(video, index, band),
                               video.masks[index].astype(np.float64) / 255.0,
                               video.images[index].astype(np.float64) / 255.0))
        if frames:
            targets[name] = frames

    # the training frames on the device, once, for re-learning (uint8: a quarter of the floats' memory)
    images = torch.as_tensor(np.asarray(train.images), device=device) if retexture_steps else None

    def render(camera, pose, positions):
        return avatar.render(camera, pose, background=background, grid=grid, inputs={part.name: positions})

    @contextmanager
    def retextured(positions):
        """Re-learn the garment's appearance on the training frames with the cloth at ``positions`` [T,M,3] (with
        ``retexture_steps`` > 0; else the appearance stays as fitted)."""
        if not retexture_steps:
            yield
            return
        generator = torch.Generator().manual_seed(seed)
        with garment_appearance(avatar, part) as looks:
            optimizer = torch.optim.Adam(looks)
            for _ in range(retexture_steps):
                index = int(torch.randint(len(training_ids), (1,), generator=generator))
                truth = images[index].float() / 255.0
                loss = (render(train.cameras[index], poses[index], positions[index])[0] - truth).abs().mean()
                optimizer.zero_grad()
                loss.backward()
                optimizer.step()
            yield

    def scored(variant, positions):
        row = {"variant": None if variant is None else dict(variant), "iou": {}, "psnr": {}}
        with torch.no_grad():
            for name, frames in targets.items():
                ious, psnrs = [], []
                for camera, pose, instant, slab, mask, truth in frames:
                    image, alpha, _ = render(camera, pose, positions[instant])
                    drawn, filmed = alpha.cpu().numpy() > 0.5, mask > 0.5
                    union = ((drawn | filmed) & slab).sum()
                    ious.append(float((drawn & filmed & slab).sum() / union) if union else 1.0)
                    psnrs.append(masked_psnr(image.clamp(0, 1).cpu().numpy().astype(np.float64), truth, mask * slab))
                row["iou"][name], row["psnr"][name] = float(np.mean(ious)), float(np.mean(psnrs))
        return row

    rows = []
    for variant in [{}, *variants, *([None] if skinned else [])]:
        if variant is None:
            with torch.no_grad():
                positions = torch.stack([part.skinned_rest(frame_bones) for frame_bones in bones])
        else:
            with changed_cloth(part, variant), torch.no_grad():
                positions, _ = part.rollout(bones, seconds)
        with retextured(positions):
            rows.append(scored(variant, positions))
    return rows


def _label(variant: dict[str, float] | None) -> str:
    if variant is None:
        return "skinned (no simulation)"
    return ", ".join(f"{key}={value:g}" for key, value in variant.items()) or "fitted"


def main(argv=None) -> int:
    parser = garment_tool_parser(__doc__.split("\n\n")[0])
    parser.add_argument("--variant", action="append", default=[], metavar="SPEC",
                        help="a change of the cloth as comma-separated key=value (repeatable, one row each): "
                             "stiffness=F (times the learned stiffness, capped below its bound), damping=F and "
                             "drag=F (fractions of their bounds, in (0, 1)), mass=S (the mass scale), flare=F (the "
                             "rest shape widened into an A-line, F at the hem), strain=R (strain limiting at R > 1 "
                             "times the rest lengths); e.g. 'damping=0.01,drag=0.01'")
    parser.add_argument("--skinned", action="store_true",
                        help="add a row of the rest shape posed by skinning alone (no simulation)")
    parser.add_argument("--retexture", type=int, default=0, metavar="STEPS",
                        help="re-learn the garment Gaussians' colours, opacities and scales on the training frames "
                             "for STEPS Adam steps before scoring each row (0: score with the fitted appearance)")
    parser.add_argument("--stride", type=int, default=3, help="score every n-th frame of each view [frames]")
    args = parser.parse_args(argv)
    if args.stride < 1:
        parser.error(f"--stride must be >= 1, got {args.stride}")
    if args.retexture < 0:
        parser.error(f"--retexture must be >= 0, got {args.retexture}")
    try:
        variants = [parse_variant(spec) for spec in args.variant]
    except ValueError as error:
        parser.error(str(error))
    try:
        subject, avatar = load_garment_tool_inputs(parser, args)
        part = avatar.part("garment")
        if part is not None and part.node_count:
            fitted = fitted_values(part)
            print("fitted: " + ", ".join(f"{key} {value:.3g}" for key, value in fitted.items())
                  + " (stiffness: mean fraction of its bound; damping, drag: fractions of theirs)")
        rows = sweep_rows(avatar, subject, variants, stride=args.stride, band=tuple(args.height_band),
                          skinned=args.skinned, retexture_steps=args.retexture)
    except (VideoFolderError, ValueError, FileNotFoundError) as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    names = list(rows[0]["iou"])
    print(markdown_table([
        {"cloth": _label(row["variant"]),
         **{f"{n} slab IoU / dB": f"{row['iou'][n]:.3f} / {row['psnr'][n]:.2f}" for n in names if n in row["iou"]}}
        for row in rows]))
    if args.json:
        write_json_atomic(args.json, rows)
    return 0


if __name__ == "__main__":
    sys.exit(main())
