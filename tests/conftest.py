"""Shared pytest set-up: every kernel test runs once per available device (CPU always, CUDA when present)."""

import importlib.util
import os
import shutil
from pathlib import Path

import pytest
import torch

from warpavatar import data
from warpavatar._src.warp_utils import available_devices

DEVICES = available_devices()


def pytest_generate_tests(metafunc):
    # A test that takes a ``device`` argument is registered once per device: test_x[cpu], test_x[cuda:0].
    if "device" in metafunc.fixturenames:
        metafunc.parametrize("device", DEVICES)


@pytest.fixture(autouse=True)
def _deterministic_seed():
    torch.manual_seed(0)
    yield


TORCH_DEFAULT_THREADS = torch.get_num_threads()
"""Torch's own thread count in this process (one per core), before the tests' one-thread rule."""


@pytest.fixture(scope="session", autouse=True)
def _one_torch_thread():
    """Torch on one thread for the whole session (module fixtures included), as ``warpavatar-fit`` runs on a CPU
    (``warpavatar.cli.common.cpu_torch_settings``), unless ``OMP_NUM_THREADS`` says otherwise. With ``-n auto``
    every core runs a worker, and torch's default thread pool, waiting for a core the other worker holds, made the
    in-process fits many times slower (tests/test_fit.py: 1229 s beside one busy core; 58 s on one thread, with
    its smaller fits)."""
    if "OMP_NUM_THREADS" in os.environ:
        yield
        return
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(TORCH_DEFAULT_THREADS)


@pytest.fixture(autouse=True)
def _default_torch_threads_where_they_are_tested(request):
    """Torch's default thread count for the tests marked ``torch_threads`` (one thread elsewhere)."""
    if request.node.get_closest_marker("torch_threads") is None or "OMP_NUM_THREADS" in os.environ:
        yield
        return
    torch.set_num_threads(TORCH_DEFAULT_THREADS)
    try:
        yield
    finally:
        torch.set_num_threads(1)


def small_avatar(skeleton, *, seed: int, per_bone: int, cells: int, distill_steps: int, random_frames: bool = False):
    """An avatar with Gaussians scattered around a skeleton's bone midpoints and a briefly distilled field.

    ``random_frames`` also randomizes the Gaussians' higher SH coefficients and orientations.
    """
    from warpavatar.model import Avatar
    from warpavatar.model import GaussianModel
    from warpavatar.model.skinning_field import VoxelSkinningField, bone_distance_prior

    generator = torch.Generator().manual_seed(seed)
    heads = torch.as_tensor(skeleton.heads)
    tails = torch.as_tensor(skeleton.tails)
    mid = (heads + tails) * 0.5
    means = (mid[:, None] + 0.03 * torch.randn(len(mid), per_bone, 3, generator=generator)).reshape(-1, 3)
    colours = torch.rand(means.shape[0], 3, generator=generator)
    scales = 0.01 + 0.02 * torch.rand(means.shape[0], 3, generator=generator)
    gaussians = GaussianModel(means, colours, scales, sh_degree=1, opacity=0.7)
    if random_frames:
        with torch.no_grad():
            gaussians.sh_rest.normal_(0.0, 0.1, generator=generator)
            gaussians.quats.normal_(generator=generator)
    lo = torch.minimum(heads.min(0).values, tails.min(0).values) - 0.2
    hi = torch.maximum(heads.max(0).values, tails.max(0).values) + 0.2
    field = VoxelSkinningField(lo, hi, skeleton.joint_count, cells=cells, min_cells=4, hidden=16, layers=1)
    prior = bone_distance_prior(field.grid_points.reshape(-1, 3), heads, tails, temperature=0.05)
    optimizer = torch.optim.Adam(field.parameters(), lr=1e-2)
    for _ in range(distill_steps):
        optimizer.zero_grad()
        field.distillation_loss(prior).backward()
        optimizer.step()
    return Avatar(skeleton, gaussians, field)


def load_tool(name: str):
    """The script ``tools/<name>.py`` as a fresh module (the tools are scripts, not part of the package; the
    siblings they import resolve through ``tools/`` on pytest's ``pythonpath``). ``research/`` is a package:
    tests import it as ``research.<name>``."""
    path = Path(__file__).resolve().parents[1] / "tools" / f"{name}.py"
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def assert_matches_central_differences(objective, inputs: dict, grads: dict, *, epsilon: float, rtol: float,
                                       relative_atol: float, min_scale: float):
    """Check analytic gradients against central differences of ``objective(inputs)`` (a float64 function).

    For every name in ``grads``, each element of ``inputs[name]`` is moved by +-``epsilon``; the difference
    quotient is compared with ``grads[name]`` (moved to float64 on the CPU) with tolerances ``rtol`` and
    ``relative_atol`` times the largest quotient, which must exceed ``min_scale`` (the input matters).
    """
    for name, grad in grads.items():
        numeric = torch.zeros_like(inputs[name])
        for element in range(numeric.numel()):
            plus, minus = {**inputs, name: inputs[name].clone()}, {**inputs, name: inputs[name].clone()}
            plus[name].view(-1)[element] += epsilon
            minus[name].view(-1)[element] -= epsilon
            numeric.view(-1)[element] = (objective(plus) - objective(minus)) / (2 * epsilon)
        scale = numeric.abs().max().item()
        assert scale > min_scale, name
        torch.testing.assert_close(grad.double().cpu(), numeric, rtol=rtol, atol=relative_atol * scale,
                                   msg=lambda message, n=name: f"d/d{n}: {message}")


