"""What a user waits before the first step, measured (the benchmark's start-up rows).

    cold    `main.py simulate SCENE --steps 1` in a new process, Taichi's offline cache empty
    warm    the same with the user's own offline cache, after one run that fills it
    taichi  `python -c "import taichi as ti; ti.init(arch=ti.cpu)"`, Taichi's own start, in turn
            with the warm runs: what a warm start is measured against
    second  in one process, a second Simulation of the scene made after the first one is
            dropped, to the end of its first step (its kernels are compiled already, fem/pool.py)
    beside  the same while the first one is still alive: it needs parts of its own
    view    `main.py view SCENE` on a warm cache: to its first frame (the scene drawn at rest)
            and to its first stepped frame, on $DISPLAY or a virtual display (Xvfb)

Medians of `repeats` runs, wall seconds. The cold runs each use a new empty cache folder.
"""

import contextlib
import datetime
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def process_seconds(scene, cache=None):
    """Wall time of `main.py simulate SCENE --steps 1` with Taichi's offline cache in `cache`
    (None: where it always is)."""
    env = dict(os.environ, **({"TI_OFFLINE_CACHE_FILE_PATH": str(cache)} if cache else {}))
    start = time.perf_counter()
    subprocess.run([sys.executable, str(ROOT / "main.py"), "simulate", scene, "--steps", "1"],
                   env=env, check=True, capture_output=True, timeout=600)
    return time.perf_counter() - start


def taichi_seconds(repeats=3):
    """Wall time of `python -c "import taichi as ti; ti.init(arch=ti.cpu)"` (median of `repeats`):
    Taichi's own start, what a warm start is measured against."""
    command = [sys.executable, "-c", "import taichi as ti; ti.init(arch=ti.cpu)"]

    def once():
        start = time.perf_counter()
        subprocess.run(command, check=True, capture_output=True, timeout=300)
        return time.perf_counter() - start

    return statistics.median(once() for _ in range(repeats))


