"""The layout's rules (docs/architecture.md), read from the code's own imports: no import cycle, model/ below
extensions/ below fit/, and the trainer reaching extensions only through the registry."""

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "warpavatar"


def _module_name(path: Path) -> str:
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _imports() -> dict[str, set[str]]:
    """Each module of the package -> the warpavatar modules it imports (at any depth of its code)."""
    modules = {_module_name(path): path for path in PACKAGE.rglob("*.py") if "data/demo" not in path.as_posix()}
    graph = {}
    for name, path in modules.items():
        targets = set()
        package = name if path.name == "__init__.py" else name.rpartition(".")[0]
        for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
            if isinstance(node, ast.Import):
                targets.update(alias.name for alias in node.names)
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    base = ".".join(package.split(".")[: len(package.split(".")) - node.level + 1] + [base])
                targets.add(base)
                targets.update(f"{base}.{alias.name}" for alias in node.names)
        graph[name] = {t for t in targets if t in modules and t != name}
    return graph


GRAPH = _imports()


def _cycle(graph) -> list[str] | None:
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(node):
        state[node] = 1
        stack.append(node)
        for target in sorted(graph[node]):
            # a package's face importing its own submodules is how a package exposes them, not a cycle
            if target.startswith(node + "."):
                continue
            if state.get(target) == 1:
                return stack[stack.index(target):] + [target]
            if target not in state and (found := visit(target)):
                return found
        stack.pop()
        state[node] = 2
        return None

    for node in sorted(graph):
        if node not in state and (found := visit(node)):
            return found
    return None


def test_the_graph_is_read():
    assert "warpavatar.model" in GRAPH["warpavatar.fit.trainer"]
    assert "warpavatar.extensions.base" in GRAPH["warpavatar.extensions.dynamics"]


def test_there_is_no_import_cycle():
    assert _cycle(GRAPH) is None, " -> ".join(_cycle(GRAPH))


@pytest.mark.parametrize("lower, higher", [
    ("warpavatar.model", "warpavatar.extensions"),
    ("warpavatar.model", "warpavatar.fit"),
    ("warpavatar.extensions", "warpavatar.fit"),
    ("warpavatar.data", "warpavatar.model"),
    ("warpavatar.geometry", "warpavatar.model"),
    ("warpavatar.fit", "warpavatar.cli"),
    ("warpavatar.fit", "warpavatar.batch"),
    ("warpavatar.evaluate", "warpavatar.batch"),
    ("warpavatar.batch", "warpavatar.cli"),
    ("warpavatar.model", "warpavatar.evaluate"),
])
def test_data_flows_one_way(lower, higher):
    offenders = sorted(f"{module} -> {target}" for module, targets in GRAPH.items() if module.startswith(lower)
                       for target in targets if target.startswith(higher))
    assert not offenders, offenders


def test_sim_builds_on_the_kernel_level_only():
    # warpavatar/sim/ is physics the avatar's parts use: it may import the ops, their kernels and bridges, the
    # shared geometry and itself (and the bare package, whose face imports nothing), never the model, the extensions, the fit or anything above them.
    # (and the atomic file writer, which imports nothing of the package, for writing meshes to inspect)
    allowed = ("warpavatar.ops", "warpavatar.geometry", "warpavatar.kernels", "warpavatar._src", "warpavatar.sim",
               "warpavatar.io.output_files")
    assert "warpavatar.sim.mass_spring_cloth" in GRAPH
    offenders = sorted(f"{module} -> {target}" for module, targets in GRAPH.items()
                       if module.startswith("warpavatar.sim")
                       for target in targets if target != "warpavatar" and not target.startswith(allowed))
    assert not offenders, offenders


def test_the_trainer_reaches_extensions_only_through_the_registry():
    offenders = sorted(f"{module} -> {target}" for module, targets in GRAPH.items()
                       if module.startswith("warpavatar.fit")
                       for target in targets if target.startswith("warpavatar.extensions.")
                       and target not in ("warpavatar.extensions.base", "warpavatar.extensions.registry"))
    assert not offenders, offenders


# a kernel family's three files share its name on purpose (docs/architecture.md): the kernels, their autograd
# bridge and their plain-torch reference
KERNEL_FAMILY_FOLDERS = (ROOT / "kernels", PACKAGE / "_src", PACKAGE / "_torch_impl")


def test_a_file_name_is_shared_only_by_a_kernel_family():
    places: dict[str, list[Path]] = {}
    for path in [*PACKAGE.rglob("*.py"), *(ROOT / "kernels").glob("*.py")]:
        if path.name not in ("__init__.py", "__main__.py") and "data/demo" not in path.as_posix():
            places.setdefault(path.name, []).append(path)
    shared = sorted(f"{name}: {', '.join(sorted(p.relative_to(ROOT).as_posix() for p in paths))}"
                    for name, paths in places.items()
                    if len(paths) > 1 and not all(p.parent in KERNEL_FAMILY_FOLDERS for p in paths))
    assert not shared, shared


@pytest.mark.parametrize("old, new", [("warpavatar.fit.skinning", "warpavatar.fit.skinning_field_stage"),
                                      ("warpavatar.fit.frames", "warpavatar.fit.training_frames"),
                                      ("warpavatar.sim.cloth", "warpavatar.sim.mass_spring_cloth"),
                                      ("warpavatar.sim.frames", "warpavatar.sim.node_frames")])
def test_renamed_modules_left_their_old_names(old, new):
    assert old not in GRAPH and new in GRAPH


def test_only_load_training_video_reads_a_folder_at_a_configs_image_scale():
    # the fit's image_scale is applied in one place (warpavatar.fit.training_frames.load_training_video): no other
    # code reads a video folder or subject with `scale=<something>.image_scale`
    offenders = []
    for folder in (PACKAGE, ROOT / "kernels", ROOT / "tools", ROOT / "research"):
        for path in folder.rglob("*.py"):
            for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
                if not isinstance(node, ast.Call):
                    continue
                name = node.func.attr if isinstance(node.func, ast.Attribute) else getattr(node.func, "id", "")
                if name in ("load_video_folder", "load_subject") and any(
                        keyword.arg == "scale" and isinstance(keyword.value, ast.Attribute)
                        and keyword.value.attr == "image_scale" for keyword in node.keywords):
                    offenders.append(f"{path.relative_to(ROOT).as_posix()}:{node.lineno}")
    assert [place.partition(":")[0] for place in offenders] == ["warpavatar/fit/training_frames.py"], offenders
