"""Export formats of a fitted avatar, chosen by the suffix of the output's name: one registry that
``warpavatar-animate`` writes through.

An :class:`Exporter` says which suffixes it writes (``.usdc``), its layout where one suffix has several
(``--layout particlefield`` or ``points`` for USD), whether it takes a motion (an animation) or only the rest
pose, and writes the file. :func:`exporter_for` picks the exporter of a path. The built-in formats:

* :class:`UsdGaussiansExporter` (``.usdc``, ``.usd``, ``.usda``): the animated Gaussians as OpenUSD, layout
  ``particlefield`` (``UsdVol.ParticleField3DGaussianSplat``, the default) or ``points`` (``UsdGeom.Points``),
  optionally with the UsdSkel rig, and a garment sheet as an animated ``UsdGeom.Mesh``
  (:class:`~warpavatar.io.usd.GaussianUsdWriter`);
* :class:`RestPosePlyExporter` (``.ply``): the canonical Gaussians as a 3DGS ``.ply``, the file a fit writes as
  ``canonical.ply``.

Other packages add formats through the entry-point group :data:`ENTRY_POINT_GROUP` (each entry an
:class:`Exporter` subclass or instance; :func:`load_entry_points`), or by calling :func:`register_exporter`.
An exporter writes its file atomically (through :mod:`warpavatar.io.output_files`: a temporary name of its own
beside the output, renamed once complete); the command holds the output's lock while it runs.
"""

from __future__ import annotations

import dataclasses
import importlib.metadata
import os
import shutil
import warnings
from collections.abc import Iterator, Mapping
from pathlib import Path

import numpy as np

__all__ = ["ENTRY_POINT_GROUP", "Exporter", "ExportMotion", "ExportOptions", "register_exporter",
           "unregister_exporter", "registered_exporters", "exporter_for", "exporter_layouts", "describe_exporters",
           "load_entry_points", "UsdGaussiansExporter", "RestPosePlyExporter"]

ENTRY_POINT_GROUP = "warpavatar.exporters"
"""Entry-point group through which installed packages add export formats (each entry an :class:`Exporter`
subclass, instantiated with no arguments, or an instance)."""


@dataclasses.dataclass(frozen=True, eq=False)
class ExportMotion:
    """The motion an animated format is written with, as ``warpavatar-animate`` read it.

    Attributes:
        bone_transforms: [T,J,4,4] float32 bone transforms of the skeleton (rest pose -> posed world), one row
            per frame.
        frame_ids: [T] int frame ids of the rows, in frames of the motion's clock.
        clock_fps: frame ids per second (the time steps of parts with state over time).
        fps: frames per second the output declares (``--fps``; by default ``clock_fps``).
        part_inputs: explicit per-frame inputs of the avatar's parts by part name, frame first (the grown
            joints' rotations [T,E,4] of ``--grown-rotations``); empty: each part decides.
    """

    bone_transforms: np.ndarray
    frame_ids: np.ndarray
    clock_fps: float
    fps: float
    part_inputs: Mapping[str, np.ndarray] = dataclasses.field(default_factory=dict)

    @classmethod
    def from_motion(cls, motion, *, fps: float | None = None,
                    part_inputs: Mapping[str, np.ndarray] | None = None) -> "ExportMotion":
        """From a :class:`~warpavatar.io.motion.Motion`; ``fps`` None keeps the motion's."""
        return cls(motion.bone_transforms, motion.frame_ids, float(motion.fps), float(fps or motion.fps),
                   dict(part_inputs or {}))

    @property
    def frame_count(self) -> int:
        """T, the number of rows."""
        return int(self.bone_transforms.shape[0])

    def time_codes(self) -> np.ndarray:
        """[T] int64 time codes of the rows (:func:`~warpavatar.io.animation.motion_time_codes`)."""
        from warpavatar.io.animation import motion_time_codes

        return motion_time_codes(self.frame_ids)

    def posed_frames(self, avatar) -> Iterator[dict]:
        """The avatar posed at each row, every part included (:func:`~warpavatar.io.animation.posed_frames`)."""
        from warpavatar.io.animation import posed_frames

        return posed_frames(avatar, self.bone_transforms, frame_ids=self.frame_ids, fps=self.clock_fps,
                            part_inputs=self.part_inputs)


