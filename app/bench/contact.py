"""The pile at several sizes, beside a peer: what contact costs as bodies are added, and how close
they come (docs/benchmark.md, "What contact costs").

Piles of N boxes (`pile`): examples/pile.toml's first N boxes, its layers of four repeated upward
past its 20. Each runs `warmup` steps from its start (the boxes fall and land), then `steps` timed
ones, with contact and with it off; the timed steps' positions give the smallest gap between two
bodies and the deepest vertex under the ground (app/bench/gaps.py). The peer, Newton's VBD with
self-contact (app/bench/peer.py), steps the same boxes the same steps, in the Python that
$PEER_PYTHON names, measured the same way. To measure this section again and render
docs/benchmark.md, the rest of docs/benchmark.json kept:

    PEER_PYTHON=/path/to/newton/venv/bin/python python -m app.bench.contact
"""

import datetime
import json
import os
import statistics
import subprocess
import sys
import tempfile
from dataclasses import replace
from pathlib import Path

import numpy as np

import fem
import scenes
from app.bench.gaps import Surfaces
from app.bench.plan import PILE

ROOT = Path(__file__).resolve().parents[2]
LAYER = 4                  # boxes a layer of pile.toml: its four columns
PERIOD = 3                 # its layers' offsets repeat every three layers, PERIOD_HEIGHT higher
PERIOD_HEIGHT = 1.35       # m
PEER_TIMEOUT_S = 3600
# N/m: the peer's contact penalty, each measured: its softbody_gift example's, and one 20 times stiffer
# (at the example's, the 20-box pile's bottom boxes sink about 2 cm into the ground)
PEER_STIFFNESSES = (5e4, 1e6)
# m/s: friction's stick speeds (`[effects] stick_speed`, the default first) the pile of STICK_PILE boxes (or of
# the size measured nearest to it) takes in turn: what holding a body more tightly costs
STICK_SPEEDS = (1e-3, 3e-3, 1e-2)
STICK_PILE = 20
PEER_INSTALL = ("not measured: set PEER_PYTHON to a Python with Newton's `newton` package "
                "(`python -m venv peer && peer/bin/pip install newton`)")


def pile(n):
    """A Scene of n boxes: pile.toml's first n, or its 20 and more above them, each box
    LAYER * PERIOD boxes before it lifted PERIOD_HEIGHT (tests/test_bench_contact.py checks that
    pile.toml's own boxes follow that rule)."""
    template = scenes.load_scene(PILE)
    bodies = list(template.bodies[:n])
    while len(bodies) < n:
        below = bodies[len(bodies) - LAYER * PERIOD]
        lifted = replace(below.mesh, vertices=below.mesh.vertices + (0.0, PERIOD_HEIGHT, 0.0))
        bodies.append(replace(below, name=f"box{len(bodies)}", mesh=lifted))
    return replace(template, name=f"pile of {n}", bodies=bodies)


def mesh(scene):
    """(tets (m, 4), body (n,)): the scene's boxes as one mesh, vertex ids in the order the
    Simulation numbers them (body by body)."""
    counts = [len(b.mesh.vertices) for b in scene.bodies]
    starts = np.cumsum([0] + counts[:-1])
    return (np.concatenate([b.mesh.tets + s for b, s in zip(scene.bodies, starts)]),
            np.repeat(np.arange(len(counts)), counts))


def closeness(surfaces, positions, ground):
    """{"gap": the smallest over the steps (m, None if no two bodies came near), "crossed_steps": the
    steps with a vertex inside another body, "sunk": the deepest under the ground (m)} of
    `positions` (steps, n, 3)."""
    each = [surfaces.measure(x, ground) for x in positions]
    gaps = [m["gap"] for m in each if m["gap"] is not None]
    return {"gap": min(gaps) if gaps else None, "crossed_steps": sum(m["crossed"] for m in each),
            "sunk": max(m["sunk"] for m in each)}


def ours(scene, warmup, steps):
    """{"on", "off"}: the scene's timed steps with contact and with it off, each {"ms_median",
    "newton", "cg" (means a step), "unconverged"}; "on" also its closeness."""
    on, positions = timed(scene, warmup, steps)
    on.update(closeness(Surfaces(*mesh(scene)), positions, scene.effects.ground))
    off, _ = timed(replace(scene, effects=replace(scene.effects, contact=None)), warmup, steps)
    return {"on": on, "off": off}


def timed(scene, warmup, steps):
    """({"ms_median", "newton", "cg" (means a step), "unconverged"}, positions (steps, n, 3)): the
    scene's `steps` timed steps after `warmup` steps from its start."""
    sim = fem.Simulation(scene)
    for _ in range(warmup):
        sim.step()
    rows, positions = [], []
    for _ in range(steps):
        rows.append(sim.step())
        positions.append(sim.positions())
    return ({"ms_median": statistics.median(row["wall_ms"] for row in rows),
             "newton": float(np.mean([row["newton_iters"] for row in rows])),
             "cg": float(np.mean([row["solver_iters"] for row in rows])),
             "unconverged": sum(not row["converged"] for row in rows)}, np.array(positions))


