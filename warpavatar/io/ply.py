"""3D Gaussian Splatting ``.ply`` files, as written by the reference 3DGS code and read by splat viewers.

One ``vertex`` element, binary little endian, float32 properties in this order::

    x y z  nx ny nz  f_dc_0 f_dc_1 f_dc_2  f_rest_0 … f_rest_{3(K-1)-1}  opacity  scale_0 scale_1 scale_2
    rot_0 rot_1 rot_2 rot_3

with ``K = (sh_degree + 1)**2`` coefficients per colour channel. The stored values are the *raw* 3DGS
parameters: ``opacity`` is the logit of the opacity, ``scale_i`` the natural log of the linear scale,
``rot`` the quaternion (w first, not necessarily normalized), ``f_dc`` the degree-0 SH coefficient
(colour = 0.5 + 0.28209479 * f_dc), and ``f_rest`` the higher-order coefficients channel-major: all
``K - 1`` red coefficients, then green, then blue. The normals are written as zeros and ignored on reading.

The functions here take and return the *activated* values warpavatar uses everywhere else (linear
opacities in 0..1, linear scales), so ``write_gaussian_ply(path, **read_gaussian_ply(path))`` is a
round trip.
"""

from __future__ import annotations

import math
import os

import numpy as np

from warpavatar.io.output_files import atomic_open

__all__ = ["write_gaussian_ply", "read_gaussian_ply"]

# PLY scalar type names (both spellings of the standard) -> numpy little-endian dtype codes.
_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}

# Opacities are stored as logits: 0 and 1 exactly would be infinite, so they are pulled into this range first.
_OPACITY_EPS = 1e-7

_HEADER_LIMIT_BYTES = 1 << 20


def _to_numpy(name: str, value) -> np.ndarray:
    """A float array from a numpy array, a torch tensor (any device) or a nested sequence."""
    if hasattr(value, "detach") and hasattr(value, "cpu"):  # torch.Tensor, without importing torch
        value = value.detach().cpu().numpy()
    try:
        array = np.asarray(value)
    except Exception as error:  # pragma: no cover - exotic inputs
        raise TypeError(f"{name} must be array-like, got {type(value).__name__}") from error
    if array.dtype.kind not in "fiu":
        raise TypeError(f"{name} must hold real numbers, got dtype {array.dtype}")
    return array


def _check_array(name: str, value, shape: tuple, *, dtype=np.float32) -> np.ndarray:
    """Convert ``value`` to a contiguous array of ``dtype`` and check its shape and finiteness.

    ``shape`` holds ints, or None for a free dimension.
    """
    array = _to_numpy(name, value)
    if array.ndim != len(shape) or any(want is not None and got != want for got, want in zip(array.shape, shape)):
        pretty = "[" + ", ".join("*" if s is None else str(s) for s in shape) + "]"
        raise ValueError(f"{name} must have shape {pretty}, got {list(array.shape)}")
    array = np.ascontiguousarray(array, dtype=dtype)
    if array.size and not np.isfinite(array).all():
        bad = int(np.count_nonzero(~np.isfinite(array)))
        raise ValueError(f"{name} holds {bad} non-finite value(s) (NaN or inf)")
    return array


def _sh_degree_from_count(coefficient_count: int) -> int | None:
    """The degree d with (d+1)^2 == coefficient_count, or None."""
    degree = math.isqrt(coefficient_count) - 1
    return degree if degree >= 0 and (degree + 1) ** 2 == coefficient_count else None


def _check_gaussians(means, quats, scales, opacities, sh_coeffs) -> tuple[np.ndarray, ...]:
    """Validate one set of Gaussians (see :func:`write_gaussian_ply`); returns float32 arrays."""
    means = _check_array("means", means, (None, 3))
    count = means.shape[0]
    quats = _check_array("quats", quats, (count, 4))
    scales = _check_array("scales", scales, (count, 3))
    opacities = _check_array("opacities", opacities, (count,))
    sh_coeffs = _check_array("sh_coeffs", sh_coeffs, (count, None, 3))
    if _sh_degree_from_count(sh_coeffs.shape[1]) is None:
        raise ValueError(f"sh_coeffs must have (d+1)^2 coefficients per Gaussian (1, 4, 9, 16, ...), "
                         f"got {sh_coeffs.shape[1]}")
    if count and not (scales > 0).all():
        raise ValueError(f"scales must be > 0 (linear scales), got a minimum of {scales.min()}")
    if count and not ((opacities >= 0) & (opacities <= 1)).all():
        raise ValueError(f"opacities must be linear values in [0, 1], got range "
                         f"[{opacities.min()}, {opacities.max()}]")
    return means, quats, scales, opacities, sh_coeffs


