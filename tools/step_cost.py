"""ms per step and Newton iterations per step of the default (Newton) step and the one-solve
step, at dt 0.02 s, on epcot, cube86 and box50k (the numbers issue 10 asks for).

    python -m tools.step_cost [--steps N] [--precision f32|f64] [SCENE ...]    # from the repository's root
"""

import argparse
import statistics

import fem
from app.bench.plan import make_scene


def measure(name, step, steps):
    sim = fem.Simulation(make_scene(name), step=step, dt=0.02)
    for _ in range(3):                                   # compile and warm up
        sim.step()
    sim.reset()
    infos = [sim.step() for _ in range(steps)]
    return {"ms": statistics.median(i["wall_ms"] for i in infos),
            "newton": statistics.mean(i["newton_iters"] for i in infos),
            "cg": statistics.mean(i["solver_iters"] for i in infos),
            "halvings": sum(i["line_search_steps"] for i in infos),
            "limited": sum(i["energy_limited"] for i in infos)}


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scenes", nargs="*", default=["epcot", "cube86", "box50k"])
    parser.add_argument("--steps", type=int, default=50)
    parser.add_argument("--precision", default="f32")
    args = parser.parse_args()
    fem.init("cpu", args.precision)
    print("| scene | step | ms/step (median) | Newton iters/step | CG iters/step | halvings | energy-limited |")
    print("|---|---|---:|---:|---:|---:|---:|")
    for name in args.scenes:
        for step in ("newton", "single"):
            r = measure(name, step, args.steps)
            print(f"| {name} | {step} | {r['ms']:.1f} | {r['newton']:.2f} | {r['cg']:.1f} | {r['halvings']} "
                  f"| {r['limited']} |", flush=True)


if __name__ == "__main__":
    main()
