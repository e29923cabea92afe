"""3DGS .ply export: round trips, the raw stored fields, and clear errors."""

import os
import re

import numpy as np
import pytest
import torch

from warpavatar.io.ply import read_gaussian_ply, write_gaussian_ply


def random_gaussians(seed: int, count: int = 37, sh_degree: int = 3) -> dict:
    rng = np.random.default_rng(seed)
    return {
        "means": rng.normal(size=(count, 3)).astype(np.float32),
        "quats": rng.normal(size=(count, 4)).astype(np.float32),
        "scales": np.exp(rng.normal(-3.0, 1.0, size=(count, 3))).astype(np.float32),
        "opacities": rng.uniform(0.01, 0.99, size=count).astype(np.float32),
        "sh_coeffs": rng.normal(size=(count, (sh_degree + 1) ** 2, 3)).astype(np.float32),
    }


def read_raw(path) -> tuple[list[str], np.ndarray]:
    """The header lines and the vertex rows of a little-endian float32 PLY, parsed independently."""
    with open(path, "rb") as stream:
        data = stream.read()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    header = data[:end].decode("ascii").splitlines()
    names = [line.split()[2] for line in header if line.startswith("property")]
    rows = np.frombuffer(data[end:], dtype=np.dtype([(name, "<f4") for name in names]))
    return header, rows


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("sh_degree", [0, 1, 3])
def test_round_trip(tmp_path, seed, sh_degree):
    gaussians = random_gaussians(seed, sh_degree=sh_degree)
    path = tmp_path / "avatar.ply"
    assert write_gaussian_ply(path, **gaussians) == str(path)
    back = read_gaussian_ply(path)
    assert sorted(back) == sorted(gaussians)
    for name in ("means", "quats", "sh_coeffs"):
        assert back[name].dtype == np.float32
        np.testing.assert_array_equal(back[name], gaussians[name], err_msg=name)
    np.testing.assert_allclose(back["scales"], gaussians["scales"], rtol=1e-6)
    np.testing.assert_allclose(back["opacities"], gaussians["opacities"], rtol=1e-6)
    # Writing what was read gives the same bytes.
    write_gaussian_ply(tmp_path / "again.ply", **back)
    back_again = read_gaussian_ply(tmp_path / "again.ply")
    for name in back:
        np.testing.assert_allclose(back_again[name], back[name], rtol=1e-6)


