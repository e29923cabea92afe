"""The exporter seam: formats chosen by the output's suffix (and --layout), their one-line errors, third-party
formats registered in code or through the ``warpavatar.exporters`` entry-point group and written by
warpavatar-animate with no change to it, and the built-in .ply and .usda formats."""

import importlib.metadata
import sys

import numpy as np
import pytest

pytest.importorskip("pxr")  # usd-core is a dependency; skip cleanly where it is absent (the GPU machine)

from conftest import small_avatar
from warpavatar import data
from warpavatar.cli import animate
from warpavatar.io import exporters
from warpavatar.io.exporters import Exporter, exporter_for, register_exporter, unregister_exporter

DANCE = data.demo_subject_path() / "novel_pose" / "dance_cam000"
KNOWN = ".usdc, .usd, .usda, .ply"


@pytest.fixture(scope="module")
def avatar_dir(tmp_path_factory):
    skeleton = data.load_video_folder(data.demo_subject_path() / "train", max_frames=2).skeleton
    avatar = small_avatar(skeleton, seed=5, per_bone=4, cells=8, distill_steps=5, random_frames=True)
    folder = tmp_path_factory.mktemp("exporters_avatar")
    avatar.save(folder / "avatar.pt")
    return folder


def _run(argv, capsys):
    """(exit status, stdout, stderr) of warpavatar-animate; argparse's own exits count as a status."""
    try:
        code = animate.main([str(argument) for argument in argv])
    except SystemExit as stop:
        code = stop.code
    out, err = capsys.readouterr()
    return code, out, err


class FrameTableExporter(Exporter):
    """A third-party animated format: one text line per frame, its time code and the posed Gaussians' mean."""

    name = "frame-table-for-a-test"
    suffixes = (".frames.txt",)
    description = "a text table of the posed Gaussians' centroid per frame"
    animated = True
    calls = []

    def export(self, avatar, path, *, motion, options):
        from warpavatar.io.output_files import atomic_open

        lines = [f"{code} " + " ".join(f"{value:.6f}" for value in posed["means"].mean(0).tolist())
                 for code, posed in zip(motion.time_codes(), motion.posed_frames(avatar))]
        with atomic_open(path, "w") as stream:
            stream.write("\n".join(lines) + "\n")
        type(self).calls.append((motion.frame_count, motion.fps, options.skeleton))
        return f"{motion.frame_count} rows"


@pytest.fixture
def frame_table():
    FrameTableExporter.calls = []
    register_exporter(FrameTableExporter)
    yield FrameTableExporter
    unregister_exporter(FrameTableExporter.name)


# ------------------------------------------------------------------------------------------------ the registry


def test_the_suffix_and_the_layout_choose_the_format():
    assert [exporter_for(name).name for name in ("a.usdc", "b/A.USD", "c.usda", "canonical.ply")] == [
        "usd-particlefield", "usd-particlefield", "usd-particlefield", "ply-rest-pose"]
    assert exporter_for("a.usdc", layout="points").name == "usd-points"
    assert exporter_for("a.usd", layout="particlefield").name == "usd-particlefield"
    assert exporter_for("a.usda", layout="points").animated and not exporter_for("a.ply").animated
    assert exporters.exporter_layouts() == ["particlefield", "points"]


def test_the_longest_registered_suffix_wins(frame_table):
    assert exporter_for("take.frames.txt").name == frame_table.name
    with pytest.raises(ValueError) as error:
        exporter_for("take.txt", flag="-o")
    assert str(error.value) == f"-o take.txt: no export format writes '.txt' files; give a name ending in one of " \
                               f"{KNOWN}, .frames.txt"


def test_unknown_suffixes_and_layouts_are_one_line_errors():
    cases = [
        (("dance.abc",), {}, f"dance.abc: no export format writes '.abc' files; give a name ending in one of {KNOWN}"),
        (("dance",), {"flag": "-o"},
         f"-o dance: no export format writes files without a suffix; give a name ending in one of {KNOWN}"),
        (("dance.usdc",), {"layout": "mesh"}, "--layout mesh: .usdc files have no such layout; give one of "
                                              "particlefield, points"),
        (("rest.ply",), {"layout": "points"}, "--layout points: .ply files have no layouts; --layout is for .usdc, "
                                              ".usd, .usda"),
    ]
    for arguments, options, message in cases:
        with pytest.raises(ValueError) as error:
            exporter_for(*arguments, **options)
        assert str(error.value) == message


