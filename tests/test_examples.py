"""The example in examples/ runs as shown in its docstring and plots what it says."""

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_volume_example_plots_linear_growing_and_corotational_kept(tmp_path):
    out = tmp_path / "volume.png"
    run = subprocess.run([sys.executable, str(ROOT / "examples" / "volume_over_time.py"), "cube86",
                          "--steps", "100", "--out", str(out)], capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stderr
    assert out.stat().st_size > 10_000
    ends = {line.split(":")[0]: [float(v) for v in line.split("end ")[1].split(", ")]
            for line in run.stdout.splitlines() if "volume ratio at the end" in line}
    assert max(abs(v - 1) for v in ends["corotational"]) < 0.05      # the cubes only turn
    assert min(ends["linear"]) > 1.1                                  # linear FEM inflates them


def test_volume_example_writes_into_out_not_where_it_is_run(tmp_path):
    run = subprocess.run([sys.executable, str(ROOT / "examples" / "volume_over_time.py"), "cube86", "--steps", "2"],
                         cwd=tmp_path, capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stderr
    assert [p.name for p in tmp_path.iterdir()] == ["out"]
    assert (tmp_path / "out" / "volume_cube86.png").stat().st_size > 1000
