"""`--profile`: where a run's time goes, kernel by kernel, from Taichi's kernel profiler.

Taichi compiles each kernel into tasks (one per top-level loop, and serial pieces between
them); each task is one launch on the device, and the profiler times every one. The table
adds them up per kernel:

    kernel | launches | tasks | tasks/step | ms | ms/step | share | bytes | GB/s

launches: calls of the kernel from Python; tasks: the device launches they made; share:
the kernel's time over the profiled steps' wall time, all of them added up (the rest is
Python, launches and waiting; shares therefore add up to at most 100 %); bytes: DRAM traffic, which only CUDA's CUPTI counters can tell (`count_bytes`,
with a Taichi built with CUPTI); elsewhere "n/a".

The profiler waits for every task to end before the next starts, so a profiled step is
somewhat slower than a plain one: read the shares, not the absolute times.
"""

import dataclasses
import re
import statistics

import taichi as ti

# The steps the issue-36 measurements compare: the one-solve step (backward Euler, one PCG
# solve) and the default (trapezoidal, Newton). Settings changed from the scene's.
STEP_KINDS = {"one-solve": {"step": "single", "integrator": "backward-euler"},
              "default": {"step": "newton", "integrator": "auto"}}
# A task's name: "<kernel>_c<id>_<n>_kernel_<task>_<kind>" (Taichi 1.7).
TASK_NAME = re.compile(r"^(?P<kernel>.+?)_c\d+_\d+_kernel_(?P<task>\d+)_")


def _profiler():
    return ti.profiler.kernel_profiler.get_default_kernel_profiler()


def count_bytes():
    """Ask CUDA's CUPTI to count each task's DRAM bytes; False where it cannot (the CPU, or a
    Taichi built without CUPTI: the PyPI wheels). Counting replays every task: time a run
    without it."""
    if ti.lang.impl.current_cfg().arch != ti.cuda:
        return False
    try:
        if not ti.profiler.set_kernel_profiler_toolkit("cupti"):
            return False
        ti.profiler.set_kernel_profiler_metrics([ti.profiler.kernel_metrics.dram_bytes_sum])
    except RuntimeError:                  # a driver or Taichi that refuses CUPTI: no bytes, still times
        ti.profiler.set_kernel_profiler_toolkit("default")
        return False
    return True


def restart():
    """Forget what was profiled so far (the first step's compiling and first touches)."""
    ti.profiler.clear_kernel_profiler_info()


def kernels():
    """{kernel: {"launches", "tasks", "ms", "bytes" (None when not counted)}} since restart()."""
    profiler = _profiler()
    profiler._update_records()            # Taichi's records of every task (no public accessor in 1.7)
    table = {}
    for record in profiler._traced_records:
        match = TASK_NAME.match(record.name)
        name, task = (match["kernel"], int(match["task"])) if match else (record.name, 0)
        row = table.setdefault(name, {"launches": 0, "tasks": 0, "ms": 0.0, "bytes": None})
        row["launches"] += task == 0      # every launch runs its task 0
        row["tasks"] += 1
        row["ms"] += record.kernel_time
        if record.metric_values:          # CUPTI's dram__bytes.sum
            row["bytes"] = (row["bytes"] or 0) + record.metric_values[0]
    return table


def rows(table, steps, wall_ms):
    """The table's rows sorted by time, each with its per-step and share figures; wall_ms: the
    profiled steps' wall time, added up (the kernels ran within it)."""
    out = []
    for name, row in sorted(table.items(), key=lambda item: -item[1]["ms"]):
        out.append({"kernel": name, **row, "tasks_per_step": row["tasks"] / steps,
                    "ms_per_step": row["ms"] / steps, "share": row["ms"] / wall_ms if wall_ms > 0 else 0.0,
                    "gb_per_s": row["bytes"] / row["ms"] / 1e6 if row["bytes"] and row["ms"] > 0 else None})
    return out


