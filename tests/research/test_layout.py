"""research/ stays apart from the product: nothing under warpavatar/ imports it (nor tools/), no script of
research/ or tools/ reaches its siblings by editing ``sys.path``, and research/README.md says what each script
answers."""

import ast
from pathlib import Path

import pytest

pytestmark = pytest.mark.research

ROOT = Path(__file__).resolve().parents[2]


def _imported_modules(path: Path) -> set[str]:
    names = set()
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and not node.level:
            names.add(node.module or "")
    return names


def test_the_product_never_imports_research_or_tools():
    outside = ("research", "tools")
    offenders = sorted(str(path.relative_to(ROOT)) for path in (ROOT / "warpavatar").rglob("*.py")
                       if any(name.split(".")[0] in outside for name in _imported_modules(path)))
    assert offenders == []


def test_no_script_inserts_into_sys_path():
    scripts = sorted([*(ROOT / "research").glob("*.py"), *(ROOT / "tools").glob("*.py")])
    assert len(scripts) > 10
    offenders = [str(path.relative_to(ROOT)) for path in scripts if "sys.path.insert" in path.read_text()]
    assert offenders == []


def test_the_readme_names_every_research_script_and_nothing_else():
    scripts = {path.name for path in (ROOT / "research").glob("*.py")} - {"__init__.py", "common.py"}
    rows = [line for line in (ROOT / "research" / "README.md").read_text().splitlines() if line.startswith("| `")]
    named = {line.split("`")[1] for line in rows}
    assert named == scripts and len(rows) == len(scripts)
    assert all("?" in line.split("|")[2] for line in rows)  # each row asks its script's question


def test_every_research_test_module_is_marked():
    modules = sorted((ROOT / "tests" / "research").glob("test_*.py"))
    unmarked = [path.name for path in modules if "pytestmark = pytest.mark.research" not in path.read_text()]
    assert modules and unmarked == []