def test_a_format_must_be_new_and_well_formed(frame_table):
    class Clash(FrameTableExporter):
        name = "another-frame-table"

    class Unnamed(FrameTableExporter):
        name = ""

    class UpperCase(FrameTableExporter):
        name = "upper"
        suffixes = (".TXT",)

    for cls, message in [(frame_table, "an exporter called 'frame-table-for-a-test' is registered already"),
                         (Clash, "exporter 'another-frame-table': .frames.txt files are written by "
                                 "'frame-table-for-a-test' already"),
                         (Unnamed, "exporter Unnamed needs a name"),
                         (UpperCase, "exporter 'upper': suffixes must be a tuple of lower-case endings")]:
        with pytest.raises(ValueError) as error:
            register_exporter(cls)
        assert str(error.value).startswith(message)
    assert [e.name for e in exporters.registered_exporters()] == [
        "usd-particlefield", "usd-points", "ply-rest-pose", "frame-table-for-a-test"]


# ------------------------------------------------------------------------------------------------ warpavatar-animate


def test_animate_refuses_an_unknown_suffix_before_any_work(tmp_path, capsys):
    # the avatar does not exist: the suffix is checked first, and nothing is written or locked
    code, out, err = _run([tmp_path / "no_fit", "-o", tmp_path / "dance.abc"], capsys)
    assert (code, out) == (2, "")
    assert err == (f"error: -o {tmp_path / 'dance.abc'}: no export format writes '.abc' files; give a name ending "
                   f"in one of {KNOWN}\n")
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("options, message", [
    (["--motion", DANCE, "--frames", "0:2"], "so --motion, --frames would not be used; leave them out"),
    (["--skeleton"], "so --skeleton would not be used; leave it out"),
])
def test_animate_refuses_motion_options_for_a_rest_pose_format(tmp_path, capsys, options, message):
    output = tmp_path / "rest.ply"
    code, out, err = _run([tmp_path / "no_fit", "-o", output, *options], capsys)
    assert (code, out) == (2, "")
    assert err == (f"error: -o {output}: the ply-rest-pose format writes the rest pose only, {message}, or give -o "
                   "the suffix of another format (--help lists them)\n")


def test_animate_refuses_a_layout_of_another_suffix(tmp_path, capsys):
    code, _, err = _run([tmp_path / "no_fit", "-o", tmp_path / "rest.ply", "--layout", "points"], capsys)
    assert code == 2
    assert err == "error: --layout points: .ply files have no layouts; --layout is for .usdc, .usd, .usda\n"


def test_animate_help_lists_the_registered_formats(frame_table, capsys):
    with pytest.raises(SystemExit):
        animate.main(["--help"])
    text = capsys.readouterr().out
    listing = text[text.index("Formats, chosen by the suffix of -o"):text.index("positional arguments")]
    assert listing.splitlines()[1:] == [
        "  .usdc .usd .usda --layout particlefield (default): an animation",
        "      OpenUSD UsdVol.ParticleField3DGaussianSplat prim (Omniverse, recent USD tools)",
        "  .usdc .usd .usda --layout points: an animation",
        "      OpenUSD UsdGeom.Points prim with the Gaussians as primvars (Blender, older USD tools)",
        "  .ply: the rest pose only",
        "      3DGS .ply of the canonical Gaussians, as the fit's canonical.ply (splat viewers open it)",
        "  .frames.txt: an animation",
        "      a text table of the posed Gaussians' centroid per frame",
        ""]


def test_animate_writes_a_format_registered_in_code(avatar_dir, tmp_path, capsys, frame_table):
    import torch

    from warpavatar.model import Avatar

    output = tmp_path / "take.frames.txt"
    code, out, err = _run([avatar_dir, "--motion", DANCE, "--frames", "2:5", "--fps", "12", "-o", output,
                           "--no-progress", "--device", "cpu"], capsys)
    assert code == 0, err
    assert out.startswith(f"wrote {output} (3 rows, 0.0 MiB) in ")
    assert frame_table.calls == [(3, 12.0, False)]
    avatar = Avatar.load(avatar_dir)
    bones = data.load_video_folder(DANCE).bone_transforms[2:5]
    rows = [line.split() for line in output.read_text().splitlines()]
    assert [row[0] for row in rows] == ["0", "3", "6"]  # the folder keeps every 3rd frame id
    with torch.no_grad():
        expected = [avatar.pose(torch.as_tensor(b, dtype=torch.float32))["means"].mean(0).numpy() for b in bones]
    np.testing.assert_allclose(np.array([row[1:] for row in rows], dtype=np.float64), expected, atol=1e-5)
    assert sorted(path.name for path in tmp_path.iterdir()) == ["take.frames.txt"]