@dataclasses.dataclass(frozen=True)
class ExportOptions:
    """What the command asks of every format.

    Attributes:
        skeleton: also write the skeleton and its animation (only formats with ``writes_skeleton``).
        progress: show a progress bar over the frames.
        keep_floaters: also write the Gaussians a format leaves out as floaters (only formats with
            ``drops_floaters``).
    """

    skeleton: bool = False
    progress: bool = True
    keep_floaters: bool = False


class Exporter:
    """One export format. Subclass it, set the class attributes and write :meth:`export`.

    Attributes:
        name: a unique name (``"usd-particlefield"``).
        suffixes: the lower-case endings of the names it writes, with the dot (``(".usdc", ".usd")``); the first
            one is its usual one.
        layout: its name among several formats of one suffix (``--layout``), or None.
        description: one line saying what the file holds, for ``--help``.
        animated: True: it takes a motion and writes every frame; False: it writes the rest pose only.
        writes_skeleton: it can also write the skeleton (``--skeleton``).
        drops_floaters: it leaves out stray Gaussians unless asked to keep them (``--keep-floaters``).
    """

    name: str = ""
    suffixes: tuple[str, ...] = ()
    layout: str | None = None
    description: str = ""
    animated: bool = True
    writes_skeleton: bool = False
    drops_floaters: bool = False

    def export(self, avatar, path: Path, *, motion: ExportMotion | None, options: ExportOptions) -> str:
        """Write ``avatar`` to ``path``, atomically (an existing file is replaced only by a complete one).

        Args:
            avatar: the :class:`~warpavatar.model.Avatar`.
            path: the output file; its folder exists.
            motion: the motion, for an ``animated`` format; None otherwise.
            options: what the command asks.

        Returns:
            a few words on what was written, for the command's ``wrote PATH (...)`` line
            (``"points, 12 frames at 30 fps, 13890 Gaussians"``).
        """
        raise NotImplementedError


_EXPORTERS: dict[str, Exporter] = {}


def _check_exporter(exporter: Exporter) -> None:
    kind = type(exporter).__name__
    if not isinstance(exporter.name, str) or not exporter.name:
        raise ValueError(f"exporter {kind} needs a name")
    suffixes = exporter.suffixes
    if (not isinstance(suffixes, tuple) or not suffixes
            or not all(isinstance(s, str) and len(s) > 1 and s.startswith(".") and s == s.lower() for s in suffixes)):
        raise ValueError(f"exporter {exporter.name!r}: suffixes must be a tuple of lower-case endings such as "
                         f"'.usdc', got {suffixes!r}")
    if exporter.layout is not None and not (isinstance(exporter.layout, str) and exporter.layout.isidentifier()):
        raise ValueError(f"exporter {exporter.name!r}: layout must be None or a word, got {exporter.layout!r}")
    if not isinstance(exporter.description, str) or not exporter.description or "\n" in exporter.description:
        raise ValueError(f"exporter {exporter.name!r} needs a one-line description")
    if not callable(getattr(exporter, "export", None)):
        raise ValueError(f"exporter {exporter.name!r} has no export method")


def register_exporter(exporter):
    """Add an export format; usable as a class decorator. Returns what it was given.

    Args:
        exporter: an :class:`Exporter` instance, or a subclass (instantiated with no arguments).

    Raises:
        ValueError: a name already taken, or a suffix and layout another format writes already, or malformed
            attributes.
    """
    instance = exporter() if isinstance(exporter, type) else exporter
    _check_exporter(instance)
    if instance.name in _EXPORTERS:
        raise ValueError(f"an exporter called {instance.name!r} is registered already "
                         f"({type(_EXPORTERS[instance.name]).__name__})")
    for other in _EXPORTERS.values():
        shared = [s for s in instance.suffixes if s in other.suffixes]
        if shared and other.layout == instance.layout:
            layout = f" with layout {instance.layout!r}" if instance.layout else ""
            raise ValueError(f"exporter {instance.name!r}: {shared[0]} files{layout} are written by "
                             f"{other.name!r} already")
    _EXPORTERS[instance.name] = instance
    return exporter


