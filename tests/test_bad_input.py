"""Bad files and parameters (tests/cases.py BAD_INPUTS): one `error:` line naming the file, exit 2.

Most run `main.main` in this process (the error comes before Taichi compiles anything); a few
run `python main.py simulate` for real to check the exit code and that no traceback leaks.
"""

import subprocess
import sys

import pytest

from cases import BAD_INPUTS, ROOT, run_bad_input

BY_NAME = {case.name: case for case in BAD_INPUTS}


@pytest.mark.parametrize("case", BAD_INPUTS, ids=[case.name for case in BAD_INPUTS])
def test_bad_input_gives_one_error_line(case, tmp_path):
    code, stderr = run_bad_input(case, tmp_path)
    lines = stderr.strip().splitlines()
    assert code == 2, stderr
    assert len(lines) == 1 and lines[0].startswith("error: "), stderr
    for words in case.expect:
        assert words in lines[0]


def simulate(case, folder, *extra):
    for name, text in case.files.items():
        (folder / name).write_text(text)
    return subprocess.run([sys.executable, str(ROOT / "main.py"), "simulate", *case.args, *extra],
                          cwd=folder, capture_output=True, text=True, timeout=300)


@pytest.mark.parametrize("name", ["NaN coordinate", "coursework: header promises 3 impulses, has 2",
                                  "misspelt key", "--dt 0"])
def test_command_line_exits_2_without_traceback(name, tmp_path):
    run = simulate(BY_NAME[name], tmp_path)
    assert run.returncode == 2
    assert run.stderr.count("\n") == 1 and run.stderr.startswith("error: "), run.stderr
    assert run.stdout == ""


def test_debug_shows_the_traceback(tmp_path):
    run = simulate(BY_NAME["zero-volume tet"], tmp_path, "--debug")
    assert run.returncode != 0
    assert "Traceback" in run.stderr and "FemError" in run.stderr