def _property_names(rest_count: int) -> list[str]:
    names = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    names += [f"f_rest_{i}" for i in range(3 * rest_count)]
    names += ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    return names


def write_gaussian_ply(path: str | os.PathLike, *, means, quats, scales, opacities, sh_coeffs) -> str:
    """Write Gaussians to a 3DGS ``.ply`` file (binary little endian, float32).

    The file is written under a temporary name of its own in the same folder and renamed into place
    (:func:`~warpavatar.io.output_files.atomic_open`), so a reader never sees a half-written file and an error
    (a full disk: :class:`~warpavatar.io.output_files.DiskFullError`) leaves any existing file at ``path``
    untouched and no temporary file.

    Args:
        path: destination file.
        means: [N,3] float positions, world units.
        quats: [N,4] float rotations (w, x, y, z); stored as given (normalize them first if needed).
        scales: [N,3] float linear scales (standard deviations along the local axes), world units, > 0.
            Stored as their natural log.
        opacities: [N] float linear opacities in [0, 1]. Stored as logits; 0 and 1 are clamped to
            [1e-7, 1 - 1e-7] first since their logits are infinite.
        sh_coeffs: [N,(d+1)^2,3] float SH coefficients per Gaussian, coefficient index then RGB channel,
            3DGS convention (colour = 0.5 + SH evaluation).
        Numpy arrays, torch tensors (any device) or nested sequences are accepted.

    Returns:
        ``path`` as a string.

    Raises:
        ValueError: wrong shapes, non-finite values, non-positive scales, opacities outside [0, 1].
        TypeError: non-numeric inputs.
    """
    means, quats, scales, opacities, sh_coeffs = _check_gaussians(means, quats, scales, opacities, sh_coeffs)
    count, coefficient_count = sh_coeffs.shape[:2]
    rest_count = coefficient_count - 1
    names = _property_names(rest_count)
    vertices = np.zeros(count, dtype=np.dtype([(name, "<f4") for name in names]))
    # View the structured rows as one [N, P] float matrix to fill columns in blocks.
    table = vertices.view("<f4").reshape(count, len(names))
    table[:, 0:3] = means
    table[:, 6:9] = sh_coeffs[:, 0, :]
    column = 9
    # Channel-major rest coefficients: [N, K-1, 3] -> [N, 3, K-1] -> [N, 3(K-1)].
    table[:, column:column + 3 * rest_count] = sh_coeffs[:, 1:, :].transpose(0, 2, 1).reshape(count, 3 * rest_count)
    column += 3 * rest_count
    clamped = np.clip(opacities.astype(np.float64), _OPACITY_EPS, 1.0 - _OPACITY_EPS)
    table[:, column] = np.log(clamped / (1.0 - clamped))
    table[:, column + 1:column + 4] = np.log(scales.astype(np.float64))
    table[:, column + 4:column + 8] = quats

    header = "ply\nformat binary_little_endian 1.0\ncomment written by warpavatar\n"
    header += f"element vertex {count}\n"
    header += "".join(f"property float {name}\n" for name in names)
    header += "end_header\n"

    path = os.fspath(path)
    with atomic_open(path) as stream:
        stream.write(header.encode("ascii"))
        stream.write(vertices.tobytes())
    return path


def _parse_header(path: str, stream) -> tuple[str, list[tuple[str, int, list]]]:
    """Read a PLY header. Returns the format and the elements as (name, count, [(prop, type or None)])."""
    first = stream.readline()
    if first.rstrip(b"\r\n") != b"ply":
        raise ValueError(f"{path}: not a PLY file (first line is {first[:40]!r})")
    file_format = None
    elements: list[tuple[str, int, list]] = []
    read = len(first)
    while True:
        line = stream.readline()
        read += len(line)
        if not line or read > _HEADER_LIMIT_BYTES:
            raise ValueError(f"{path}: PLY header has no end_header line")
        words = line.decode("ascii", errors="replace").split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        if words[0] == "end_header":
            break
        if words[0] == "format" and len(words) >= 2:
            file_format = words[1]
        elif words[0] == "element" and len(words) == 3:
            try:
                element_count = int(words[2])
            except ValueError:
                raise ValueError(f"{path}: bad element line {line!r}") from None
            if element_count < 0:
                raise ValueError(f"{path}: negative element count in {line!r}")
            elements.append((words[1], element_count, []))
        elif words[0] == "property" and elements:
            if words[1] == "list":
                elements[-1][2].append((words[-1], None))
            elif len(words) == 3 and words[1] in _PLY_TYPES:
                elements[-1][2].append((words[2], _PLY_TYPES[words[1]]))
            else:
                raise ValueError(f"{path}: unsupported property line {line!r}")
        else:
            raise ValueError(f"{path}: unexpected PLY header line {line!r}")
    if file_format is None:
        raise ValueError(f"{path}: PLY header has no format line")
    return file_format, elements


