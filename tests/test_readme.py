"""README.md's commands: what it tells a user to type exists, and the lines that take seconds run.

README.md is what a newcomer copies from, so its ```bash blocks are checked against the code on every run (these
tests are marked ``readme``: ``pytest -m readme`` runs them alone):

- every ``warpavatar-*`` command in them is a console script of ``setup.cfg``;
- every option they give such a command (``--flag`` or ``-o``) appears in that command's ``--help`` (and in its
  ``--help-all``, where ``--help`` offers one);
- every file a relative link of README.md points to exists, and so does every path into the repository's own
  folders that a block or a code span names;
- the lines that need neither the network nor long work (``--help`` calls) run and exit with status 0.

A block is parsed into :class:`Command` s, one per simple command: continued lines joined, comments dropped, split at
``&&``, ``||``, ``;`` and ``|``. :func:`run_command` runs one as a reader of the README would, from the repository
root (a ``warpavatar-*`` command through its entry point with this interpreter), and :func:`run_block` a whole
block. The demo's test runs the demo's fit, then the block README gives next: the viewer (until it serves its
page), the turntable and the export, in a fresh folder on the shipped data.
"""

from __future__ import annotations

import configparser
import functools
import re
import shlex
import subprocess
import sys
import threading
from dataclasses import dataclass
from pathlib import Path

import pytest

pytestmark = pytest.mark.readme

REPOSITORY = Path(__file__).resolve().parent.parent
README = REPOSITORY / "README.md"
SOURCE_FOLDERS = ("warpavatar", "kernels", "tools", "research", "tests", "docs", ".ci")
"""Top-level folders of the repository: a path whose first component is one of them must exist."""
SEPARATORS = ("&&", "||", ";", "|")
HELP_FLAGS = ("--help", "-h", "--help-all")
HELP_SECONDS = 300  # a command's --help imports torch and warp: seconds on an idle machine, a minute on a busy one


@dataclass(frozen=True)
class Command:
    """One simple command of a README block.

    Attributes:
        argv: the words, as the shell splits them (quotes removed).
        line: the source line it came from (continuations joined, the comment dropped).
        block: index of its ```bash block in README.md, from 0.
    """

    argv: tuple[str, ...]
    line: str
    block: int

    @property
    def is_warpavatar(self) -> bool:
        """Whether it runs one of warpavatar's console scripts."""
        return self.argv[0].startswith("warpavatar-")

    @property
    def is_quick(self) -> bool:
        """Whether it asks for help only: no network, no long work."""
        return any(word in HELP_FLAGS for word in self.argv[1:])


def bash_blocks(markdown: str) -> list[str]:
    """The contents of every ```bash fenced block of a markdown text, in order."""
    return re.findall(r"^```bash[ \t]*\n(.*?)^```[ \t]*$", markdown, flags=re.MULTILINE | re.DOTALL)


def parse_block(text: str, *, block: int = 0) -> list[Command]:
    """The simple commands of one shell block (continued lines joined, comments dropped, split at separators)."""
    commands = []
    for line in text.replace("\\\n", " ").splitlines():
        lexer = shlex.shlex(line, posix=True, punctuation_chars=";&|")
        lexer.whitespace_split = True
        lexer.commenters = "#"
        words: list[str] = []
        for word in [*lexer, ";"]:
            if word in SEPARATORS:
                if words:
                    commands.append(Command(tuple(words), line.split(" #")[0].strip(), block))
                words = []
            else:
                words.append(word)
    return commands


def readme_commands() -> list[Command]:
    """Every simple command of README.md's ```bash blocks."""
    return [command for index, text in enumerate(bash_blocks(README.read_text(encoding="utf-8")))
            for command in parse_block(text, block=index)]


@functools.lru_cache(maxsize=None)
def console_scripts() -> dict[str, str]:
    """setup.cfg's console scripts: name -> ``module:function``."""
    parser = configparser.ConfigParser()
    parser.read(REPOSITORY / "setup.cfg", encoding="utf-8")
    entries = parser["options.entry_points"]["console_scripts"]
    return dict((part.strip() for part in entry.split("=", 1)) for entry in entries.strip().splitlines())


def entry_point_argv(script: str, arguments: tuple[str, ...] | list[str]) -> list[str]:
    """The argv that runs console script ``script`` with ``arguments`` through this interpreter, installed or not."""
    module, function = console_scripts()[script].split(":")
    code = f"import sys; from {module} import {function} as main; sys.argv = sys.argv[1:]; sys.exit(main())"
    return [sys.executable, "-c", code, script, *arguments]


