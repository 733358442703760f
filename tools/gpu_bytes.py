"""The bytes a step moves on a GPU, counted by Nsight Compute (issue 36).

Taichi's own profiler counts bytes only through CUPTI, which the PyPI wheel lacks; NVIDIA's
`ncu` counts them from outside. `run` steps a box of tools/gpu_measure.py and lets ncu profile
only its timed steps (cuProfilerStart / cuProfilerStop around them); `table` reads ncu's CSV
and prints each Taichi kernel's launches, time, bytes and bandwidth, and the step's own:

    ncu --profile-from-start off --clock-control none --print-units base --csv \\
        --metrics dram__bytes_read.sum,dram__bytes_write.sum,gpu__time_duration.sum \\
        --log-file ncu.csv python -m tools.gpu_bytes run --k 46 --kind default --steps 3
    python -m tools.gpu_bytes table ncu.csv --steps 3 --device "NVIDIA H100 80GB HBM3" [--ms-per-step 20.1]

ncu runs the kernels one at a time, so the kernels' times are each kernel's alone: the
bandwidth over them is what the kernels achieve. With --ms-per-step (a plain run's median step
time, tools/gpu_measure.py) the table also gives the step's bytes over its whole time.
"""

import argparse
import csv
import ctypes
import dataclasses
import sys
from collections import defaultdict

import taichi as ti

import fem
from app import profile
from tools.gpu_measure import PEAK_GB_S, STEPS, WARMUP, box_simulation

BYTES = ("dram__bytes_read.sum", "dram__bytes_write.sum")
TIME = "gpu__time_duration.sum"
UNITS = {"byte": 1, "kbyte": 1e3, "mbyte": 1e6, "gbyte": 1e9, "nsecond": 1e-9, "ns": 1e-9, "usecond": 1e-6, "us": 1e-6,
         "msecond": 1e-3, "second": 1}


def taichi_kernel(name):
    """A CUDA kernel's Taichi kernel: `cg_iterations_c80_0_kernel_3_range_for` -> cg_iterations."""
    found = profile.TASK_NAME.match(name)
    return found["kernel"] if found else name


def read(path):
    """{ncu's kernel ID: {"kernel", "bytes", "seconds"}} from an ncu --csv log (other lines skipped)."""
    with open(path, newline="") as f:
        lines = [line for line in f if line.startswith('"')]           # ncu's own ==PROF== lines are not CSV
    launches = defaultdict(lambda: {"bytes": 0.0, "seconds": 0.0})
    for row in csv.DictReader(lines):
        metric, unit = row["Metric Name"], row["Metric Unit"].lower()
        if metric not in (*BYTES, TIME):
            continue
        value = float(row["Metric Value"].replace(",", "")) * UNITS[unit]
        launch = launches[row["ID"]]
        launch["kernel"] = taichi_kernel(row["Kernel Name"])
        launch["bytes" if metric in BYTES else "seconds"] += value
    return launches


def table(launches, steps, device="", ms_per_step=None):
    """The per-kernel table (markdown) and the step's bandwidth, from `read`'s launches of `steps` steps."""
    kernels = defaultdict(lambda: {"tasks": 0, "bytes": 0.0, "seconds": 0.0})
    for launch in launches.values():
        k = kernels[launch["kernel"]]
        k["tasks"] += 1
        k["bytes"] += launch["bytes"]
        k["seconds"] += launch["seconds"]
    total_bytes = sum(k["bytes"] for k in kernels.values())
    total_seconds = sum(k["seconds"] for k in kernels.values())
    peak = next((v for key, v in PEAK_GB_S.items() if key in device), None)

    def share(gb_s):
        return f" ({100 * gb_s / peak:.0f} % of {peak:,} GB/s)" if peak else ""

    lines = ["| kernel | tasks/step | ms/step | share | MB/step | GB/s |", "|---|---:|---:|---:|---:|---:|"]
    for name, k in sorted(kernels.items(), key=lambda item: -item[1]["seconds"]):
        gb_s = k["bytes"] / k["seconds"] / 1e9 if k["seconds"] else 0.0
        lines.append(f"| {name} | {k['tasks'] / steps:.1f} | {1e3 * k['seconds'] / steps:.3f} | "
                     f"{100 * k['seconds'] / total_seconds:.1f} % | {k['bytes'] / steps / 1e6:.1f} | {gb_s:.0f} |")
    achieved = total_bytes / total_seconds / 1e9
    lines += ["", f"The step's kernels: {sum(k['tasks'] for k in kernels.values()) / steps:.0f} tasks, "
                  f"{1e3 * total_seconds / steps:.2f} ms and {total_bytes / steps / 1e6:.0f} MB a step: "
                  f"{achieved:.0f} GB/s{share(achieved)}."]
    if ms_per_step:
        whole = total_bytes / steps / (ms_per_step * 1e-3) / 1e9
        lines.append(f"Over the whole step ({ms_per_step:.2f} ms, launches and the host included): "
                     f"{whole:.0f} GB/s{share(whole)}.")
    return "\n".join(lines) + "\n"


def run(k, kind, steps, arch="gpu"):
    """WARMUP steps of the box with k, then `steps` steps of `kind` with ncu profiling on
    (arch cpu: the same steps, nothing profiled: a check of this script)."""
    fem.init(arch, "f32")
    sim = box_simulation(k)
    sim.settings = dataclasses.replace(sim.settings, **STEPS[kind])
    for _ in range(WARMUP):
        sim.step()
    cuda = ctypes.CDLL("libcuda.so.1") if arch != "cpu" else None
    ti.sync()
    started = cuda.cuProfilerStart() if cuda else "cpu"      # 0: CUDA_SUCCESS
    for _ in range(steps):
        sim.step()
    ti.sync()
    if cuda:
        cuda.cuProfilerStop()
    print(f"{sim.model.n_tets:,} tets, {kind}: {steps} steps profiled (cuProfilerStart: {started})", file=sys.stderr)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    commands = parser.add_subparsers(dest="command", required=True)
    stepping = commands.add_parser("run", help="step a box under ncu")
    stepping.add_argument("--k", type=int, default=17, help="the box of 2k x k x k cells (default 17: box50k)")
    stepping.add_argument("--kind", choices=list(STEPS), default="default")
    stepping.add_argument("--steps", type=int, default=3)
    stepping.add_argument("--arch", choices=["gpu", "cpu"], default="gpu")
    reading = commands.add_parser("table", help="read ncu's CSV log")
    reading.add_argument("csv")
    reading.add_argument("--steps", type=float, default=3, help="steps profiled (a run cut short: its tasks over a step's)")
    reading.add_argument("--device", default="")
    reading.add_argument("--ms-per-step", type=float)
    args = parser.parse_args(argv)
    if args.command == "run":
        run(args.k, args.kind, args.steps, args.arch)
    else:
        print(table(read(args.csv), args.steps, args.device, args.ms_per_step))
    return 0


if __name__ == "__main__":
    sys.exit(main())