def unregister_exporter(name: str) -> None:
    """Remove an export format (tests, plugins that were only tried)."""
    _EXPORTERS.pop(name, None)


def registered_exporters() -> list[Exporter]:
    """Every registered export format, in the order registered."""
    return list(_EXPORTERS.values())


def exporter_layouts() -> list[str]:
    """Every layout name of the registered formats, each once, in the order registered."""
    return list(dict.fromkeys(e.layout for e in _EXPORTERS.values() if e.layout is not None))


def _known_suffixes() -> str:
    return ", ".join(dict.fromkeys(s for e in _EXPORTERS.values() for s in e.suffixes)) or "none"


def exporter_for(path: str | os.PathLike, layout: str | None = None, *, flag: str | None = None) -> Exporter:
    """The export format of ``path``, by the ending of its name (the longest registered suffix it ends in, any
    case), and by ``layout`` where that suffix has several formats.

    Args:
        path: the output file.
        layout: a format's layout; None: the first format registered for the suffix (USD: ``particlefield``).
        flag: the option that gave ``path`` (``"-o"``), for the messages.

    Raises:
        ValueError: no format writes files of that suffix (the message names it and the known ones), or none of
            that suffix has ``layout``.
    """
    path = Path(path)
    shown = f"{flag} {path}" if flag else str(path)
    name = path.name.lower()
    matches = [(suffix, e) for e in _EXPORTERS.values() for suffix in e.suffixes if name.endswith(suffix)]
    if not matches:
        ending = f"{path.suffix!r} files" if path.suffix else "files without a suffix"
        raise ValueError(f"{shown}: no export format writes {ending}; give a name ending in one of "
                         f"{_known_suffixes()}")
    longest = max(len(suffix) for suffix, _ in matches)
    suffix = next(s for s, _ in matches if len(s) == longest)
    candidates = [e for s, e in matches if s == suffix]
    if layout is None:
        return candidates[0]
    for exporter in candidates:
        if exporter.layout == layout:
            return exporter
    layouts = [e.layout for e in candidates if e.layout is not None]
    if layouts:
        raise ValueError(f"--layout {layout}: {suffix} files have no such layout; give one of {', '.join(layouts)}")
    with_layouts = ", ".join(dict.fromkeys(s for e in _EXPORTERS.values() if e.layout for s in e.suffixes))
    raise ValueError(f"--layout {layout}: {suffix} files have no layouts; --layout is for "
                     f"{with_layouts or 'no format registered now'}")


def describe_exporters() -> list[str]:
    """Two lines per registered format, for ``--help``: its suffixes, layout and whether it is animated, then its
    description."""
    defaults = set()  # suffixes whose default format (the first registered) is listed already
    lines = []
    for exporter in _EXPORTERS.values():
        default = all(s not in defaults for s in exporter.suffixes)
        defaults.update(exporter.suffixes)
        layout = ""
        if exporter.layout:
            layout = f" --layout {exporter.layout}{' (default)' if default else ''}"
        what = "an animation" if exporter.animated else "the rest pose only"
        lines += [f"  {' '.join(exporter.suffixes)}{layout}: {what}", f"      {exporter.description}"]
    return lines


def load_entry_points() -> list[str]:
    """Register the formats installed packages declare in :data:`ENTRY_POINT_GROUP`; returns their names.

    An entry that cannot be loaded, is not an :class:`Exporter`, or clashes with a registered one is skipped with
    a warning naming it (one broken plugin does not stop the others, or the built-in formats). An entry
    registered already (by its own module, or an earlier call) is skipped silently.
    """
    names = []
    for entry in importlib.metadata.entry_points(group=ENTRY_POINT_GROUP):
        try:
            value = entry.load()
            if isinstance(value, type) and issubclass(value, Exporter):
                if any(type(e) is value for e in _EXPORTERS.values()):
                    continue
            elif isinstance(value, Exporter):
                if _EXPORTERS.get(value.name) is value:
                    continue
            else:
                raise ValueError(f"{value!r} is not an Exporter subclass or instance")
            register_exporter(value)
            names.append(registered_exporters()[-1].name)
        except Exception as error:  # noqa: BLE001 - report any broken plugin, keep the others
            warnings.warn(f"warpavatar exporter entry point {entry.name!r} ({entry.value}) was not loaded: {error}",
                          stacklevel=2)
    return names


