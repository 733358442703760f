"""The command line as a new user meets it: help, exit codes, output paths, limits, interruptions.

Most commands run `main.main([...])` in this process, from an empty temporary folder, with
tiny step and frame counts; the interruption tests run `main.py` for real, since a signal
must reach a separate process.
"""

import contextlib
import io
import json
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

import main
from conftest import as_in_a_terminal
from app import device, progress
from app.display import display_problem
from fem import mesh

ROOT = Path(__file__).resolve().parents[1]


def run(*argv):
    """main.main(argv) in this process: (exit code, stdout, stderr)."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            code = main.main(list(argv))
        except SystemExit as exit:      # argparse's --help and usage errors
            code = exit.code
    return code, out.getvalue(), err.getvalue()


def one_error_line(err, *words):
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), err
    for word in words:
        assert word in lines[0], lines[0]
    return lines[0]


# The line a run without a terminal logs every 10 s (app.progress): a loaded machine prints
# some before an error found late in the run (a full disk, a video another run wrote).
# The progress of a run's steps or frames (app/progress.py), and of its kernels compiling (app/compiling.py).
PROGRESS_LINE = re.compile(r".+: \d+/\d+ \w+s \(\d+ %\) after \d+ s"
                           r"|.+: compiling kernels, \d+( of \d+)? \(\d+ s\)|.+: compiled \d+ kernels? in [\d.]+ s")


def final_error_line(err, *words):
    """The one `error:` line that ends err, after nothing but progress lines."""
    *progress, last = err.strip().splitlines() or [""]
    assert all(PROGRESS_LINE.fullmatch(line) for line in progress), err
    return one_error_line(last, *words)


@pytest.fixture
def here(tmp_path, monkeypatch):
    """An empty current folder, like a fresh clone's user would have for output."""
    monkeypatch.chdir(tmp_path)
    return tmp_path


# ---------------------------------------------------------------- help, and no work without a command

@pytest.mark.parametrize("argv", [["--help"], ["-h"], ["help"]])
def test_help_lists_every_command_and_starts_nothing(here, argv):
    code, out, err = run(*argv)
    assert code == 0, err
    for command in ("simulate", "export", "view", "bench", "scenes", "help"):
        assert f"\n    {command} " in out
    assert list(here.iterdir()) == []


def test_help_of_one_command_shows_its_options(here):
    code, out, _ = run("help", "export")
    assert code == 0 and "--frames" in out and "--video" in out
    code, _, err = run("help", "exprot")
    assert code == 2
    one_error_line(err, "no command 'exprot'")


@pytest.mark.parametrize("argv, hint", [(["simulat", "epcot"], "no command 'simulat'; did you mean simulate?"),
                                        (["help", "simulat"], "no command 'simulat'; did you mean simulate?"),
                                        (["simulate", "cube", "--stpes", "5"], "--stpes 5; did you mean --steps?"),
                                        (["export", "cube", "--frame=3"], "--frame=3; did you mean --frames?"),
                                        (["simulate", "cube", "--step", "10"],
                                         "'10' (choose from 'newton', 'single'); did you mean --steps?"),
                                        (["epcot", "--linear"], "e.g. `main.py simulate epcot --linear`")])
def test_a_mistyped_command_or_option_gets_a_did_you_mean(here, argv, hint):
    code, out, err = run(*argv)
    assert code == 2 and out == ""
    one_error_line(err, hint)
    assert list(here.iterdir()) == []


def test_a_word_given_to_a_choice_is_not_taken_for_a_number(here):
    code, _, err = run("simulate", "cube", "--step", "newtn")
    assert code == 2 and "did you mean" not in one_error_line(err, "invalid choice: 'newtn'")


@pytest.mark.parametrize("argv", [["--linear"], ["--frames", "3"], ["--debug"]])
def test_flags_without_a_command_are_one_error_and_start_nothing(here, argv):
    code, out, err = run(*argv)
    assert code == 2 and out == ""
    one_error_line(err, "no command given", "simulate")
    assert list(here.iterdir()) == []


# ---------------------------------------------------------------- output paths