def run_command(command: Command, *, cwd: Path = REPOSITORY,
                timeout: float = HELP_SECONDS) -> subprocess.CompletedProcess:
    """Run one README command as its reader would, from ``cwd`` (the repository root by default).

    ``warpavatar-*`` commands run through their entry points, ``python``/``python3`` is this interpreter, anything
    else as written. Output is captured (text).
    """
    argv = list(command.argv)
    if command.is_warpavatar:
        argv = entry_point_argv(argv[0], argv[1:])
    elif argv[0] in ("python", "python3"):
        argv[0] = sys.executable
    return subprocess.run(argv, cwd=cwd, capture_output=True, text=True, timeout=timeout)


def run_block(commands: list[Command], *, cwd: Path, skip=lambda command: command.argv[0] == "pip",
              timeout: float = 3600) -> list[subprocess.CompletedProcess]:
    """Run a block's commands in order from ``cwd``, skipping those ``skip`` names (installs by default); stops at
    the first that fails, which is the last result returned."""
    results = []
    for command in commands:
        if skip(command):
            continue
        results.append(run_command(command, cwd=cwd, timeout=timeout))
        if results[-1].returncode != 0:
            break
    return results


@functools.lru_cache(maxsize=None)
def help_text(script: str) -> str:
    """What ``script --help`` prints, and ``--help-all`` too where ``--help`` offers it."""
    texts = []
    for flag in ("--help", "--help-all"):
        if flag == "--help-all" and "--help-all" not in texts[0]:
            break
        result = subprocess.run(entry_point_argv(script, [flag]), cwd=REPOSITORY, capture_output=True, text=True,
                                timeout=HELP_SECONDS)
        assert result.returncode == 0, f"{script} {flag} failed ({result.returncode}):\n{result.stderr[-2000:]}"
        texts.append(result.stdout)
    return "\n".join(texts)


def option_words(command: Command) -> list[str]:
    """The options a command gives: words that start with ``-`` (``--flag=value`` as ``--flag``), numbers aside."""
    words = [word.split("=", 1)[0] for word in command.argv[1:] if word.startswith("-")]
    return [word for word in words if not re.fullmatch(r"-[0-9.]+", word)]


def missing_options(command: Command, help_output: str) -> list[str]:
    """The options of ``command`` that ``help_output`` does not list, as whole words."""
    return [word for word in option_words(command)
            if not re.search(rf"(?<![\w-]){re.escape(word)}(?![\w-])", help_output)]


def repository_paths(markdown: str) -> list[str]:
    """Paths into the repository that a markdown text names, relative to its folder: every relative link target,
    and the words of its bash blocks and its code spans whose first component is one of :data:`SOURCE_FOLDERS`
    (other words with a slash are the reader's own files and outputs)."""
    links = [link for link in re.findall(r"\]\(([^)\s#]+)(?:#[^)]*)?\)", markdown)
             if "://" not in link and not link.startswith("mailto:")]
    words = [word for text in bash_blocks(markdown) for command in parse_block(text) for word in command.argv]
    words += re.findall(r"`([^`\s]+)`", markdown)
    words = [word.removeprefix("./").rstrip(".,:;") for word in words]
    words = [word for word in words if "://" not in word and word.split("/", 1)[0] in SOURCE_FOLDERS and "/" in word]
    paths = []
    for path in [*links, *words]:
        if path not in paths:
            paths.append(path)
    return paths


WARPAVATAR_COMMANDS = [command for command in readme_commands() if command.is_warpavatar]


def test_the_setup_commands_come_first():
    first = parse_block(bash_blocks(README.read_text(encoding="utf-8"))[0])
    assert [command.argv for command in first] == [
        ("pip", "install", "torch==2.13.0", "-e", "."), ("warpavatar-fit", "--demo"),
        ("pip", "install", "torch==2.13.0", "-e", ".[test]"),
        ("python3", "-m", "pytest", "-q", "-n", "auto", "--dist", "loadfile", "tests")]


def test_ci_runs_the_readme_test_command():
    """``.ci/run`` ends with README's test command, word for word (its parallel workers included)."""
    readme_test = parse_block(bash_blocks(README.read_text(encoding="utf-8"))[0])[-1]
    ci_commands = parse_block((REPOSITORY / ".ci" / "run").read_text(encoding="utf-8"))
    assert ci_commands[-1].argv == readme_test.argv, (ci_commands[-1].line, readme_test.line)


def test_the_parser_joins_continued_lines_drops_comments_and_splits_at_separators():
    text = 'a --x "1 2" && b -y  # c --z\nd \\\n  --w=3 | e; f\n'
    assert [command.argv for command in parse_block(text)] == [
        ("a", "--x", "1 2"), ("b", "-y"), ("d", "--w=3"), ("e",), ("f",)]
    assert option_words(parse_block(text)[2]) == ["--w"]
    assert option_words(Command(("warpavatar-render", "--background", "0", "-1", "-o", "x"), "", 0)) == [
        "--background", "-o"]