# A fit small enough for a test: about 40 ms a step on a CPU core (tests run it through the CLI).
TINY_FIT = ["--preset", "quick", "--image-scale", "0.25", "--max-train-frames", "4", "--init-points-per-bone", "10",
            "--init-carve-candidates", "2000", "--init-carve-points", "200", "--grid-cells", "8", "--grid-min-cells",
            "4", "--field-hidden", "16", "--field-layers", "1", "--field-warmup-steps", "5", "--gaussian-only-steps",
            "20", "--densify-from", "10", "--densify-until", "40", "--densify-every", "10", "--max-gaussians", "2000",
            "--log-every", "1", "--preview-frames", "1", "--no-progress", "--device", "cpu"]


@pytest.fixture(scope="module")
def avatar_dir(tmp_path_factory):
    """A test module's small avatar on the demo skeleton (Gaussians around its bones, a briefly distilled field)."""
    skeleton = data.load_video_folder(data.demo_subject_path() / "train", max_frames=1).skeleton
    folder = tmp_path_factory.mktemp("avatar")
    small_avatar(skeleton, seed=5, per_bone=6, cells=8, distill_steps=10).save(folder / "avatar.pt")
    return folder


CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
CHROMEDRIVER = shutil.which("chromedriver")


def require_browser():
    """Skip where Chromium or chromedriver is missing, except under CI (the variable CI set), where it fails."""
    missing = [name for name, found in (("chromium", CHROMIUM), ("chromedriver", CHROMEDRIVER)) if found is None]
    if missing:
        message = f"no {' and no '.join(missing)} executable (Debian: apt-get install chromium chromium-driver)"
        if os.environ.get("CI"):
            pytest.fail(f"{message}; CI is set, so the browser test must run")
        pytest.skip(message)


# ------------------------------------------------------------------------- the mesh export's test avatar
def body_mesh(skeleton):
    """An ellipsoid around ``skeleton``'s bones (an icosphere, 642 vertices) with spherical UVs, a random 32x32
    texture and random vertex colours: an :class:`~warpavatar.mesh.AvatarMesh` without skin weights [m]."""
    import numpy as np
    import trimesh

    from warpavatar.mesh import AvatarMesh

    sphere = trimesh.creation.icosphere(subdivisions=3)
    points = np.concatenate([skeleton.heads, skeleton.tails])
    centre, half = (points.max(0) + points.min(0)) / 2, (points.max(0) - points.min(0)) / 2 + 0.05
    unit = np.asarray(sphere.vertices)
    normals = unit / half
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    uvs = np.stack([0.5 + np.arctan2(unit[:, 1], unit[:, 0]) / (2 * np.pi), np.arccos(unit[:, 2]) / np.pi], 1)
    rng = np.random.default_rng(3)
    return AvatarMesh(vertices=(centre + unit * half).astype(np.float32),
                      faces=np.asarray(sphere.faces, dtype=np.int32), normals=normals.astype(np.float32),
                      uvs=uvs.astype(np.float32), texture=rng.integers(0, 256, (32, 32, 3), dtype=np.uint8),
                      vertex_colors=rng.integers(0, 256, (len(unit), 3), dtype=np.uint8))


def sway_part(displacements: torch.Tensor):
    """An avatar part that moves every posed Gaussian by ``displacements[frame]`` [T,3] [m]: motion that skinning
    cannot make (a stand-in for cloth)."""
    from warpavatar.model.parts import AvatarPart

    class Sway(AvatarPart):
        name = "sway"

        def __init__(self):
            super().__init__()
            self.displacements = displacements

        def deform_posed(self, posed, frame):
            posed = type(posed)(posed)
            posed["means"] = posed["means"] + self.displacements[frame.frame_index]
            return posed

    return Sway()


@pytest.fixture(scope="module")
def export_avatar(avatar_dir):
    """The test module's small avatar (``avatar_dir``), loaded once: do not add parts to it."""
    from warpavatar.model import Avatar

    return Avatar.load(avatar_dir / "avatar.pt")


@pytest.fixture(scope="module")
def export_motion(export_avatar):
    """The first 5 frames of the demo's dance as an ExportMotion; its frame ids step by 3, so that times and time
    codes differ from row numbers."""
    from warpavatar.io.exporters import ExportMotion
    from warpavatar.io.motion import load_motion

    loaded = load_motion(data.demo_subject_path() / "novel_pose" / "dance_cam000", export_avatar.skeleton,
                         frames=slice(0, 5))
    return ExportMotion(loaded.bone_transforms, loaded.frame_ids, loaded.fps, loaded.fps)


@pytest.fixture(scope="module")
def skinned_body(export_avatar):
    """:func:`body_mesh` around the avatar's skeleton with the avatar's skin weights."""
    from warpavatar.mesh.skin import skin_mesh

    return skin_mesh(export_avatar, body_mesh(export_avatar.skeleton))


@pytest.fixture(scope="module")
def swaying_body(avatar_dir, skinned_body, export_motion):
    """(:func:`body_mesh` skinned, its animation by ``export_motion`` with vertex offsets) of a fresh copy of the
    avatar with a :func:`sway_part`: motion that the file's skinning alone cannot reproduce."""
    from warpavatar.mesh.skin import mesh_animation
    from warpavatar.model import Avatar

    avatar = Avatar.load(avatar_dir / "avatar.pt")
    displacements = 0.02 * torch.randn(export_motion.frame_count, 3, generator=torch.Generator().manual_seed(2))
    avatar.add_part(sway_part(displacements))
    animation = mesh_animation(avatar, skinned_body, export_motion)
    assert animation.vertex_offsets is not None
    return skinned_body, animation