# Each writes where nothing can be written; "afile" is a file in the current folder.
UNWRITABLE = {
    "--out under a file": ["export", "cube86", "--out", "afile/sub"],
    "--out in /proc": ["export", "cube86", "--out", "/proc/softfem-out"],
    "--video under a file": ["export", "cube86", "--out", "frames", "--video", "afile/v.mp4"],
    "--video in /proc": ["export", "cube86", "--out", "frames", "--video", "/proc/v.mp4"],
    "--video is a folder": ["export", "cube86", "--out", "frames", "--video", "."],
    "--stats under a file": ["simulate", "cube86", "--stats", "afile/s.jsonl"],
    "--stats in /proc": ["simulate", "cube86", "--stats", "/proc/s.jsonl"],
    "view --stats in /proc": ["view", "cube86", "--stats", "/proc/s.jsonl"],
    "view --out under a file": ["view", "cube86", "--out", "afile/shots"],
    "bench --out in /proc": ["bench", "--quick", "--out", "/proc/bench"],
}


@pytest.mark.parametrize("name", list(UNWRITABLE))
def test_every_unwritable_output_is_one_error_before_any_work(here, name):
    if "/proc/" in " ".join(UNWRITABLE[name]) and not Path("/proc/self").is_dir():
        pytest.skip("no /proc on this system")
    (here / "afile").write_text("mine")
    argv = UNWRITABLE[name]
    code, out, err = run(*argv)
    assert code == 2, err
    option = next(word for word in name.split() if word.startswith("--"))
    assert one_error_line(err).startswith(f"error: {option} "), err
    # Checked before any work: no frames, no folders, nothing else in the folder.
    assert sorted(p.name for p in here.iterdir()) == ["afile"]
    assert (here / "afile").read_text() == "mine"


# ---------------------------------------------------------------- --stats -, rejected steps

def test_stats_to_stdout_keeps_stdout_pure_json_and_the_summary_on_stderr(here):
    code, out, err = run("simulate", "cube86", "--steps", "3", "--stats", "-")
    assert code == 0, err
    rows = [json.loads(line) for line in out.splitlines()]
    assert [r["step"] for r in rows] == [1, 2, 3]
    assert "ms/step" in err and "scene cube86" in err


def test_a_closed_stdout_drops_what_was_meant_for_it(tmp_path):
    """`main.py ... >&-` starts Python without a stdout (sys.stdout is None): the run still ends
    with exit code 0, no traceback, and writes its files."""
    command = f"exec {sys.executable} {ROOT / 'main.py'} simulate torsion --steps 2 --stats s.jsonl >&-"
    done = subprocess.run(["bash", "-c", command], cwd=tmp_path, stderr=subprocess.PIPE, text=True, timeout=600)
    assert done.returncode == 0 and "Traceback" not in done.stderr, done.stderr
    assert len((tmp_path / "s.jsonl").read_text().splitlines()) == 2


def test_the_summary_says_where_the_linear_solve_stopped_at_its_cap(here):
    """A linear solve cut short by --max-iters leaves Newton's direction inexact: every such
    iteration is counted in the stats rows (solver_capped) and the summary says how many of the
    run's Newton iterations it was; a run whose solves all converged says nothing of it."""
    code, out, err = run("simulate", "cube86", "--steps", "3", "--max-iters", "1", "--tol", "1e-10",
                         "--stats", "capped.jsonl")
    assert code == 0, err
    rows = [json.loads(line) for line in Path("capped.jsonl").read_text().splitlines()]
    capped, newton = sum(r["solver_capped"] for r in rows), sum(r["newton_iters"] for r in rows)
    assert 0 < capped <= newton and all(r["solver_capped"] <= r["newton_iters"] for r in rows)
    assert not all(r["converged"] for r in rows)
    assert (f"the linear solve stopped at its cap of 1 iteration, unconverged, in {capped} of {newton} "
            f"Newton iterations") in out, out
    code, out, err = run("simulate", "cube86", "--steps", "3", "--stats", "free.jsonl")
    assert code == 0 and "stopped at its cap" not in out, err
    assert all(json.loads(line)["solver_capped"] == 0 for line in Path("free.jsonl").read_text().splitlines())


@pytest.mark.parametrize("argv, says", [((), "dt 0.02 s, trapezoidal (rho_infinity 0.961) (auto), solver"),   # damped: exp(-dt / 0.5 s)
                                        (("--integrator", "bdf2"), "dt 0.02 s, bdf2, solver")])
def test_the_summary_names_the_integrator_the_steps_took(here, argv, says):
    code, out, err = run("simulate", "cube86", "--steps", "2", *argv)
    assert code == 0 and says in out, err