# -------------------------------------------------------------------------------------------------------------
# The built-in formats


class UsdGaussiansExporter(Exporter):
    """The animated Gaussians as OpenUSD in one ``layout`` (docs/export.md lists every attribute), optionally
    with the UsdSkel rig of :meth:`~warpavatar.model.Avatar.rig` (``--skeleton``: the grown joints included). A
    part that poses Gaussians on a triangle sheet (the garment of ``--garment-surface sheet``) adds that sheet as a
    ``UsdGeom.Mesh`` beside the Gaussians (``/Avatar/Garment``), its points those the Gaussians sit on each frame.

    ``.usdc`` and ``.usd`` are the binary crate format, written frame by frame with bounded memory. ``.usda`` is
    the text format: the crate is written first in a temporary folder of its own beside the output, then
    exported as text (larger and slower: for small exports that are to be read by eye or diffed).
    """

    suffixes = (".usdc", ".usd", ".usda")
    animated = True
    writes_skeleton = True

    def __init__(self, layout: str = "particlefield"):
        self.layout = layout
        self.name = f"usd-{layout}"
        self.description = {
            "particlefield": "OpenUSD UsdVol.ParticleField3DGaussianSplat prim (Omniverse, recent USD tools)",
            "points": "OpenUSD UsdGeom.Points prim with the Gaussians as primvars (Blender, older USD tools)",
        }.get(layout, f"OpenUSD Gaussians, layout {layout}")

    def export(self, avatar, path: Path, *, motion: ExportMotion | None, options: ExportOptions) -> str:
        if motion is None:
            raise ValueError(f"{path}: USD Gaussians are an animation and need a motion")
        path = Path(path)
        if path.suffix.lower() != ".usda":
            self._write_crate(avatar, path, motion=motion, options=options)
        else:
            self._write_text(avatar, path, motion=motion, options=options)
        return f"{self.layout}, {motion.frame_count} frames at {motion.fps:g} fps, {avatar.gaussians.count} Gaussians"

    def _write_crate(self, avatar, path: Path, *, motion: ExportMotion, options: ExportOptions) -> None:
        import tqdm

        from warpavatar.io.usd import GaussianUsdWriter

        skeleton = avatar.skeleton
        up_axis = "XYZ"[int(abs(skeleton.up).argmax())]
        g = avatar.gaussians
        sheets = _sheet_meshes(avatar)
        with GaussianUsdWriter(path, layout=self.layout, gaussian_count=g.count, sh_degree=g.sh_degree,
                               opacities=g.opacities.detach().cpu().numpy(),
                               sh_coeffs=g.sh_coefficients().detach().cpu().numpy(), fps=motion.fps, up_axis=up_axis,
                               meters_per_unit=1.0, skeleton=avatar.rig() if options.skeleton else None,
                               meshes=[mesh for mesh, _ in sheets]) as writer:
            time_codes = motion.time_codes()  # frames of the motion's clock, played at fps
            frames = tqdm.tqdm(motion.posed_frames(avatar), total=motion.frame_count, disable=not options.progress,
                               desc="animate")
            for t, posed in enumerate(frames):
                writer.write_frame(int(time_codes[t]), positions=posed["means"].cpu().numpy(),
                                   orientations=posed["quats"].cpu().numpy(),
                                   scales=posed["scales"].detach().cpu().numpy(),
                                   # the skeleton's transforms, then any grown joints' (ToMiE), as posed
                                   joint_transforms=posed["bone_transforms"].cpu().numpy() if options.skeleton
                                   else None,
                                   # the sheets the parts placed their Gaussians on this frame
                                   mesh_points={mesh.name: part.posed_sheet(posed)[0].cpu().numpy()
                                                for mesh, part in sheets})

    def _write_text(self, avatar, path: Path, *, motion: ExportMotion, options: ExportOptions) -> None:
        from pxr import Sdf, Tf

        from warpavatar.io.output_files import atomic_path, disk_full_error, is_disk_full, temporary_path
        from warpavatar.io.usd import _save_error

        # a scratch folder named as the output's temporaries are, so a killed export's is removed by the next one
        scratch = temporary_path(path)
        scratch.mkdir()
        try:
            crate = scratch / "crate.usdc"
            try:
                self._write_crate(avatar, crate, motion=motion, options=options)
            except OSError as error:
                if is_disk_full(error):
                    raise disk_full_error(path, error.errno) from None  # named as -o, not as the scratch file
                raise
            with atomic_path(path, suffix=".usda") as text:
                layer = Sdf.Layer.FindOrOpen(os.fspath(crate))
                try:
                    if layer is None or not layer.Export(os.fspath(text)):
                        raise OSError(f"{path}: USD cannot write the file")
                except Tf.ErrorException as error:
                    raise _save_error(os.fspath(path), error) from None
                finally:
                    del layer  # the last reference: the layer leaves Sdf's registry and unmaps the crate
        finally:
            shutil.rmtree(scratch, ignore_errors=True)