def test_raw_fields_follow_3dgs_conventions(tmp_path):
    gaussians = random_gaussians(3, count=11, sh_degree=2)
    path = tmp_path / "raw.ply"
    write_gaussian_ply(path, **gaussians)
    header, rows = read_raw(path)
    assert header[:2] == ["ply", "format binary_little_endian 1.0"]
    assert "element vertex 11" in header
    names = list(rows.dtype.names)
    rest = 3 * (9 - 1)
    assert names == (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
                     + [f"f_rest_{i}" for i in range(rest)]
                     + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"])
    sh = gaussians["sh_coeffs"]
    for axis, name in enumerate("xyz"):
        np.testing.assert_array_equal(rows[name], gaussians["means"][:, axis])
        np.testing.assert_array_equal(rows["n" + name], 0.0)
    for channel in range(3):
        np.testing.assert_array_equal(rows[f"f_dc_{channel}"], sh[:, 0, channel])
        for coefficient in range(1, 9):
            # Channel-major: all red rest coefficients, then green, then blue.
            index = channel * 8 + (coefficient - 1)
            np.testing.assert_array_equal(rows[f"f_rest_{index}"], sh[:, coefficient, channel])
    for i in range(4):
        np.testing.assert_array_equal(rows[f"rot_{i}"], gaussians["quats"][:, i])  # w first
    opacity = gaussians["opacities"].astype(np.float64)
    np.testing.assert_array_equal(rows["opacity"], np.log(opacity / (1 - opacity)).astype(np.float32))
    for i in range(3):
        np.testing.assert_array_equal(rows[f"scale_{i}"],
                                      np.log(gaussians["scales"][:, i].astype(np.float64)).astype(np.float32))


def test_torch_inputs_and_empty(tmp_path):
    gaussians = {k: torch.from_numpy(v) for k, v in random_gaussians(4, count=5, sh_degree=1).items()}
    write_gaussian_ply(tmp_path / "t.ply", **gaussians)
    np.testing.assert_array_equal(read_gaussian_ply(tmp_path / "t.ply")["means"], gaussians["means"].numpy())
    empty = {k: v[:0] for k, v in random_gaussians(5, sh_degree=2).items()}
    write_gaussian_ply(tmp_path / "empty.ply", **empty)
    back = read_gaussian_ply(tmp_path / "empty.ply")
    assert back["means"].shape == (0, 3) and back["sh_coeffs"].shape == (0, 9, 3)


def test_saturated_opacities_are_clamped(tmp_path):
    gaussians = random_gaussians(6, count=4, sh_degree=0)
    gaussians["opacities"] = np.array([0.0, 1.0, 0.5, 1.0], dtype=np.float32)
    write_gaussian_ply(tmp_path / "s.ply", **gaussians)
    _, rows = read_raw(tmp_path / "s.ply")
    assert np.isfinite(rows["opacity"]).all()
    back = read_gaussian_ply(tmp_path / "s.ply")["opacities"]
    np.testing.assert_allclose(back, gaussians["opacities"], atol=1e-6)


def test_reads_other_layouts(tmp_path):
    """Big-endian doubles, other property order, an extra element before the vertices, no f_rest."""
    count = 3
    rng = np.random.default_rng(7)
    names = ["rot_0", "rot_1", "rot_2", "rot_3", "x", "y", "z", "opacity", "scale_0", "scale_1", "scale_2",
             "f_dc_0", "f_dc_1", "f_dc_2", "extra"]
    rows = np.zeros(count, dtype=[(name, ">f8") for name in names])
    for name in names:
        rows[name] = rng.normal(size=count)
    header = ("ply\nformat binary_big_endian 1.0\ncomment hand made\nelement camera 1\nproperty uchar id\n"
              f"element vertex {count}\n" + "".join(f"property double {n}\n" for n in names) + "end_header\n")
    path = tmp_path / "other.ply"
    path.write_bytes(header.encode() + b"\x07" + rows.tobytes())
    back = read_gaussian_ply(path)
    np.testing.assert_array_equal(back["means"][:, 1], rows["y"].astype(np.float32))
    np.testing.assert_array_equal(back["quats"][:, 0], rows["rot_0"].astype(np.float32))
    np.testing.assert_allclose(back["scales"][:, 2], np.exp(rows["scale_2"]), rtol=1e-6)
    np.testing.assert_allclose(back["opacities"], 1 / (1 + np.exp(-rows["opacity"])), rtol=1e-6)
    assert back["sh_coeffs"].shape == (count, 1, 3)


@pytest.mark.parametrize("change, message", [
    (lambda g: g.update(means=g["means"][:, :2]), "means must have shape"),
    (lambda g: g.update(quats=g["quats"][:-1]), "quats must have shape"),
    (lambda g: g.update(sh_coeffs=g["sh_coeffs"][:, :3]), re.escape("(d+1)^2")),
    (lambda g: g["means"].__setitem__((0, 0), np.nan), "non-finite"),
    (lambda g: g["scales"].__setitem__((1, 2), 0.0), "scales must be > 0"),
    (lambda g: g["opacities"].__setitem__(2, 1.5), r"opacities must be linear values in \[0, 1\]"),
    (lambda g: g.update(opacities=np.array(["a"] * len(g["opacities"]))), "real numbers"),
])
def test_write_errors_leave_existing_file(tmp_path, change, message):
    path = tmp_path / "keep.ply"
    path.write_bytes(b"old contents")
    gaussians = random_gaussians(8, count=6, sh_degree=1)
    change(gaussians)
    with pytest.raises((ValueError, TypeError), match=message):
        write_gaussian_ply(path, **gaussians)
    assert path.read_bytes() == b"old contents"
    assert os.listdir(tmp_path) == ["keep.ply"]


def test_interrupted_write_removes_temporary(tmp_path, monkeypatch):
    path = tmp_path / "keep.ply"
    path.write_bytes(b"old contents")

    def failing_replace(src, dst):
        raise OSError("disk full")

    monkeypatch.setattr(os, "replace", failing_replace)
    with pytest.raises(OSError, match="disk full"):
        write_gaussian_ply(path, **random_gaussians(9, count=4, sh_degree=0))
    assert path.read_bytes() == b"old contents"
    assert os.listdir(tmp_path) == ["keep.ply"]


def test_read_errors(tmp_path):
    good = tmp_path / "good.ply"
    write_gaussian_ply(good, **random_gaussians(10, count=8, sh_degree=1))
    data = good.read_bytes()
    cases = {
        "notply.ply": (b"hello\n", "not a PLY file"),
        "ascii.ply": (b"ply\nformat ascii 1.0\nelement vertex 0\nproperty float x\nend_header\n", "binary only"),
        "truncated.ply": (data[:-10], "truncated"),
        "noend.ply": (b"ply\nformat binary_little_endian 1.0\nelement vertex 1\n", "end_header"),
        "missing.ply": (b"ply\nformat binary_little_endian 1.0\nelement vertex 1\nproperty float x\nend_header\n"
                        + b"\0" * 4, "missing properties"),
        "rest.ply": (data.replace(b"property float f_rest_8\n", b"property float f_rest_x\n"), "f_rest"),
    }
    for name, (content, message) in cases.items():
        path = tmp_path / name
        path.write_bytes(content)
        with pytest.raises(ValueError, match=message) as info:
            read_gaussian_ply(path)
        assert name in str(info.value)
    nan = random_gaussians(11, count=2, sh_degree=0)
    write_gaussian_ply(tmp_path / "nan.ply", **nan)
    raw = bytearray((tmp_path / "nan.ply").read_bytes())
    raw[-4:] = np.array([np.nan], dtype="<f4").tobytes()  # last rot_3
    (tmp_path / "nan.ply").write_bytes(bytes(raw))
    with pytest.raises(ValueError, match="non-finite"):
        read_gaussian_ply(tmp_path / "nan.ply")
    with pytest.raises(OSError):
        read_gaussian_ply(tmp_path / "absent.ply")