def test_a_time_step_out_of_range_is_refused_before_the_run(here):
    # 1e6 s survives the step, 1e30 s did not: neither is a time step (a run whose every step is
    # rejected is tests/test_limits.py's)
    code, out, err = run("simulate", "cube86", "--steps", "3", "--dt", "1e30")
    assert code == 2 and out == ""
    assert err.startswith("error: ") and "dt must be in [1e-08, 100] s" in err


def test_export_without_out_writes_a_new_folder_each_time(here):
    for folder in ("cube86", "cube86-2"):
        code, out, err = run("export", "cube86", "--frames", "1", "--size", "160x128")
        assert code == 0, err
        assert (here / "out" / folder / "frame_00000.png").is_file()
        assert f"out/{folder}/frame_00000.png" in out


# ---------------------------------------------------------------- size limits

def test_a_huge_frame_is_refused_with_the_limit_and_the_way_past_it(here):
    code, _, err = run("export", "cube86", "--size", "100000x100000", "--out", "o")
    assert code == 2
    one_error_line(err, "--size 100000x100000", "8192", "--allow-large")
    assert list(here.iterdir()) == []


def test_a_huge_mesh_is_refused_before_memory_runs_out(here):
    start = time.perf_counter()
    code, _, err = run("simulate", "cube86", "--set", "body.*.mesh.cells=[2000,2000,2000]")
    assert code == 2
    one_error_line(err, "--set body.*.mesh.cells=[2000,2000,2000]", "40,000,000,000 tets",
                   "GB of host memory", "--allow-large")
    assert time.perf_counter() - start < 30      # refused before the lattice is built, not after


def test_allow_large_lifts_the_tet_limit(here, monkeypatch):
    monkeypatch.setattr(mesh, "MAX_TETS", 100)   # cube86's cubes have 135 tets each
    code, _, err = run("simulate", "cube86", "--steps", "1")
    assert code == 2
    one_error_line(err, "135 tets", "limit of 100")
    code, out, err = run("simulate", "cube86", "--steps", "1", "--allow-large")
    assert code == 0, err
    assert mesh.MAX_TETS == 100                   # lifted for that command only


# ---------------------------------------------------------------- --set

def test_set_mistakes_are_blamed_on_set_not_on_the_scene_file(here):
    code, _, err = run("simulate", "torsion", "--set", "body.bar.material.E=-1")
    assert code == 2
    line = one_error_line(err, "E must be > 0")
    assert line.startswith("error: --set body.bar.material.E=-1: ")
    code, _, err = run("simulate", "torsion", "--set", "solver.dt=0.01", "--set", "solver.tolerance=0")
    line = one_error_line(err, "tolerance must be > 0")
    assert line.startswith("error: --set solver.tolerance=0: ")


def test_set_paths_are_relative_to_the_current_folder(here):
    import scenes
    from cases import CUBE_MESH

    (here / "statue.mesh").write_text(CUBE_MESH)
    scene = scenes.load_scene("fertility", overrides=['body.*.mesh={file="statue.mesh"}', "body.*.scale=2.0"])
    assert [len(b.mesh.tets) for b in scene.bodies] == [5, 5]
    assert all(b.mesh.source == str(here / "statue.mesh") for b in scene.bodies)
    code, _, err = run("simulate", "fertility", "--set", 'body.low.mesh={file="missing.mesh"}')
    assert code == 2
    one_error_line(err, "--set body.low.mesh=", "not found", str(here / "missing.mesh"))


# ---------------------------------------------------------------- devices and displays

def test_a_software_vulkan_device_is_named_and_warned_about():
    devices = [("llvmpipe (LLVM 15.0.6, 256 bits)", 4)]
    name, kind = device.pick_vulkan_device(devices)
    found = {"backend": "vulkan", "name": name, "software": kind == device.VULKAN_CPU_TYPE}
    line = device.report("gpu", found)
    assert line.startswith("warning: --arch gpu: running on Vulkan (llvmpipe") and "--arch cpu" in line
    hardware = {"backend": "cuda", "name": "NVIDIA H100", "software": False}
    assert device.report("gpu", hardware) == "--arch gpu: running on CUDA (NVIDIA H100)"
    assert "no CUDA" in device.report("auto", {"backend": "x64", "name": "a CPU", "software": False})


def test_taichi_picks_the_discrete_gpu_unless_told_otherwise():
    devices = [("llvmpipe", 4), ("Intel UHD", 1), ("NVIDIA RTX", 2)]
    assert device.pick_vulkan_device(devices) == ("NVIDIA RTX", 2)
    assert device.pick_vulkan_device(devices, visible="0") == ("llvmpipe", 4)


