"""tools/gpu_measure.py, the script the GPU measurement runs, at tiny sizes on the CPU: every
case timed, both steps, the kernel tables of two sizes, the numbers in OUT.json."""

import json
import subprocess
import sys

from tests.test_cli import ROOT


def test_gpu_measure_runs_on_the_cpu_at_tiny_sizes(tmp_path):
    out = tmp_path / "gpu.md"
    run = subprocess.run([sys.executable, "-m", "tools.gpu_measure", str(out), "--arch", "cpu", "--quick"],
                         cwd=ROOT, capture_output=True, text=True, timeout=900)
    assert run.returncode == 0, run.stderr
    results = json.loads(out.with_suffix(".json").read_text())
    assert [case["tets"] for case in results["cases"]] == [10 * k ** 3 for k in (3, 4, 5, 6)]
    for case in results["cases"]:
        for kind in ("one-solve", "default"):
            assert 0 < case[kind]["ms_min"] <= case[kind]["ms_median"] <= case[kind]["ms_max"]
            assert case[kind]["cg_per_step"] >= 1
    assert list(results["profiles"]) == ["box k = 3 (270 tets)", "box k = 5 (1,250 tets)"]
    for kinds in results["profiles"].values():
        for kind, table in kinds.items():
            names = {row["kernel"] for row in table["rows"]}
            assert {"cg_iterations", "extract_rotations"} <= names, kind
            assert all(row["bytes"] is None for row in table["rows"])        # no byte counters on a CPU
    text = out.read_text()
    assert text.count("| one-solve |") == 4 and text.count("| default |") == 4
    assert text.count("## Kernel profile") == 4
    assert "n/a (bytes need CUPTI" in text
    assert text.count("Launches: ") == 4 and "tasks an iteration" in text
