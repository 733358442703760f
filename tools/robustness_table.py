"""Write docs/robustness.md: what the program does with every hard case and bad input.

    .venv/bin/python -m tools.robustness_table            # from the repository's root: a few minutes on two CPU cores

The cases come from scenes/hard_cases.py and tests/cases.py, the same lists the tests check,
so the table stays true.
"""

import contextlib
import io
import sys
import tempfile
from pathlib import Path

import numpy as np

import fem
from scenes.hard_cases import ENERGY_DTS, ENERGY_STEPS, ENERGY_TOLERANCE, GROUND_STEPS, HARD_CASES, METHODS, groups
from fem.scene import INTEGRATORS
from tests.cases import (BAD_INPUTS, CLI_HARD_CASES, ROOT, energy_history, forced_failures, ground_history,
                         run_bad_input, run_cli_case, run_hard_cases)
from tests.hostile import HOSTILE, run_hostile

PRECISIONS = ("f32", "f64")
OUT = ROOT / "docs" / "robustness.md"


def hard_case_rows():
    results = {}
    for precision in PRECISIONS:
        fem.init("cpu", precision)
        for group in groups():
            print(f"{precision}: {', '.join(case.name for case in group)}", file=sys.stderr)
            for o in run_hard_cases(group):
                results[o.case.name, o.method, precision] = o
    rows = []
    for case in HARD_CASES:
        for method in METHODS:
            cells = []
            for precision in PRECISIONS:
                o = results[case.name, method, precision]
                cells.append(f"{o.summary()} (max {o.energy_max:.3g}); max {o.max_iterations} CG iterations "
                             f"in a step, {o.unconverged_steps} steps not converged, {o.rejected_steps} rejected")
            rows.append(f"| {case.name} | {case.what}; dt {case.dt:g} s x {case.steps} | {method} | "
                        + " | ".join(cells) + " |")
    return rows


def energy_rows():
    """Per dt, precision and integrator: the largest rise of any case's total energy in one step,
    relative to its starting energy (negative: it only fell), which case came closest, and how
    many steps needed the energy safeguard. First the free hard cases, then the ground drops."""
    rows = {"free": [], "ground": []}
    for precision in PRECISIONS:
        fem.init("cpu", precision)
        for dt in ENERGY_DTS:
            for integrator in INTEGRATORS:
                print(f"{precision}: energy at dt {dt:g}, {integrator}", file=sys.stderr)
                for kind, (layout, energies, infos) in (("free", energy_history(dt, integrator=integrator)),
                                                        ("ground", ground_history(dt, integrator))):
                    rise = np.diff(energies, axis=0).max(axis=0) / np.abs(energies).max(axis=0)
                    worst = int(np.argmax(rise))
                    case, method, _ = layout[worst]
                    name = getattr(case, "name", case)
                    limited = sum(info["energy_limited"] > 0 for info in infos)
                    converged = sum(info["converged"] for info in infos)
                    rows[kind].append(
                        f"| {dt:g} | {precision} | {integrator} | {rise[worst]:.2g} ({name}, {method}) | "
                        f"{ENERGY_TOLERANCE[precision]:g} | {'yes' if rise.max() <= ENERGY_TOLERANCE[precision] else 'NO'}"
                        f" | {limited} of {len(infos)} | {converged} of {len(infos)} |")
    return rows


def forced_rows():
    rows = []
    for precision in PRECISIONS:
        fem.init("cpu", precision)
        stderr = io.StringIO()

        def capture():
            text = stderr.getvalue()
            stderr.seek(0)
            stderr.truncate()
            return text

        with contextlib.redirect_stderr(stderr):
            r = forced_failures(capture)
        capped = r["capped"][-1]
        warning = r["stderr"].strip().splitlines()
        rows.append(f"| solve capped at 2 iterations (tolerance 1e-12) | {precision} | every step reports "
                    f"`solver_iters` {capped['solver_iters']}, `converged` {capped['converged']}, "
                    f"`residual` {capped['residual']:.2g} |")
        rows.append(f"| NaN written into a velocity, 3 steps | {precision} | steps rejected: "
                    f"{[not i['finite'] for i in r['nan']]}, positions unchanged: "
                    f"{bool((r['after'] == r['before']).all())}, stderr ({len(warning)} line): "
                    f"`{warning[0] if warning else ''}` |")
    return rows


def cli_rows():
    rows = []
    for method, precision in CLI_HARD_CASES:
        with tempfile.TemporaryDirectory() as folder:
            run = run_cli_case(method, precision, folder)
        summary = run.stdout.strip().splitlines()
        rows.append(f"| `simulate extremes.toml --steps 10 --precision {precision}`, {method} | "
                    f"exit {run.returncode}; {'; '.join(summary[-2:])} |")
    return rows