def _sheet_meshes(avatar) -> list:
    """The avatar's parts that pose Gaussians on a triangle sheet (a method ``posed_sheet(posed)`` returning the
    frame's vertices [V,3] and faces [F,3], with ``faces``, ``node_count`` and ``gaussian_ids``, as
    :class:`~warpavatar.extensions.garment_sheet_part.GarmentSheetPart`), each as ``(AnimatedMesh, part)``.

    The mesh is named after the part (``garment`` -> ``Garment``); its display colour is the opacity-weighted mean
    colour (SH DC term, as sRGB, made linear) of the part's Gaussians.
    """
    import torch

    from warpavatar.io.usd import AnimatedMesh
    from warpavatar.io.usd_mesh import srgb_to_linear
    from warpavatar.model.gaussians import sh_dc_to_rgb

    g = avatar.gaussians
    sheets = []
    for part in avatar.parts.values():
        if not callable(getattr(part, "posed_sheet", None)):
            continue
        with torch.no_grad():
            ids = part.gaussian_ids
            colors = sh_dc_to_rgb(g.sh_coefficients()[ids, 0, :]).clamp(0, 1).double().cpu().numpy()
            weights = g.opacities[ids].double().cpu().numpy()
        color = (0.5, 0.5, 0.5)
        if ids.numel():
            weights = weights if weights.sum() > 0 else np.ones_like(weights)
            linear = srgb_to_linear(colors * 255.0).astype(np.float64)
            color = tuple(np.clip(weights @ linear / weights.sum(), 0.0, 1.0).tolist())
        name = "".join(word.capitalize() for word in part.name.split("_")) or "Sheet"
        sheets.append((AnimatedMesh(name, part.faces.detach().cpu().numpy(), int(part.node_count), color), part))
    return sheets


class RestPosePlyExporter(Exporter):
    """The canonical (rest-pose) Gaussians as a 3DGS ``.ply`` (:func:`~warpavatar.io.ply.write_gaussian_ply`):
    byte for byte the ``canonical.ply`` a fit writes for the same avatar: Gaussians far from every bone or nearly
    transparent left out (:func:`~warpavatar.fit.outputs.canonical_floaters`) unless ``options.keep_floaters``."""

    name = "ply-rest-pose"
    suffixes = (".ply",)
    description = "3DGS .ply of the canonical Gaussians, as the fit's canonical.ply (splat viewers open it)"
    animated = False
    drops_floaters = True

    def export(self, avatar, path: Path, *, motion: ExportMotion | None, options: ExportOptions) -> str:
        from warpavatar.fit.outputs import write_canonical_ply

        written = write_canonical_ply(avatar.gaussians, path, skeleton=avatar.skeleton,
                                      keep_floaters=options.keep_floaters)
        left_out = avatar.gaussians.count - written
        floaters = f", {left_out} floaters left out (--keep-floaters keeps them)" if left_out else ""
        return f"3DGS .ply of the rest pose, {written} Gaussians{floaters}"


register_exporter(UsdGaussiansExporter("particlefield"))
register_exporter(UsdGaussiansExporter("points"))
register_exporter(RestPosePlyExporter)