def read_gaussian_ply(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """Read a 3DGS ``.ply`` file written by :func:`write_gaussian_ply` or by 3DGS-style trainers.

    Binary little- or big-endian files with float or double properties are read; elements before
    ``vertex`` are skipped when they have no list properties, elements after it are ignored.

    Args:
        path: the file.

    Returns:
        dict with float32 arrays ``means`` [N,3], ``quats`` [N,4] (w, x, y, z, as stored), ``scales``
        [N,3] (linear: exp of the stored logs), ``opacities`` [N] (linear: sigmoid of the stored logits)
        and ``sh_coeffs`` [N,(d+1)^2,3] (the degree follows from the number of ``f_rest`` properties).

    Raises:
        ValueError: not a PLY file, ASCII format, missing 3DGS properties, a truncated file, or
            non-finite values; the message names the file.
        OSError: the file cannot be opened.
    """
    path = os.fspath(path)
    with open(path, "rb") as stream:
        file_format, elements = _parse_header(path, stream)
        if file_format == "binary_little_endian":
            order = "<"
        elif file_format == "binary_big_endian":
            order = ">"
        else:
            raise ValueError(f"{path}: PLY format {file_format!r} is not supported (binary only)")
        vertices = None
        for name, element_count, properties in elements:
            if any(kind is None for _, kind in properties):
                if name == "vertex":
                    raise ValueError(f"{path}: list properties in the vertex element are not supported")
                raise ValueError(f"{path}: element {name!r} before 'vertex' has list properties; cannot skip it")
            dtype = np.dtype([(prop, order + kind) for prop, kind in properties])
            data = stream.read(dtype.itemsize * element_count)
            if len(data) != dtype.itemsize * element_count:
                raise ValueError(f"{path}: file is truncated (element {name!r} needs "
                                 f"{dtype.itemsize * element_count} bytes, found {len(data)})")
            if name == "vertex":
                vertices = np.frombuffer(data, dtype=dtype, count=element_count)
                break
    if vertices is None:
        raise ValueError(f"{path}: PLY file has no 'vertex' element")

    fields = set(vertices.dtype.names or ())
    required = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity",
                "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    missing = [name for name in required if name not in fields]
    if missing:
        raise ValueError(f"{path}: not a 3DGS PLY file, missing properties {missing}")
    rest_total = 0
    while f"f_rest_{rest_total}" in fields:
        rest_total += 1
    if rest_total % 3 or _sh_degree_from_count(rest_total // 3 + 1) is None:
        raise ValueError(f"{path}: {rest_total} f_rest properties do not match any SH degree "
                         f"(expected 3((d+1)^2 - 1): 0, 9, 24, 45, ...)")
    rest_count = rest_total // 3
    count = vertices.shape[0]

    def columns(names: list[str]) -> np.ndarray:
        out = np.empty((count, len(names)), dtype=np.float32)
        for i, name in enumerate(names):
            out[:, i] = vertices[name]
        return out

    means = columns(["x", "y", "z"])
    quats = columns([f"rot_{i}" for i in range(4)])
    log_scales = columns([f"scale_{i}" for i in range(3)]).astype(np.float64)
    logits = vertices["opacity"].astype(np.float64)
    sh_coeffs = np.empty((count, rest_count + 1, 3), dtype=np.float32)
    sh_coeffs[:, 0, :] = columns(["f_dc_0", "f_dc_1", "f_dc_2"])
    if rest_count:
        rest = columns([f"f_rest_{i}" for i in range(rest_total)]).reshape(count, 3, rest_count)
        sh_coeffs[:, 1:, :] = rest.transpose(0, 2, 1)
    for name, array in (("positions", means), ("rotations", quats), ("log scales", log_scales),
                        ("opacity logits", logits), ("SH coefficients", sh_coeffs)):
        if array.size and not np.isfinite(array).all():
            raise ValueError(f"{path}: {name} hold non-finite values")
    with np.errstate(over="ignore"):
        scales = np.exp(log_scales).astype(np.float32)
        # Numerically stable logistic function, in float64, rounded once to float32.
        opacities = np.where(logits >= 0, 1.0 / (1.0 + np.exp(-logits)),
                             np.exp(logits) / (1.0 + np.exp(logits))).astype(np.float32)
    return {"means": means, "quats": quats, "scales": scales, "opacities": opacities, "sh_coeffs": sh_coeffs}