def bad_input_rows():
    rows = []
    for case in BAD_INPUTS:
        with tempfile.TemporaryDirectory() as folder:
            code, stderr = run_bad_input(case, folder)
        line = stderr.strip().replace("|", "\\|")
        rows.append(f"| {case.name} | `simulate {' '.join(case.args)}` | {code} | `{line}` |")
    return rows


def hostile_rows():
    """(rows of every hostile case, rows of the count per class with the exit codes seen)."""
    rows, seen = [], {}
    for case in HOSTILE:
        with tempfile.TemporaryDirectory() as folder:
            code, stderr = run_hostile(case, folder)
        # Paths as a user would see them from the folder, not this machine's temporary names.
        stderr = stderr.replace(str(Path(folder).resolve()) + "/", "").replace(folder + "/", "")
        stderr = stderr.replace(str(ROOT) + "/", "")
        lines = stderr.strip().splitlines()
        line = (lines[-1] if lines else "").replace("|", "\\|")
        shown = line if len(line) <= 160 else line[:160] + "..."
        rows.append(f"| {case.kind} | {case.name} | {code} | `{shown}` |")
        seen.setdefault(case.kind, []).append(code)
    counts = [f"| {kind} | {len(codes)} | {', '.join(f'{codes.count(c)} x exit {c}' for c in sorted(set(codes)))} |"
              for kind, codes in seen.items()]
    return rows, counts


# What the tests run as separate processes (signals, pipes, two runs at once, a mounted disk):
# the classes and what the program does, with the test that checks each.
PROCESS_CLASSES = [
    ("two exports at once, same --video", "the first to finish puts its video in place; the other exits 2, "
     "its video kept beside it as v-2.mp4; neither claims the other's file", "test_outputs.py"),
    ("--out another export is writing", "refused: exit 2, `another run is writing into this folder`", "test_outputs.py"),
    ("--overwrite over a folder with other files", "replaces frame_00000 .. frame_{N-1} only; older frames and "
     "other files are left, and a note says so", "test_outputs.py"),
    ("full disk (a 64 kB tmpfs, and a writer raising ENOSPC)", "exit 2, `PATH: no space left on device; kept the "
     "N complete rows` (or frames, and the video closed on them)", "test_outputs.py"),
    ("a killed run's `.NAME.PID.xxxx.softfem-part` files", "removed by the next run into the folder (their process is "
     "gone, or the id is now another process's, started later); they never make a folder count as non-empty",
     "test_outputs.py"),
    ("a killed run's stats rows (SIGKILL)", "the next run to the same file keeps them beside it as s-2.jsonl, "
     "with a note", "test_hostile_outputs.py"),
    ("a user's `.thesis.2023.part`, `.x.99999999999999999999.part` beside the frames or video",
     "kept: only names with this program's marker and a process id that is gone are removed", "test_hostile_outputs.py"),
    ("SIGHUP, SIGQUIT, SIGUSR1/2, SIGALRM, SIGXCPU", "as SIGTERM: exit 130, the complete rows in the real file "
     "(not a hidden temporary one), as many video frames as PNGs; under `nohup` SIGHUP is ignored",
     "test_hostile_outputs.py"),
    ("an MP4 the encoder left without its index, a GIF on a full disk", "exit 2, `the video was not written; kept "
     "the N complete frames`; nothing broken put in place", "test_hostile_outputs.py"),
    ("stdout on /dev/full (simulate, scenes, help, export -h, --version)", "exit 2, `error: standard output: no space "
     "left on device`", "test_hostile_outputs.py"),
    ("`--stats /dev/stdout > log.txt`", "exit 2: a file this run already has open; give - for standard output "
     "(never a file of its own in place of /dev/stdout)", "test_hostile_outputs.py"),
    ("two or three SIGTERMs 5 ms apart", "exit 130, complete rows kept; later signals are ignored",
     "test_outputs.py"),
    ("`simulate --stats - \\| head -c 100`", "stops quietly, exit 141 (128 + SIGPIPE), no traceback",
     "test_outputs.py"),
    ("a poisoned cache entry (vertex index -1408)", "rebuilt: entries carry a checksum and are checked like a "
     "mesh file", "test_trust.py"),
    ("TI_ARCH=opengl or xyz with --arch cpu", "a warning that TI_ARCH is ignored; runs on the CPU, exit 0",
     "test_trust.py"),
    ("TI_CPU_MAX_NUM_THREADS=abc", "exit 2, `Taichi cannot start with the environment variables ...`",
     "test_trust.py"),
    ("fuzzed TOML scene values and --set values (hypothesis, 600 examples)", "a Scene or one FemError",
     "test_fuzz_scenes.py"),
]


