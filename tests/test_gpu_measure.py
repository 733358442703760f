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


NCU_CSV = '''==PROF== Connected to process 7 (/usr/bin/python3)
"ID","Process ID","Process Name","Host Name","Kernel Name","Context","Stream","Block Size","Grid Size","Device","CC","Section Name","Metric Name","Metric Unit","Metric Value"
{rows}==PROF== Disconnected from process 7
'''


def ncu_rows(launch, kernel, read, written, time, time_unit="nsecond"):
    row = f'"{launch}","7","python3","host","{kernel}","1","7","(128, 1, 1)","(64, 1, 1)","0","9.0","Command line profiler metrics",'
    return "".join(row + f'"{metric}","{unit}","{value}"\n' for metric, unit, value in
                   (("dram__bytes_read.sum", "byte", read), ("dram__bytes_write.sum", "byte", written),
                    ("gpu__time_duration.sum", time_unit, time)))


def test_gpu_bytes_reads_what_ncu_counted_per_taichi_kernel(tmp_path):
    """tools/gpu_bytes.py: bytes and times from ncu's CSV (thousands separators, units), summed per
    Taichi kernel over its tasks, and the step's bandwidth against the device's peak."""
    from tools import gpu_bytes
    log = tmp_path / "ncu.csv"
    log.write_text(NCU_CSV.format(rows=ncu_rows(0, "cg_iterations_c80_0_kernel_3_range_for", "2,000,000", "1,000,000", "1,500")
                                  + ncu_rows(1, "cg_iterations_c80_0_kernel_4_range_for", "1,000,000", "0", "1,000")
                                  + ncu_rows(2, "after_step_c90_1_kernel_0_range_for", "500", "500", "0.5", "usecond")))
    launches = gpu_bytes.read(log)
    assert [launch["kernel"] for launch in launches.values()] == ["cg_iterations", "cg_iterations", "after_step"]
    assert launches["2"] == {"kernel": "after_step", "bytes": 1000.0, "seconds": 5e-7}
    text = gpu_bytes.table(launches, steps=2, device="NVIDIA H100 80GB HBM3", ms_per_step=0.01)
    # cg_iterations: 4 MB in 2.5 us over 2 steps: 2 MB and 0.00125 ms a step, 1600 GB/s
    assert "| cg_iterations | 1.0 | 0.001 | 83.3 % | 2.0 | 1600 |" in text
    # all: 4.001 MB in 3 us: 1334 GB/s, 40 % of the H100's 3,350; over 0.01 ms steps 200 GB/s, 6 %
    assert "1334 GB/s (40 % of 3,350 GB/s)" in text
    assert "200 GB/s (6 % of 3,350 GB/s)" in text
    # its stepping half, on the CPU (nothing profiled there): the box builds and steps
    run = subprocess.run([sys.executable, "-m", "tools.gpu_bytes", "run", "--k", "3", "--arch", "cpu", "--steps", "1"],
                         cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert run.returncode == 0 and "270 tets, default: 1 steps profiled" in run.stderr, run.stderr


def test_gpu_tune_times_each_setting_on_a_solver_built_with_it(tmp_path):
    """tools/gpu_tune.py, its docstring's CPU command: the defaults, then each setting, on a box."""
    out = tmp_path / "tune.json"
    run = subprocess.run([sys.executable, "-m", "tools.gpu_tune", str(out), "--arch", "cpu", "--sizes", "2",
                          "--steps", "1", "CHUNK=16,CG_UNROLL=3,GPU_GRID_BLOCKS=512"], cwd=ROOT, capture_output=True, text=True, timeout=900)
    assert run.returncode == 0, run.stderr
    results = json.loads(out.read_text())
    assert [case["setting"] for case in results["cases"]] == [{}, {"CHUNK": 16, "CG_UNROLL": 3, "GPU_GRID_BLOCKS": 512}]
    assert results["defaults"]["CG_UNROLL"] == 2 and results["defaults"]["GPU_CHUNK"] == 32
    assert results["defaults"]["GPU_GRID_BLOCKS"] == 2048 and results["defaults"]["GPU_CAPACITY_LOOPS"] == 0
    for case in results["cases"]:
        assert case["tets"] == 80 and case["one-solve"]["ms_median"] > 0 and case["default"]["cg_per_step"] >= 1
    assert run.stdout.splitlines()[1].startswith("CHUNK=16 CG_UNROLL=3 GPU_GRID_BLOCKS=512 | 80 | one-solve ")
    bad = subprocess.run([sys.executable, "-m", "tools.gpu_tune", str(out), "--arch", "cpu", "CHUNKS=3"],
                         cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert bad.returncode != 0 and "error: unknown tunable ['CHUNKS']" in bad.stderr
    for setting, said in (("GPU_GRID_BLOCKS=-1", "GPU_GRID_BLOCKS=-1: must be 0 (Taichi's own grid) or a positive integer"),
                          ("GPU_CAPACITY_LOOPS=-1", "GPU_CAPACITY_LOOPS=-1: must be 0 (off) or a positive integer"),
                          ("CHUNK=0", "CHUNK=0: must be a positive integer")):
        bad = subprocess.run([sys.executable, "-m", "tools.gpu_tune", str(tmp_path / "no.json"), "--arch", "cpu", setting],
                             cwd=ROOT, capture_output=True, text=True, timeout=300)
        assert (bad.returncode, bad.stderr.strip()) == (2, f"error: {said}")
        assert not (tmp_path / "no.json").exists()