def stick_speeds(n, warmup, steps):
    """{"bodies": n, "rows": [{"stick_speed" (m/s), timed's figures}]}: the pile of n boxes at each of
    STICK_SPEEDS."""
    scene = pile(n)
    return {"bodies": n, "rows": [{"stick_speed": speed, **timed(replace(scene, effects=replace(
        scene.effects, stick_speed=speed)), warmup, steps)[0]} for speed in STICK_SPEEDS]}


def peer(scene, warmup, steps, python, stiffness):
    """The peer's steps of the scene (app/bench/peer.py, in `python`) with a contact penalty of
    `stiffness` N/m: ({"ms_median", closeness}, what the peer says of itself: its versions,
    sub-steps, iterations)."""
    tets, body = mesh(scene)
    e, material = scene.effects, scene.bodies[0].material
    with tempfile.TemporaryDirectory() as folder:
        source, target = Path(folder) / "in.npz", Path(folder) / "out.npz"
        np.savez(source, vertices=np.concatenate([b.mesh.vertices for b in scene.bodies]), tets=tets, body=body,
                 dt=scene.solver.dt, warmup=warmup, steps=steps, E=material.E, nu=material.nu,
                 density=material.density, beta=e.beta, gravity=np.array(e.gravity, float), ground=e.ground,
                 ground_friction=e.friction, distance=e.contact.distance, friction=e.contact.friction,
                 contact_stiffness=stiffness)
        run = subprocess.run([python, "-m", "app.bench.peer", str(source), str(target)], cwd=ROOT, check=True,
                             capture_output=True, text=True, timeout=PEER_TIMEOUT_S)
        info = json.loads(run.stdout.splitlines()[-1])      # Warp prints its own lines before
        positions = np.load(target)["positions"]
    ms = info.pop("ms")
    return {"ms_median": statistics.median(ms), **closeness(Surfaces(tets, body), positions, e.ground)}, info


def scaling(sizes, warmup, steps, peer_python=None):
    """{"sizes", "warmup", "steps", "load_average" (at the start and the end), "date", "distance",
    "ours": [{"bodies", "vertices", "on", "off"}], "peer": {"rows": [{"bodies", "contact_stiffness",
    "ms_median", closeness}], "setup"}, or a line saying why it is not measured}.
    Taichi must run (fem.init), its profiler off: these are the times a user sees."""
    out = {"sizes": list(sizes), "warmup": warmup, "steps": steps, "load_average": [os.getloadavg()[0]],
           "date": datetime.date.today().isoformat(), "distance": pile(1).effects.contact.distance}
    out["ours"] = []
    for n in sizes:
        print(f"contact: a pile of {n} boxes", file=sys.stderr)
        out["ours"].append({"bodies": n, "vertices": sum(len(b.mesh.vertices) for b in pile(n).bodies),
                            **ours(pile(n), warmup, steps)})
    n = min(sizes, key=lambda size: abs(size - STICK_PILE))
    print(f"contact: stick speeds, a pile of {n} boxes", file=sys.stderr)
    out["stick_speeds"] = stick_speeds(n, warmup, steps)
    out["peer"] = PEER_INSTALL
    if peer_python:
        print(f"contact: the peer, {len(sizes) * len(PEER_STIFFNESSES)} runs", file=sys.stderr)
        try:
            runs = {(n, k): peer(pile(n), warmup, steps, peer_python, k) for n in sizes for k in PEER_STIFFNESSES}
        except subprocess.CalledProcessError as failed:      # one line of why, and the rest still reported
            out["peer"] = f"not measured: {peer_python} -m app.bench.peer failed ({failed.stderr.strip()[-300:]})"
        except subprocess.TimeoutExpired:
            out["peer"] = f"not measured: the peer ran past {PEER_TIMEOUT_S} s"
        else:
            out["peer"] = {"rows": [{"bodies": n, "contact_stiffness": k, **row} for (n, k), (row, _) in runs.items()],
                           "setup": next(iter(runs.values()))[1]}
    out["load_average"].append(os.getloadavg()[0])
    return out


def refresh_docs():
    """Measure the contact section of docs/benchmark.json again (what `bench --docs` measures under
    "contact", the rest of the run kept) and render docs/benchmark.md from it."""
    from types import SimpleNamespace

    from app.bench import report
    from app.bench.measure import contact_cost, machine
    from app.bench.plan import full_plan

    plan = full_plan()
    path = report.DOCS / report.DOCS_FILES["json"]
    results = json.loads(path.read_text())
    args = SimpleNamespace(arch="cpu", precision="f32", debug=False)
    backend = fem.init(args.arch, args.precision)
    info = machine(backend, args.precision)
    results["contact"] = contact_cost(plan.contact, plan, args, info)
    fem.init(args.arch, args.precision)                     # the profiler off again
    results["contact"]["scaling"] = scaling(plan.contact_sizes, *plan.contact_steps, os.environ.get("PEER_PYTHON"))
    results["plan"]["contact_sizes"] = list(plan.contact_sizes)
    report.write(results, report.DOCS, {"json": report.DOCS_FILES["json"], "md": report.DOCS_FILES["md"]})


if __name__ == "__main__":
    refresh_docs()
