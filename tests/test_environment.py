"""The environment Taichi reads as it starts (issue 37): settings it would die on (SIGABRT,
SIGFPE, SIGSEGV at exit) either run, with a checked cache folder, or end in one `error:` line."""

import os
import subprocess
import sys

import pytest

from test_cli import ROOT, final_error_line, one_error_line


def simulate(tmp_path, change):
    """`main.py simulate cube --steps 1` in tmp_path with the environment changed as `change`
    says ({name: value}, a value None unsets it). A changed HOME also unsets XDG_CACHE_HOME, which
    would otherwise name the cache folder whatever HOME is (a run of the suite with it set)."""
    env = {**os.environ, "FEM_CACHE_DIR": str(tmp_path / "cache")}
    if "HOME" in change:
        env.pop("XDG_CACHE_HOME", None)
    for name, value in change.items():
        if value is None:
            env.pop(name, None)
        else:
            env[name] = value
    return subprocess.run([sys.executable, str(ROOT / "main.py"), "simulate", "cube", "--steps", "1"],
                          cwd=tmp_path, env=env, capture_output=True, text=True, timeout=600)


@pytest.mark.parametrize("change", [{"HOME": None}, {"HOME": "/dev/null"}, {"XDG_CACHE_HOME": "/proc"},
                                    {"TI_OFFLINE_CACHE_FILE_PATH": str(ROOT / "README.md")}],
                         ids=["HOME unset", "HOME=/dev/null", "XDG_CACHE_HOME=/proc", "cache path a file"])
def test_an_unusable_home_or_cache_folder_still_runs(tmp_path, change):
    run = simulate(tmp_path, change)
    assert run.returncode == 0, run.stderr
    assert "1 step to t =" in run.stdout
    if change != {"HOME": None}:
        assert "cannot be written; using" in run.stderr


@pytest.mark.parametrize("name, value", [("TI_LOG_LEVEL", "garbage"), ("TI_CPU_MAX_NUM_THREADS", "0"),
                                         ("TI_CPU_MAX_NUM_THREADS", "100000")])
def test_a_taichi_setting_it_cannot_use_is_one_error_line(tmp_path, name, value):
    run = simulate(tmp_path, {name: value})
    assert run.returncode == 2
    one_error_line(run.stderr, f"environment variable {name}={value!r}")


def main_py(tmp_path, *argv, stdout, env=None):
    return subprocess.run([sys.executable, str(ROOT / "main.py"), *argv], cwd=tmp_path, stdout=stdout,
                          stderr=subprocess.PIPE, text=True, timeout=600, env={**os.environ, **(env or {})})


@pytest.mark.parametrize("argv", [["scenes"], ["simulate", "cube", "--steps", "1"]], ids=["scenes", "simulate"])
def test_stdout_on_a_full_device_is_one_error_line(tmp_path, argv):
    with open("/dev/full", "w") as full:
        run = main_py(tmp_path, *argv, stdout=full)
    assert run.returncode == 2
    final_error_line(run.stderr, "standard output: no space left on device")


@pytest.mark.parametrize("argv", [["--version"], ["--help"], ["help", "export"]])
def test_a_reader_gone_before_the_version_or_help_is_quiet(tmp_path, argv):
    read, write = os.pipe()
    os.close(read)                                 # `main.py --version | true`
    with os.fdopen(write, "w") as pipe:
        run = main_py(tmp_path, *argv, stdout=pipe)
    # 141 where the write failed at the end (SIGPIPE's code), 0 where print's own failure emptied
    # the buffer; either way no traceback (a shell reports `true`'s code for the pipe anyway).
    assert run.returncode in (0, 141) and run.stderr == ""


def test_a_name_the_terminal_cannot_show_is_escaped(tmp_path):
    (tmp_path / "cubé.mesh").write_text("MeshVersionFormatted 1\nDimension 3\nVertices\n4\n0 0 0 0\n1 0 0 0\n"
                                        "0 1 0 0\n0 0 1 0\nTetrahedra\n1\n1 2 3 4 0\nEnd\n")
    run = main_py(tmp_path, "simulate", "cubé.mesh", "--steps", "1", stdout=subprocess.PIPE,
                  env={"PYTHONIOENCODING": "ascii"})
    assert run.returncode == 0, run.stderr
    assert "scene cub\\xe9:" in run.stdout
