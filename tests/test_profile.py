"""`simulate --profile`: a table of kernels whose times add up to the step's, on the CPU."""

import contextlib
import io

import main


def run(*argv):
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main.main(list(argv))
    return code, out.getvalue(), err.getvalue()


def table(text):
    """{kernel: [cells]} of the profile's markdown rows."""
    rows = {}
    for line in text.splitlines():
        cells = [c.strip() for c in line.strip("|").split("|")]
        if line.startswith("| ") and len(cells) == 9 and cells[0] != "kernel":
            rows[cells[0]] = cells[1:]
    return rows


def test_profile_lists_the_solver_kernels_and_their_shares_add_up():
    code, out, err = run("simulate", "cube86", "--steps", "6", "--profile", "--integrator", "backward-euler",
                         "--step", "single")
    assert code == 0, err
    assert "kernel profile of the 5 steps after the first" in out
    rows = table(out)
    assert {"cg_iterations", "start_residual", "extract_rotations"} <= set(rows)
    for name in ("cg_iterations", "start_residual"):
        launches, tasks, per_step = int(rows[name][0]), int(rows[name][1]), float(rows[name][2])
        assert launches >= 5 and tasks >= launches
        assert abs(per_step - tasks / 5) < 0.05
        assert rows[name][6:] == ["n/a", "n/a"]                  # the CPU cannot count bytes
    kernels = [float(cells[5].rstrip(" %")) for name, cells in rows.items()
               if name not in ("all kernels", "outside kernels (Python, launching, waiting)")]
    total = float(rows["all kernels"][5].rstrip(" %"))
    outside = float(rows["outside kernels (Python, launching, waiting)"][5].rstrip(" %"))
    assert abs(sum(kernels) - total) < 0.1 * len(kernels)       # rounding of each row
    assert abs(total + outside - 100) < 0.2
    assert 0 < total <= 100 and outside >= 0                    # the steps' wall time holds their kernels
    # launches per step, per Newton and per PCG iteration, from the table's tasks and the steps' counts
    line = next(line for line in out.splitlines() if line.startswith("launches: "))
    numbers = [float(word) for word in line.replace(",", " ").replace(";", " ").split() if word[0].isdigit()]
    per_step, newton, per_newton, pcg, per_pcg = numbers
    all_tasks, cg_tasks = int(rows["all kernels"][1]), int(rows["cg_iterations"][1])
    assert per_step == round(all_tasks / 5) and newton == 1.0 and per_newton == round(all_tasks / 5)
    assert pcg > 0 and abs(per_pcg - cg_tasks / (5 * pcg)) <= 0.05 * per_pcg + 0.05   # pcg is rounded


def test_profile_of_a_pile_whose_steps_differ_has_no_share_over_100_percent():
    """The shares are of the profiled steps' summed wall time: steps of uneven length (contact)
    cannot make the kernels more than all of it, or the time outside them negative."""
    code, out, err = run("simulate", "examples/pile.toml", "--steps", "4", "--profile")
    assert code == 0, err
    rows = table(out)
    total = float(rows["all kernels"][5].rstrip(" %"))
    outside = float(rows["outside kernels (Python, launching, waiting)"][3])
    assert 0 < total <= 100 and outside >= 0


def test_profile_with_fewer_than_two_steps_says_why_there_is_no_table():
    for steps in ("0", "1"):
        code, out, err = run("simulate", "cube86", "--steps", steps, "--profile")
        assert code == 0, err
        assert f"kernel profile: none, as the run took {steps} step" in out
        assert "--steps 2 or more" in out and not table(out)


def test_without_profile_no_table():
    code, out, err = run("simulate", "cube86", "--steps", "2")
    assert code == 0, err
    assert "kernel profile" not in out


def test_profile_on_a_gpu_backend_without_a_working_profiler_is_an_error_not_a_crash():
    """Taichi 1.7's profiler on Vulkan (Mesa's software llvmpipe here, with its driver installed)
    ended the process with a segmentation fault at the first field written."""
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    run_ = subprocess.run([sys.executable, str(root / "main.py"), "simulate", "cube86", "--steps", "2",
                           "--profile", "--arch", "gpu"], capture_output=True, text=True, timeout=600)
    assert run_.returncode in (0, 2), run_.stderr                   # 0: CUDA, which profiles
    assert "Traceback" not in run_.stderr
    if run_.returncode == 2:
        errors = [line for line in run_.stderr.splitlines() if line.startswith("error: ")]
        assert len(errors) == 1 and ("runs on the CPU and CUDA only" in errors[0] or "no GPU backend" in errors[0])
