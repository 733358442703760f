"""Every command the READMEs show works, run in the order shown, as on a fresh clone.

The commands are read from README.md, scenes/README.md and docs/experiments.md: the lines
of `bash` blocks and the inline `python main.py ...` spans (not the syntax lines, whose words in capitals, such
as SCENE or FILE.jsonl, stand for what a user fills in). Each runs in one shared, initially
empty folder through `main.main` in this process, with fewer frames and steps and smaller
pictures than shown, and shorter figures. A user's own files the text names (my_shape.obj,
fertility.mesh) are made up first. Commands that cannot run here are listed in SKIPPED with
the reason, so a new command in a README fails this test until it runs or is listed.
"""

import contextlib
import io
import re
import shlex
import shutil
from pathlib import Path

import pytest
import trimesh
from conftest import fan_tets

import fem
import main
from app import cli
from assets import box, tetrahedralize
from fem.mesh import TetMesh, write_tet_mesh

ROOT = Path(__file__).resolve().parents[1]
READMES = [ROOT / "README.md", ROOT / "scenes" / "README.md", ROOT / "docs" / "experiments.md"]
PROGRAMS = ("python main.py", ".venv/bin/python main.py", "softfem", ".venv/bin/softfem")
# What a command may start with that does not run here, and why.
SKIPPED = {
    "python3 -m venv": "makes the environment these tests run in",
    ".venv/bin/pip install": "installs; tests/test_package.py installs the package for real",
    ".venv/bin/python -m pytest": "the test suite itself",
    "apt-get install": "system packages",
    "view": "opens a window and waits for its user; tests/test_viewer.py drives it under Xvfb",
    "bench": "takes minutes; tests/test_bench.py runs it on one small scene",
}
FRAMES, STEPS, SIZE = "2", "3", "160x128"
# `figures` runs --quick, and only these when the command asks for all of them (minutes);
# tests/test_figures.py checks the figures and their numbers.
FIGURES = ["torsion_length"]
PLACEHOLDER = re.compile(r"^\[|\]$|\||^[A-Z]+([._=][A-Za-z0-9.]+)?$")


def commands(text):
    """Commands in a README, in order, each as its list of words."""
    found = []
    for block, inline in re.findall(r"```bash\n(.*?)```|`([^`\n]+)`", text, flags=re.S):
        # An inline span is a command when it runs the program with arguments, not a mention of it.
        lines = block.splitlines() if block else [inline] if inline.startswith(PROGRAMS) else []
        for line in lines:
            for command in line.split("&&"):
                words = shlex.split(command, comments=True)
                if not words or any(PLACEHOLDER.search(word) for word in words):
                    continue
                if block or argv_of(words):
                    found.append(words)
    return found


def python_blocks(text):
    return re.findall(r"```python\n(.*?)```", text, flags=re.S)


def argv_of(words):
    """The arguments after the program, or None when the command is not the program."""
    for program in sorted(PROGRAMS, key=len, reverse=True):
        if words[:len(program.split())] == program.split():
            return words[len(program.split()):]
    return None


def skip_reason(words):
    argv = argv_of(words)
    for start, reason in SKIPPED.items():
        if shlex.join(words).startswith(start) or (argv and argv[0] == start):
            return reason
    return None


def smaller(argv):
    """argv with fewer frames and steps and a smaller picture: same command, quicker."""
    argv = list(argv)
    wanted = {"export": {"--frames": FRAMES, "--size": SIZE}, "simulate": {"--steps": STEPS}}
    for option, value in wanted.get(argv[0] if argv else None, {}).items():
        if option in argv:
            argv[argv.index(option) + 1] = value
        else:
            argv += [option, value]
    if argv[:1] == ["figures"]:
        argv += ["--quick"] + ([] if "--only" in argv else ["--only", *FIGURES])
    return argv


ALL = [(str(readme.relative_to(ROOT)), words) for readme in READMES for words in commands(readme.read_text())]


def test_the_readmes_show_commands():
    shown = [words for _, words in ALL]
    assert [] in map(argv_of, shown), "the bare `main.py` of the two commands"
    assert any("my_shape.obj" in words for words in shown), "your own mesh in one command"
    unknown = [shlex.join(w) for w in shown if argv_of(w) is None and not skip_reason(w)]
    assert unknown == [], "commands that neither run here nor are listed in SKIPPED"


@pytest.fixture(scope="module")
def clone(tmp_path_factory):
    """The folder a new user runs the commands in, with the files they would bring."""
    folder = tmp_path_factory.mktemp("fresh-clone")
    shutil.copytree(ROOT / "examples", folder / "examples", ignore=shutil.ignore_patterns("*.py"))   # a clone's scene files
    trimesh.creation.icosphere(subdivisions=2, radius=40.0).export(folder / "my_shape.obj")
    statue = box(size=(40.0, 130.0, 30.0), cells=(2, 4, 2))
    write_tet_mesh(TetMesh(statue.vertices, statue.tets), folder / "fertility.mesh")
    return folder


@pytest.mark.parametrize("readme, words", ALL, ids=[f"{r}: {shlex.join(w)}" for r, w in ALL])
def test_command_works_in_the_order_shown(clone, monkeypatch, readme, words):
    command, argv = shlex.join(words), argv_of(words)
    reason = skip_reason(words)
    if reason:
        pytest.skip(f"{command}: {reason}")
    monkeypatch.chdir(clone)
    monkeypatch.setenv("FEM_CACHE_DIR", str(clone / ".cache"))
    monkeypatch.setattr(tetrahedralize, "_run_wildmeshing", fan_tets)   # test_own_mesh runs the real one
    if argv == []:                       # the bare command: the export made without a display
        monkeypatch.delenv("DISPLAY", raising=False)
        monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
        monkeypatch.setattr(cli, "DEFAULT_FRAMES", int(FRAMES))
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            code = main.main(smaller(argv))
        except SystemExit as exit:       # --help
            code = exit.code
    assert code == 0, f"{command}\n{err.getvalue()}"
    assert "error:" not in err.getvalue()


@pytest.mark.parametrize("readme", READMES[:1], ids=["README.md"])
def test_python_example_runs(clone, monkeypatch, readme):
    monkeypatch.chdir(clone)
    for code in python_blocks(readme.read_text()):
        with contextlib.redirect_stdout(io.StringIO()) as out:
            exec(compile(code, str(readme), "exec"), {})
        assert "(" in out.getvalue()      # it prints the volume ratios and the positions' shape
    fem.init("cpu", "f32")


def test_one_form_of_the_command_throughout():
    """Copied as written, `python main.py` runs the system's Python, without Taichi: every page
    writes the command as the README's first lines do (.venv/bin/python main.py, or softfem)."""
    bare = re.compile(r"(?<![/\w.])python3? main\.py")
    pages = READMES + sorted((ROOT / "docs").glob("*.md"))
    found = [f"{page.relative_to(ROOT)}:{n}" for page in pages
             for n, line in enumerate(page.read_text().splitlines(), 1) if bare.search(line)]
    assert found == []