def test_animate_writes_a_format_declared_by_an_entry_point(avatar_dir, tmp_path, capsys, monkeypatch):
    module = tmp_path / "plugin" / "third_party_exporter_for_a_test.py"
    module.parent.mkdir()
    module.write_text(
        "from warpavatar.io.exporters import Exporter\n"
        "from warpavatar.io.output_files import write_text_atomic\n\n\n"
        "class CountExporter(Exporter):\n"
        "    name = 'gaussian-count-for-a-test'\n"
        "    suffixes = ('.count',)\n"
        "    description = 'the number of Gaussians, as text'\n"
        "    animated = False\n\n"
        "    def export(self, avatar, path, *, motion, options):\n"
        "        write_text_atomic(path, f'{avatar.gaussians.count} {motion}\\n')\n"
        "        return 'a count'\n")
    monkeypatch.syspath_prepend(str(module.parent))
    group = exporters.ENTRY_POINT_GROUP
    declared = [importlib.metadata.EntryPoint(name="count", value="third_party_exporter_for_a_test:CountExporter",
                                              group=group),
                importlib.metadata.EntryPoint(name="broken", value="no_such_module_for_a_test:Exporter", group=group)]
    monkeypatch.setattr(importlib.metadata, "entry_points",
                        lambda group=None: declared if group == exporters.ENTRY_POINT_GROUP else [])
    try:
        output = tmp_path / "avatar.count"
        code, out, err = _run([avatar_dir, "-o", output, "--no-progress", "--device", "cpu"], capsys)
        assert code == 0, err
        assert err == ("warning: warpavatar exporter entry point 'broken' (no_such_module_for_a_test:Exporter) was "
                       "not loaded: No module named 'no_such_module_for_a_test'\n")
        assert out.startswith(f"wrote {output} (a count, 0.0 MiB) in ")
        from warpavatar.model import Avatar

        assert output.read_text() == f"{Avatar.load(avatar_dir).gaussians.count} None\n"  # no motion read
        with pytest.warns(UserWarning, match="entry point 'broken'"):  # registered once, however often it is read
            assert exporters.load_entry_points() == []
    finally:
        unregister_exporter("gaussian-count-for-a-test")
        sys.modules.pop("third_party_exporter_for_a_test", None)


def test_the_ply_format_writes_the_canonical_ply_of_a_fit(tmp_path, capsys):
    from warpavatar.cli import fit
    from warpavatar.fit.outputs import canonical_floaters
    from warpavatar.io.ply import read_gaussian_ply
    from warpavatar.model import Avatar

    folder = tmp_path / "fit"
    assert fit.main([str(data.demo_subject_path() / "train"), "-o", str(folder), "--device", "cpu", "--iterations",
                     "3", "--field-warmup-steps", "2", "--init-carve-candidates", "2000", "--preview-frames", "1",
                     "--no-progress"]) == 0
    capsys.readouterr()
    avatar = Avatar.load(folder)
    # both leave out the same floaters (far from every bone, or nearly transparent); the avatar keeps them all
    kept = avatar.gaussians.count - int(canonical_floaters(avatar.gaussians.means, avatar.gaussians.opacities,
                                                           avatar.skeleton, scales=avatar.gaussians.scales).sum())
    output = tmp_path / "out" / "rest.PLY"
    code, out, err = _run([folder, "-o", output, "--no-progress", "--device", "cpu"], capsys)
    assert code == 0, err
    left_out = avatar.gaussians.count - kept
    assert 0 < kept <= avatar.gaussians.count and left_out < avatar.gaussians.count // 10
    floaters = f", {left_out} floaters left out (--keep-floaters keeps them)" if left_out else ""
    assert out.startswith(f"wrote {output} (3DGS .ply of the rest pose, {kept} Gaussians{floaters}, ")
    assert output.read_bytes() == (folder / "canonical.ply").read_bytes()
    assert read_gaussian_ply(output)["means"].shape == (kept, 3)
    assert sorted(path.name for path in output.parent.iterdir()) == ["rest.PLY"]


def test_usda_is_the_text_of_the_same_stage(avatar_dir, tmp_path, capsys):
    from warpavatar.io.usd import read_gaussian_usd

    arguments = [avatar_dir, "--motion", DANCE, "--frames", "0:3", "--layout", "points", "--skeleton", "--no-progress",
                 "--device", "cpu"]
    for name in ("anim.usdc", "anim.usda"):
        code, out, err = _run([*arguments, "-o", tmp_path / name], capsys)
        assert code == 0, err
        assert out.startswith(f"wrote {tmp_path / name} (points, 3 frames at 30 fps, ")
    assert (tmp_path / "anim.usda").read_bytes().startswith(b"#usda 1.0")
    crate, text = read_gaussian_usd(tmp_path / "anim.usdc"), read_gaussian_usd(tmp_path / "anim.usda")
    assert text["layout"] == "points" and list(text["time_codes"]) == list(crate["time_codes"])
    for key in ("positions", "orientations", "scales", "sh_coeffs", "joint_transforms"):
        np.testing.assert_allclose(text[key], crate[key], rtol=1e-6, atol=1e-6, err_msg=key)
    assert sorted(path.name for path in tmp_path.iterdir()) == ["anim.usda", "anim.usdc"]  # no scratch folder left