def markdown(rows, steps, wall_ms, top=None):
    """The table as markdown, with a total row and the time outside kernels."""
    shown = rows[:top] if top else rows
    lines = ["| kernel | launches | tasks | tasks/step | ms | ms/step | share | bytes | GB/s |",
             "|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in shown:
        lines.append(f"| {r['kernel']} | {r['launches']} | {r['tasks']} | {r['tasks_per_step']:.1f} "
                     f"| {r['ms']:.1f} | {r['ms_per_step']:.3f} | {100 * r['share']:.1f} % "
                     f"| {_bytes(r['bytes'])} | {_figure(r['gb_per_s'], '.0f')} |")
    if len(shown) < len(rows):
        lines.append(f"| ({len(rows) - len(shown)} more kernels) | | | | | | | | |")
    ms = sum(r["ms"] for r in rows)
    counted = [r["bytes"] for r in rows if r["bytes"] is not None]
    total_bytes = sum(counted) if counted else None
    lines.append(f"| all kernels | {sum(r['launches'] for r in rows)} | {sum(r['tasks'] for r in rows)} "
                 f"| {sum(r['tasks'] for r in rows) / steps:.1f} | {ms:.1f} | {ms / steps:.3f} "
                 f"| {100 * ms / wall_ms if wall_ms > 0 else 0:.1f} % | {_bytes(total_bytes)} "
                 f"| {_figure(total_bytes / ms / 1e6 if total_bytes and ms > 0 else None, '.0f')} |")
    if ms <= wall_ms:
        lines.append(f"| outside kernels (Python, launching, waiting) | | | | {wall_ms - ms:.1f} "
                     f"| {(wall_ms - ms) / steps:.3f} | {100 * (wall_ms - ms) / wall_ms:.1f} % | | |")
    else:       # the device's timers and the host's clock disagree: no share can be given
        lines.append(f"| outside kernels: n/a (the kernels' timers add up to {ms:.1f} ms, more than the "
                     f"steps' {wall_ms:.1f} ms of wall time) | | | | | | | | |")
    return "\n".join(lines)


def _bytes(count):
    return "n/a" if count is None else f"{count / 1e6:.1f} MB"


def _figure(value, spec):
    return "n/a" if value is None else format(value, spec)


def profile_steps(sim, kind, warmup, steps):
    """{"rows", "ms_median", "wall_ms", "steps", "tets", "cg_iterations"}: the kernel table of `steps` steps
    of the STEP_KINDS `kind`, from the scene's start after `warmup` steps, and the PCG iterations
    they took (Taichi running with its profiler on)."""
    sim.reset()
    sim.settings = dataclasses.replace(sim.settings, **STEP_KINDS[kind])
    for _ in range(warmup):
        sim.step()
    restart()
    ms, iterations = [], 0
    for _ in range(steps):
        sim.step()
        ms.append(sim.last["wall_ms"])
        iterations += sim.last["solver_iters"]
    return {"rows": rows(kernels(), steps, sum(ms)), "ms_median": statistics.median(ms), "wall_ms": sum(ms),
            "steps": steps,
            "tets": sim.model.n_tets, "cg_iterations": iterations}


def launches_note(table):
    """One line: device tasks per step, and per PCG iteration those of the PCG kernels
    (cg_iterations runs CG_UNROLL iterations a launch, up to SERIAL_UNROLL on a small mesh whose
    loops run on one thread; start_residual once a solve)."""
    per_step = sum(r["tasks"] for r in table["rows"]) / table["steps"]
    cg = sum(r["tasks"] for r in table["rows"] if r["kernel"] == "cg_iterations")
    iterations = table["cg_iterations"]
    return (f"{per_step:.0f} device tasks a step; {iterations / table['steps']:.1f} PCG iterations a step, "
            f"cg_iterations {cg / iterations if iterations else 0:.1f} tasks an iteration")