def test_an_option_that_help_does_not_list_is_reported():
    help_output = "usage: x [-o OUT] [--motion MOTION]\n  --motion-scale S  a longer flag\n"
    command = Command(("warpavatar-x", "--motion", "m", "--motion-sc", "-o", "y", "--mot"), "", 0)
    assert missing_options(command, help_output) == ["--motion-sc", "--mot"]


def test_paths_are_taken_from_blocks_links_and_code_spans():
    markdown = ("see [a](docs/a.md#top), [b](B.md), [c](https://example.com/c), `tools/x.py` and "
                "`warpavatar-out/demo`\n"
                "```bash\nrun research/y.py -o out/z https://example.com/docs/q\n```\n")
    assert repository_paths(markdown) == ["docs/a.md", "B.md", "research/y.py", "tools/x.py"]


def test_readme_names_warpavatar_commands():
    assert {command.argv[0] for command in WARPAVATAR_COMMANDS} >= {
        "warpavatar-fit", "warpavatar-view", "warpavatar-render", "warpavatar-animate"}


@pytest.mark.parametrize("name", sorted({command.argv[0] for command in WARPAVATAR_COMMANDS}))
def test_every_warpavatar_command_is_a_console_script(name):
    assert name in console_scripts(), f"README.md runs {name}, which setup.cfg does not install"


@pytest.mark.parametrize("command", WARPAVATAR_COMMANDS, ids=[command.line for command in WARPAVATAR_COMMANDS])
def test_every_option_is_in_the_commands_help(command):
    if command.argv[0] not in console_scripts():
        pytest.fail(f"{command.argv[0]} is not a console script")
    missing = missing_options(command, help_text(command.argv[0]))
    assert not missing, f"README.md block {command.block}: {command.line!r} gives {missing}, not in --help"


def test_every_repository_path_exists():
    missing = [path for path in repository_paths(README.read_text(encoding="utf-8"))
               if not (REPOSITORY / path).exists()]
    assert not missing, f"README.md names paths that do not exist: {missing}"


QUICK_COMMANDS = [command for command in readme_commands() if command.is_quick]


def test_readme_has_quick_lines():
    assert len(QUICK_COMMANDS) >= 2


@pytest.mark.parametrize("command", QUICK_COMMANDS, ids=[command.line for command in QUICK_COMMANDS])
def test_quick_lines_run(command):
    result = run_command(command)
    assert result.returncode == 0, f"{command.line!r} exited with {result.returncode}:\n{result.stderr[-2000:]}"
    assert result.stdout.startswith("usage: " + command.argv[0]), result.stdout[:500]


def _demo_blocks() -> tuple[Command, list[Command]]:
    """The demo's fit (the first set-up command, without its install) and the block of commands README runs on
    its output (the one that opens the viewer on ``warpavatar-out/demo``)."""
    blocks = [parse_block(text, block=index) for index, text in enumerate(bash_blocks(README.read_text()))]
    (fit,) = [command for command in blocks[0] if command.argv[:2] == ("warpavatar-fit", "--demo")]
    (after,) = [block for block in blocks
                if any(command.argv[:2] == ("warpavatar-view", "warpavatar-out/demo") for command in block)]
    return fit, after


def _view_serves(command: Command, cwd: Path, *, timeout: float = 300) -> str:
    """Start ``warpavatar-view`` as README says, wait for the address it prints, stop it; that address."""
    process = subprocess.Popen(entry_point_argv(command.argv[0], command.argv[1:]), cwd=cwd, text=True,
                               stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    try:
        timer = threading.Timer(timeout, process.kill)
        timer.start()
        for line in process.stdout:
            if found := re.search(r"http://127\.0\.0\.1:\d+/", line):
                return found.group(0)
        return ""
    finally:
        timer.cancel()
        process.terminate()
        process.wait(timeout=60)


def test_the_demo_and_the_commands_on_its_output_run(tmp_path):
    """README's demo, run as a reader would (in a fresh folder, on the shipped data), then the block it gives next:
    the viewer serves its page, the turntable is rendered and the export is written (the installs skipped)."""
    fit, after = _demo_blocks()
    result = run_command(fit, cwd=tmp_path, timeout=1800)
    assert result.returncode == 0, result.stderr[-2000:]
    assert "demo result in" in result.stdout and result.stdout.rstrip().splitlines()[-1].startswith("next: ")
    assert (tmp_path / "warpavatar-out" / "demo" / "avatar.pt").is_file()
    outputs = []
    for command in after:
        if command.argv[0] == "pip":
            continue
        if command.argv[0] == "warpavatar-view":
            assert _view_serves(command, tmp_path), f"{command.line!r} printed no address"
            continue
        result = run_command(command, cwd=tmp_path, timeout=900)
        assert result.returncode == 0, f"{command.line!r}: {result.stderr[-2000:]}"
        outputs.append(command.argv[command.argv.index("-o") + 1])
    assert outputs and all((tmp_path / output).stat().st_size > 0 for output in outputs), outputs
