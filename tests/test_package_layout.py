"""Where the code lives: setup.cfg installs every package and runs every command from ``warpavatar/cli/``, the
CUDA-graph helpers are one package, and ``warpavatar.io``'s public names are imported from their modules on
first use (so ``import warpavatar.io`` does not load usd-core)."""

import configparser
import importlib
import importlib.util
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SETUP = configparser.ConfigParser(interpolation=None)
SETUP.read(ROOT / "setup.cfg")


def _lines(section: str, key: str) -> list[str]:
    return [line.strip() for line in SETUP[section][key].splitlines() if line.strip()]


def test_setup_cfg_lists_exactly_the_packages_on_disk():
    on_disk = {".".join(path.parent.relative_to(ROOT).parts) for path in (ROOT / "warpavatar").rglob("__init__.py")}
    on_disk.add("warpavatar.kernels")  # kernels/, installed under the package (package_dir)
    assert "warpavatar._src.graphs" in on_disk
    assert set(_lines("options", "packages")) == on_disk


def test_every_command_is_the_main_of_a_cli_module():
    commands = dict(line.split(" = ") for line in _lines("options.entry_points", "console_scripts"))
    assert commands["warpavatar-prepare"] == "warpavatar.cli.prepare:main"
    for command, target in commands.items():
        module, function = target.split(":")
        assert module == "warpavatar.cli." + command.removeprefix("warpavatar-").replace("-", "_"), command
        assert importlib.util.find_spec(module) is not None, target
    from warpavatar.cli import prepare

    assert prepare.__all__ == ["main"] and callable(prepare.main)
    assert importlib.util.find_spec("warpavatar.prepare.cli") is None  # moved, not copied


def test_python_m_warpavatar_prepare_runs_the_command():
    result = subprocess.run([sys.executable, "-m", "warpavatar.prepare", "--help"], capture_output=True, text=True,
                            cwd=ROOT, timeout=120)
    assert result.returncode == 0, result.stderr
    assert result.stdout.startswith("usage: warpavatar-prepare ")


@pytest.mark.parametrize("old", ["warpavatar._src.cuda_graph", "warpavatar._src.address_graphs",
                                 "warpavatar._src.splat_replay", "warpavatar._src.status_mailbox",
                                 "warpavatar.fit.step_graph"])
def test_the_graph_helpers_left_their_old_places(old):
    assert importlib.util.find_spec(old) is None


def test_the_graph_package_names_and_describes_each_module():
    graphs = importlib.import_module("warpavatar._src.graphs")
    modules = sorted(path.stem for path in Path(graphs.__file__).parent.glob("*.py") if path.stem != "__init__")
    assert sorted(graphs.__all__) == modules == ["address_graphs", "capture", "splat_replay", "status_mailbox",
                                                  "step_graph"]
    for name in modules:
        assert f":mod:`~warpavatar._src.graphs.{name}`" in graphs.__doc__, name
        assert importlib.import_module(f"warpavatar._src.graphs.{name}").__all__, name


def test_import_warpavatar_io_loads_no_writer():
    probe = ("import sys, warpavatar.io as io; "
             "print(sorted(m for m in sys.modules if m.startswith(('pxr', 'warpavatar.io.')))); "
             "io.GaussianUsdWriter; print('pxr' in sys.modules, 'warpavatar.io.usd' in sys.modules)")
    result = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert result.returncode == 0, result.stderr
    assert result.stdout.splitlines() == ["[]", "True True"]


def test_warpavatar_io_exports_its_modules_own_objects():
    import warpavatar.io as io

    assert set(io.__all__) <= set(dir(io))
    for name in io.__all__:
        value = getattr(io, name)
        module = sys.modules[value.__module__]
        assert module.__name__.startswith("warpavatar.io.") and name in module.__all__, name
        assert value is getattr(module, name), name
    with pytest.raises(AttributeError, match="module 'warpavatar.io' has no attribute 'gaussian_extent'"):
        io.gaussian_extent  # noqa: B018 (a module's other names stay in the module)


def test_export_doc_examples_import_public_names():
    import warpavatar.io as io

    text = (ROOT / "docs" / "export.md").read_text()
    imported = [name.strip() for names in re.findall(r"^from warpavatar\.io import (.+)$", text, flags=re.M)
                for name in names.split(",")]
    assert {"write_gaussian_ply", "GaussianUsdWriter", "load_motion"} <= set(imported)
    assert set(imported) <= set(io.__all__)