def test_arch_gpu_says_which_device_or_why_there_is_none(here):
    code, out, err = run("simulate", "cube86", "--steps", "1", "--arch", "gpu")
    if code == 2:                                  # no GPU backend on this machine
        one_error_line(err, "--arch gpu", "no GPU")
    else:
        assert code == 0 and "--arch gpu: running on" in err


def test_wayland_without_a_compositor_is_one_error_line(here, monkeypatch, tmp_path):
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.setenv("WAYLAND_DISPLAY", "wayland-97")
    monkeypatch.setenv("XDG_RUNTIME_DIR", str(tmp_path))
    code, out, err = run("view", "cube86")
    assert code == 2
    one_error_line(err, "view:", "no Wayland compositor", "wayland-97")
    # A compositor but no XWayland: Taichi's window speaks X11 only.
    (tmp_path / "wayland-97").touch()
    assert "needs X11" in display_problem({"WAYLAND_DISPLAY": "wayland-97", "XDG_RUNTIME_DIR": str(tmp_path)})
    assert display_problem({"DISPLAY": "remote:0"}) is None


# ---------------------------------------------------------------- progress in logs

def test_no_progress_bar_in_a_log(monkeypatch):
    log = io.StringIO()                            # not a terminal
    with progress.Progress(1000, "frame", "epcot", stream=log) as bar:
        for _ in range(1000):
            bar.update()
    assert log.getvalue() == ""                    # a quick run: not a line
    monkeypatch.setattr(progress, "LOG_INTERVAL", 0.0)
    with progress.Progress(3, "frame", "epcot", stream=log) as bar:
        for _ in range(3):
            bar.update()
            bar.set_description("epcot (linear)")
    assert "\r" not in log.getvalue()
    assert log.getvalue().splitlines() == ["epcot: 1/3 frames (33 %) after 0 s",
                                           "epcot (linear): 2/3 frames (67 %) after 0 s"]


# ---------------------------------------------------------------- interruptions

def start(argv, folder):
    """`main.py argv` in folder, able to get the signals a terminal sends (`as_in_a_terminal`)."""
    return subprocess.Popen([sys.executable, str(ROOT / "main.py"), *argv], cwd=folder,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            preexec_fn=as_in_a_terminal)


def wait_for(condition, process, timeout=300):
    end = time.monotonic() + timeout
    while not condition() and process.poll() is None and time.monotonic() < end:
        time.sleep(0.05)
    assert process.poll() is None, process.communicate()


@pytest.mark.parametrize("signal_number", [signal.SIGINT, signal.SIGTERM, signal.SIGHUP, signal.SIGQUIT,
                                           signal.SIGUSR1], ids=["ctrl-c", "sigterm", "sighup", "sigquit", "sigusr1"])
def test_interrupted_simulate_keeps_every_complete_row(tmp_path, signal_number):
    process = start(["simulate", "cube86", "--steps", "100000", "--stats", "s.jsonl"], tmp_path)

    def rows_written():
        return sum(p.read_text().count("\n") for p in tmp_path.glob(".s.jsonl.*.softfem-part"))

    wait_for(lambda: rows_written() >= 20, process)
    process.send_signal(signal_number)
    out, err = process.communicate(timeout=300)
    assert process.returncode == 130, err
    assert "Traceback" not in err
    rows = [json.loads(line) for line in (tmp_path / "s.jsonl").read_text().splitlines()]
    assert len(rows) >= 20 and [r["step"] for r in rows] == list(range(1, len(rows) + 1))
    assert f"kept its {len(rows)} complete rows in s.jsonl" in err
    assert [p.name for p in tmp_path.iterdir()] == ["s.jsonl"]        # no .part file left


def test_a_bare_command_without_a_usable_display_exports_instead(here, monkeypatch, tmp_path):
    from app import cli
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.setenv("WAYLAND_DISPLAY", "wayland-97")      # set, but no compositor behind it
    monkeypatch.setenv("XDG_RUNTIME_DIR", str(tmp_path))
    (here / "out" / "epcot").mkdir(parents=True)
    (here / "out" / "epcot" / "mine.png").write_text("an earlier export")
    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        argv = cli.default_arguments()
    assert argv[:3] == ["export", "epcot", "--compare"] and "out/epcot-2" in argv
    assert "no Wayland compositor" in err.getvalue()