def main():
    hostile, hostile_counts = hostile_rows()
    bad = bad_input_rows()
    hard = hard_case_rows()
    energy = energy_rows()
    forced = forced_rows()
    cli = cli_rows()
    text = f"""# Robustness: what softfem does with hard cases and bad input

Generated by `.venv/bin/python -m tools.robustness_table` from the case lists in `scenes/hard_cases.py` and
`tests/cases.py`, the same lists that `tests/test_hard_cases.py` and `tests/test_bad_input.py` check.
Do not edit by hand.

## Hard cases

Every case runs with linear and with corotational bodies, in f32 and f64, Rayleigh damping
alpha = beta = 0.1, PCG tolerance 1e-4, at most 400 CG iterations per linear solve (one each
Newton iteration). Energy is kinetic + elastic (J) at the start and the end; "inverted" counts
tets with det F <= 0; "volume" is the final volume over the rest volume of each body. Iteration
counts are for the whole shared solve (cases with the same dt run as bodies of one scene).

| case | what | method | f32 | f64 |
|---|---|---|---|---|
{chr(10).join(hard)}

Very soft bodies (E = 10 Pa) and bodies hit by a 1e5 m/s impulse can stay inverted at the end
of the run (the tests only require finite positions and falling energy for them). Convergence
is tested per body, so the huge-impulse body shares its solve with the quiet ones.

## Total energy never rises

Every hard case, both methods, {ENERGY_STEPS} steps at each time step and with each integrator,
all in one scene per dt, precision and integrator. The column "largest rise" is the largest
increase of a case's total energy (kinetic + elastic + gravitational) from one step to the
next, over its largest energy; negative means it only fell. `tests/test_energy.py` requires
it below the tolerance. "Safeguard" counts the steps in which the energy safeguard
(`limit_energy`, docs/method.md section 6) had to trim some body's rise: the step itself did
not keep the promise there. "Converged" counts the steps in which every body met the
gradient tolerance.

| dt (s) | precision | integrator | largest rise (closest case) | tolerance | kept | safeguard | converged |
|---|---|---|---|---|---|---|---|
{chr(10).join(energy["free"])}

### Dropped and spun onto the ground

`scenes/hard_cases.py: ground_scene`: 0.5 m cubes of E 1e3 Pa (nu 0.3 and 0.49995), 5e4 Pa
(nu 0.49995) and 1e9 Pa (nu 0.3 and 0.49995), linear and corotational, falling at 2 m/s and
spinning at 3 rad/s onto the ground under gravity, without damping, friction 0.5
({", ".join(f"{n} steps at dt {dt:g} s" for dt, n in GROUND_STEPS.items())}). Total energy here
includes the ground's contact energy. The stiff, near-incompressible corotational cube rarely
meets the gradient tolerance, and as it shares each solve, the scene's steps rarely count as
converged.

| dt (s) | precision | integrator | largest rise (closest case) | tolerance | kept | safeguard | converged |
|---|---|---|---|---|---|---|---|
{chr(10).join(energy["ground"])}

## Forced solver failures

| what | precision | result |
|---|---|---|
{chr(10).join(forced)}

## Through the command line

`extremes.toml`: nu = 0.4999, E = 1e9 and E = 10 Pa cubes, 1e5 m/s impulses on two of them, dt 0.5 s.

| command | result |
|---|---|
{chr(10).join(cli)}

## Hostile input

What a hostile user would try (`tests/hostile.py`, checked by `tests/test_hostile.py`): each runs
`.venv/bin/python main.py ARGS` in a folder holding only its files. Sizes are checked from the
description before anything is allocated (peak memory of the largest refused description, a box
of 2000^3 cells or 10,000 bodies: about 150 MB, the program's own imports); `--allow-large`
lifts the size limits, not the ranges of numbers.

| class | tried | exit codes |
|---|---|---|
{chr(10).join(hostile_counts)}

| class | input | exit | stderr (last line) |
|---|---|---|---|
{chr(10).join(hostile)}

Checked by the tests as separate processes:

| class | what the program does | test |
|---|---|---|
{chr(10).join(f"| {what} | {does} | `tests/{test}` |" for what, does, test in PROCESS_CLASSES)}

## Bad input

Each runs `.venv/bin/python main.py simulate ARGS` in a folder holding only the listed case's files;
the program prints one line on stderr and exits with code 2 (a traceback only with `--debug`).

| input | command | exit | stderr |
|---|---|---|---|
{chr(10).join(bad)}
"""
    OUT.parent.mkdir(exist_ok=True)
    OUT.write_text(text)
    print(f"wrote {OUT.relative_to(ROOT)}", file=sys.stderr)


if __name__ == "__main__":
    main()
