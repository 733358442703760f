"""Sizes checked before anything is allocated, numbers that would overflow, nesting, long names
(issue 24, "memory and time" and "crafted input"): one `error:` line, exit 2, small memory.
"""

import os
import resource
import subprocess
import sys

import pytest

from app.commands.simulate import Tally, check_rejected, fallback_note
from fem import limits
from tests.test_cli import ROOT, final_error_line, here, one_error_line, run  # noqa: F401  (here is a fixture)

# Peak memory of a run refused before its allocation: Python, numpy and the engine's imports
# take about 150 MB; a refused description must not add more than a little to it.
REFUSED_PEAK_MB = 400


def many_bodies(count):
    return "".join(f'[[body]]\nname = "b{i}"\nmesh = {{generator = "box", cells = [1, 1, 1]}}\n'
                   f'material = {{E = 1e4, nu = 0.3}}\nposition = [{2 * i}, 0, 0]\n' for i in range(count))


SIZES = {
    "box of 1500^3 cells": ["cube", "--set", "body.0.mesh.cells=[1500,1500,1500]"],
    "box of 2000^3 cells": ["cube", "--set", "body.0.mesh.cells=[2000,2000,2000]"],
    "dome with a million legs": ["epcot", "--set", "body.0.mesh.legs=1000000"],
    "statue of resolution 100000": ["fertility", "--set", "body.0.mesh.resolution=100000"],
    "10000 bodies": ["many.toml"],
    "a 300 MB mesh file": ["big.mesh"],
    "a 300 MB surface file": ["big.obj"],
}


def write_inputs(folder):
    (folder / "many.toml").write_text(many_bodies(10_000))
    for name in ("big.mesh", "big.obj"):
        with open(folder / name, "wb") as f:          # sparse: takes no disk
            f.truncate(300 * 2**20)


@pytest.mark.parametrize("name", list(SIZES))
def test_a_size_over_its_limit_is_refused_before_allocation(here, name):
    write_inputs(here)
    code, out, err = run("simulate", *SIZES[name], "--steps", "1")
    assert code == 2, err
    one_error_line(err, "--allow-large lifts the limit")


@pytest.mark.parametrize("argv, words", [
    (["export", "cube", "--size", "100000x100000"], ["8192 pixels a side"]),
    (["export", "cube", "--speed", "1e300"], ["steps per frame", "--steps-per-frame"]),
    (["export", "cube", "--fps", "1e-9"], ["steps per frame"]),
], ids=["image size", "speed 1e300", "fps 1e-9"])
def test_an_export_that_would_never_end_or_fill_the_memory_is_refused(here, argv, words):
    code, out, err = run(*argv, "--frames", "2", "--out", "o")
    assert code == 2, err
    final_error_line(err, *words)        # after the kernels' progress lines, where they compile first
    assert not (here / "o").exists()


# Linux counts a forked child's peak from its parent's size at the fork: a test process grown
# to hundreds of MB would report that for every child. A small launcher starts it instead.
LAUNCHER = """import os, subprocess, sys
process = subprocess.Popen(sys.argv[1:], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
err = process.stderr.read()
_, status, usage = os.wait4(process.pid, 0)
sys.stderr.write(err)
print(usage.ru_maxrss)
sys.exit(os.waitstatus_to_exitcode(status))
"""


def peak_memory_mb(argv, folder):
    """(exit code, stderr, peak resident memory in MB) of `main.py argv` as its own process."""
    done = subprocess.run([sys.executable, "-c", LAUNCHER, sys.executable, str(ROOT / "main.py"), *argv],
                          cwd=folder, capture_output=True, text=True)
    return done.returncode, done.stderr, int(done.stdout.split()[-1]) / 1024      # Linux: kB


@pytest.mark.parametrize("name", ["box of 2000^3 cells", "10000 bodies", "a 300 MB mesh file"])
def test_the_largest_refused_descriptions_take_little_memory(tmp_path, name):
    write_inputs(tmp_path)
    code, err, peak = peak_memory_mb(["simulate", *SIZES[name], "--steps", "1"], tmp_path)
    assert code == 2 and err.startswith("error: "), err
    assert peak < REFUSED_PEAK_MB, f"{name}: {peak:.0f} MB"


CRAFTED = {
    "E 1e308": ["--set", "body.0.material.E=1e308"],
    "E 1e14": ["--set", "body.0.material.E=1e14"],
    "density 1e308": ["--set", "body.0.material.density=1e308"],
    "position 1e308": ["--set", "body.0.position=[1e308, 0, 0]"],
    "position 1e16": ["--set", "body.0.position=[1e16, 0, 0]"],
    "scale 1e-300": ["--set", "body.0.scale=1e-300"],
    "size inf": ["--set", "body.0.mesh.size=[inf, 1, 1]"],
    "size 1e-300": ["--set", "body.0.mesh.size=[1e-300, 1, 1]"],
    "cells inf": ["--set", "body.0.mesh.cells=[inf, 1, 1]"],
    "gravity 1e308": ["--set", "effects.gravity=[0, -1e308, 0]"],
    "velocity 1e308": ["--set", "initial=[{velocity=[1e308, 0, 0]}]"],
    "max_iterations 1e30": ["--set", "solver.max_iterations=1000000000000000000000000000000"],
    "dt 1e-300": ["--dt", "1e-300"],
    "dt 1e6": ["--dt", "1e6"],
    "solver.dt 1e-300": ["--set", "solver.dt=1e-300"],
}