def breakdown(scene, options=(), repeats=3):
    """Where a warm start of `main.py simulate SCENE [options] --steps 1` goes: the median over
    `repeats` new processes (after one that fills the cache) of each figure that
    app/bench/startup_probe.py prints (imports, Taichi's start, building, the first step; the
    kernels' translating and compiling or loading, their count and variants), with the
    slowest kernels of the median run."""
    command = [sys.executable, "-m", "app.bench.startup_probe", scene, *options]

    def probe():
        run = subprocess.run(command, cwd=ROOT, check=True, capture_output=True, text=True, timeout=900)
        return json.loads(run.stdout.splitlines()[-1])

    probe()
    load = os.getloadavg()[0]
    runs = sorted((probe() for _ in range(repeats)), key=lambda run: run["total_s"])
    median = runs[len(runs) // 2]
    figures = {key: statistics.median(run[key] for run in runs) for key, value in median.items()
               if isinstance(value, (int, float))}
    return {"scene": scene, "options": list(options), **figures, "slowest": median["slowest"],
            "date": datetime.date.today().isoformat(), "load_average": load}


def first_step_seconds(scene):
    """Seconds from making a Simulation of `scene` (a Scene) to the end of its first step."""
    import fem

    start = time.perf_counter()
    sim = fem.Simulation(scene)
    sim.step()
    return time.perf_counter() - start, sim


def measure(scene_name, repeats=3, cold=True):
    """{"cold_s", "warm_s", "taichi_s", "second_s", "beside_s"}: medians over `repeats` (cold only
    if asked; taichi_s: Taichi's own start, `taichi_seconds`, measured between the warm starts).
    fem.init must have been called (second and beside run in this process)."""
    import scenes

    out = {}
    if cold:
        with tempfile.TemporaryDirectory() as folder:
            out["cold_s"] = statistics.median(process_seconds(scene_name, Path(folder) / f"cold{k}")
                                              for k in range(repeats))
    process_seconds(scene_name)                            # fills the cache where it lacks the scene's kernels
    warm, taichi = [], []
    for _ in range(repeats):              # in turn: both see the same load
        warm.append(process_seconds(scene_name))
        taichi.append(taichi_seconds(1))
    out["warm_s"], out["taichi_s"] = statistics.median(warm), statistics.median(taichi)
    scene = scenes.load_scene(scene_name)
    first_step_seconds(scene)                              # compiles, then the Simulation is dropped
    seconds = []
    for _ in range(repeats):
        elapsed, sim = first_step_seconds(scene)
        seconds.append(elapsed)
        del sim
    out["second_s"] = statistics.median(seconds)
    _, alive = first_step_seconds(scene)
    out["beside_s"], _ = first_step_seconds(scene)
    del alive
    return out


def resting_cost(scene_name="epcot", steps=20):
    """(ms per step with every body asleep, ms per step of the same bodies at rest but awake):
    the scene without its initial conditions and impulses, so nothing moves."""
    from dataclasses import replace

    import fem
    import scenes

    scene = scenes.load_scene(scene_name)
    scene = replace(scene, initial=[], impulses=[])
    costs = []
    for sleep in (True, False):
        sim = fem.Simulation(replace(scene, solver=replace(scene.solver, sleep=sleep)))
        for _ in range(40):                  # long enough to fall asleep (25 quiet steps)
            sim.step()
        assert all(sim.asleep) == sleep
        start = time.perf_counter()
        for _ in range(steps):
            sim.step()
        costs.append(1e3 * (time.perf_counter() - start) / steps)
        del sim
    return tuple(costs)


def view_seconds(scene_name, repeats=3, display=None, timeout=120):
    """{"view_first_s", "view_stepped_s"}: medians over `repeats` warm runs of `main.py view
    SCENE`, seconds from the launch to its first frame (the scene drawn at rest, the window's
    first stats row) and to its first stepped frame (the second row). A first run fills the
    cache. display: an X display; None: $DISPLAY, else a virtual one when Xvfb is installed.
    {} when no window can open here."""
    with _a_display(display) as display:
        if display is None:
            return {}
        env = dict(os.environ, DISPLAY=display)
        runs = [_first_frames(scene_name, env, timeout) for _ in range(repeats + 1)][1:]
    if None in runs:
        return {}
    return {"view_first_s": statistics.median(r[0] for r in runs),
            "view_stepped_s": statistics.median(r[1] for r in runs)}


def _first_frames(scene_name, env, timeout):
    """(seconds to the window's first stats row, to its second), or None when the window ended first."""
    with tempfile.TemporaryDirectory() as folder:
        stats = Path(folder) / "view.jsonl"
        start = time.perf_counter()
        window = subprocess.Popen([sys.executable, str(ROOT / "main.py"), "view", scene_name,
                                   "--stats", str(stats)], cwd=folder, env=env,
                                  stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        seen = []
        try:
            while len(seen) < 2 and time.perf_counter() - start < timeout:
                if window.poll() is not None:
                    return None
                # the window writes its rows straight into the stats file, as they come
                rows = stats.read_text().count("\n") if stats.exists() else 0
                seen += [time.perf_counter() - start] * (min(rows, 2) - len(seen))
                time.sleep(0.005)
        finally:
            window.terminate()
            window.wait(30)
        return tuple(seen) if len(seen) == 2 else None


@contextlib.contextmanager
def _a_display(display):
    """Yields an X display to open windows on: `display`, $DISPLAY, a virtual one, or None."""
    from app.display import display_problem

    if display or display_problem() is None:
        yield display or os.environ.get("DISPLAY")
        return
    if shutil.which("Xvfb") is None:
        yield None
        return
    read, write = os.pipe()
    server = subprocess.Popen(["Xvfb", "-displayfd", str(write), "-screen", "0", "1280x720x24",
                               "-nolisten", "tcp"], pass_fds=[write],
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    os.close(write)
    with os.fdopen(read) as f:
        number = f.readline().strip()
    try:
        yield f":{number}" if number else None
    finally:
        server.terminate()
        server.wait(10)


def refresh_docs():
    """Measure the start-up section of docs/benchmark.json again (what `bench --docs` measures
    under "startup", the rest of the run kept) and render docs/benchmark.md from it:

        python -m app.bench.startup
    """
    import json

    import fem
    from app.bench import report
    from app.bench.plan import full_plan

    plan = full_plan()
    path = report.DOCS / report.DOCS_FILES["json"]
    results = json.loads(path.read_text())
    fem.init("cpu", "f32")
    start = measure(plan.startup)
    start["resting_ms"] = resting_cost(plan.startup)
    start.update(view_seconds(plan.startup))
    start["breakdown"] = [breakdown(scene, options) for scene, options in plan.startup_breakdown]
    results["startup"] = start
    report.write(results, report.DOCS, {"json": report.DOCS_FILES["json"], "md": report.DOCS_FILES["md"]})


if __name__ == "__main__":
    refresh_docs()