@pytest.mark.parametrize("name", list(CRAFTED))
def test_numbers_that_would_overflow_are_refused(here, name):
    code, out, err = run("simulate", "cube", "--steps", "1", *CRAFTED[name])
    assert code == 2, err
    one_error_line(err)


def test_deep_nesting_in_a_file_or_a_set_value_is_refused(here):
    (here / "deep.toml").write_text("x = " + "[" * 1000 + "]" * 1000 + "\n")
    (here / "deep2.toml").write_text("x = " + "{a = " * 1000 + "1" + "}" * 1000 + "\n")
    for argv in (["deep.toml"], ["deep2.toml"], ["cube", "--set", "x=" + "[" * 1000 + "]" * 1000],
                 ["cube", "--set", "x=" + "[" * 100 + "]" * 100], ["cube", "--set", "a" + ".a" * 3000 + "=1"]):
        code, out, err = run("simulate", *argv, "--steps", "1")
        assert code == 2, err
        line = one_error_line(err, "deep")
        assert len(line) < 300                      # the value is quoted, not printed whole


def test_a_name_longer_than_the_file_system_allows_is_one_error_line(here):
    long = "a" * 300
    for argv in ([f"{long}.toml"], [f"{long}.obj"], ["cube", "--set", f'body.0.mesh={{file="{long}.mesh"}}'],
                 ["cube", "--stats", f"{long}.jsonl"]):
        code, out, err = run("simulate", *argv, "--steps", "1")
        assert code == 2, err
        one_error_line(err, "file name too long")


def test_an_error_quotes_a_short_excerpt_of_a_file_not_its_line(here):
    (here / "system.mesh").write_text("1 root:x:0:0:" + "x" * 5000 + "\x1b[31m\n")
    code, out, err = run("simulate", "system.mesh", "--steps", "1")
    assert code == 2
    line = one_error_line(err, "system.mesh")
    assert len(line) < 300 and "\x1b" not in line


def test_a_run_whose_every_step_is_rejected_fails_with_a_clear_error(capsys):
    rows = Tally()
    rows += [{"wall_ms": 1.0, "solver_iters": 0, "newton_iters": 0, "converged": False, "finite": False,
              "energy_limited": 0, "restarted": 0, "solver_capped": 0}] * 3
    assert check_rejected(rows, 0.02) == 1
    assert capsys.readouterr().err.startswith("error: every one of the 3 steps was rejected")


def test_the_summary_counts_rigid_steps_and_backward_euler_restarts():
    rows = Tally()
    row = {"wall_ms": 1.0, "solver_iters": 1, "newton_iters": 1, "converged": False, "finite": True, "solver_capped": 0}
    rows += [dict(row, energy_limited=2, restarted=0), dict(row, energy_limited=0, restarted=1, converged=True),
             dict(row, energy_limited=1, restarted=0)]
    assert fallback_note(rows) == (" (of them 2 with a rigid step instead of the solve's), 1 step by backward "
                                   "Euler after a strained body's failed one")
    assert fallback_note(Tally()) == ""


def test_a_runs_step_records_are_compact_columns():
    rows = Tally()
    rows += [{"wall_ms": 2.0, "solver_iters": 5, "newton_iters": 1, "converged": True, "finite": True,
              "energy_limited": 0, "restarted": 0, "solver_capped": 0, "big": list(range(100))}] * 1000
    assert len(rows) == 1000 and sum(rows["finite"]) == 1000
    assert sum(column.itemsize * len(column) for column in rows.columns.values()) < 70_000   # 8 columns


def test_allow_large_lifts_the_size_limits():
    with limits.lifted():
        limits.check_body_count(10 * limits.MAX_BODIES, "x.toml")
    with pytest.raises(limits.SizeLimitError):
        limits.check_body_count(10 * limits.MAX_BODIES, "x.toml")


def test_peak_memory_is_measured_in_kilobytes():
    assert resource.getrusage(resource.RUSAGE_SELF).ru_maxrss > 10_000      # this process, > 10 MB in kB


# ---------------------------------------------------------------- the tet limit follows the memory

def test_the_tet_limit_is_half_the_host_memory_at_the_bytes_a_tet_takes():
    total = next(int(line.split()[1]) * 1024 for line in open("/proc/meminfo") if line.startswith("MemTotal"))
    # MemTotal leaves out what the kernel reserves: within a few percent of the physical pages
    assert limits.tet_limit() == pytest.approx(limits.MEMORY_SHARE * total / limits.BYTES_PER_TET["f32"],
                                               rel=0.05)
    assert limits.memory()[1] == "host memory"


def test_a_box_over_the_memorys_limit_is_refused_naming_the_memory_then_built_knowingly(here, monkeypatch):
    """With 40 MB of memory (20 MB for the tets: 36,363 at 550 bytes), box50k's 49,130 tets are
    refused, naming the memory they need and the memory there is; --allow-large builds them."""
    monkeypatch.setattr(limits, "host_memory", lambda: 40_000_000)
    assert limits.tet_limit() == 36_363
    box = str(ROOT / "examples" / "box50k.toml")
    code, _, err = run("simulate", box, "--steps", "1")
    assert code == 2
    one_error_line(err, "49,130 tets", "limit of 36,363 tets per mesh", "need about 27 MB of memory",
                   "50% of the 40 MB of host memory", "--allow-large lifts the limit")
    code, out, err = run("simulate", box, "--steps", "1", "--set", "body.bar.mesh.cells=[20,10,10]")
    assert code == 0, err                                      # 10,000 tets fit
    code, out, err = run("simulate", box, "--steps", "1", "--allow-large")
    assert code == 0, err
    assert "49130 tets" in out
