"""First against second order: each integrator's position error against dt, and its observed order.

A free 2 x 0.5 x 0.5 m bar (E 2 kPa: soft enough that dt 0.02 s resolves its fastest mode)
spins and twists for 0.4 s; each integrator runs at DTS and at REFERENCE_DT, and its error at
a dt is the largest distance of a vertex from its own reference run. The slope of log error
against log dt is the observed order: 1 for backward Euler, 2 for BDF2 and the trapezoidal rule
(`main.py figures --only integrator_order`; docs/experiments.md, experiment 9).
"""

import math

import numpy as np

import fem
from assets.generators import box
from fem.scene import Body, Material, Scene, SolverSettings

DTS = (0.02, 0.01, 0.005)       # s
REFERENCE_DT = 0.00125          # s: the same integrator, 16 times finer than the coarsest
SECONDS = 0.4
INTEGRATORS = {"backward-euler": "backward Euler", "bdf2": "BDF2", "trapezoidal": "trapezoidal"}
GUIDES = (("backward-euler", 1), ("bdf2", 2))   # the slopes drawn, each through one integrator's coarsest point


def twisting_state(dt, integrator, tolerance=1e-10, step="newton"):
    """(scene, x, v): the spinning, twisting bar at dt, its state at t = 0 (fem.init first)."""
    mesh = box(size=(2.0, 0.5, 0.5), cells=(4, 1, 1), split=6)
    solver = SolverSettings(dt=dt, integrator=integrator, step=step, tolerance=tolerance, newton_tolerance=1e-12,
                            max_newton=100, max_iterations=1000, sleep=False)
    scene = Scene("twisting bar", [Body("bar", mesh, Material(2e3, 0.3, 1000.0), "corotational")], solver=solver)
    x = mesh.vertices.astype(np.float64)
    v = np.cross([1.0, 2.0, 0.0], x - x.mean(0)) + np.cross([3.0, 0.0, 0.0], x) * x[:, :1]
    return scene, x, v - v.mean(0)


def twisting_bar(dt, integrator, step="newton"):
    """Positions (n, 3) of the spinning, twisting bar after SECONDS at dt (fem.init first)."""
    scene, x, v = twisting_state(dt, integrator, step=step)
    sim = fem.Simulation(scene)
    sim.set_state(x, v)
    for _ in range(round(SECONDS / dt)):
        sim.step()
    return sim.positions()


def observed_order(step="newton", integrators=tuple(INTEGRATORS)):
    """{integrator: {"dt": [...], "error": [...] (m), "slopes": [...]}}, each integrator's `step`
    against its own converged (Newton) run at REFERENCE_DT, in float64: in f32 each step of the
    reference stops at the round-off floor of the convergence test, and over its 320 steps that
    adds up to about 1e-4 m, more than the trapezoidal rule's error at dt 0.005 s. Taichi
    restarts in f64 for it and back, which ends every Simulation made before."""
    arch, precision, debug = fem.runtime.requested() or ("cpu", "f32", False)
    if precision == "f64":
        return measured_order(step, integrators)
    fem.init(arch, "f64", debug=debug)
    try:
        return measured_order(step, integrators)
    finally:
        fem.init(arch, precision, debug=debug)


def measured_order(step, integrators):
    out = {}
    for integrator in integrators:
        reference = twisting_bar(REFERENCE_DT, integrator)
        errors = [float(np.abs(twisting_bar(dt, integrator, step) - reference).max()) for dt in DTS]
        out[integrator] = {"dt": list(DTS), "error": errors,
                           "slopes": [math.log2(a / b) for a, b in zip(errors, errors[1:])]}
    return out


def order_figure(size, dpi):
    """(save(file), numbers): the log-log plot of error against dt, with slopes 1 and 2 drawn."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    numbers = observed_order()
    fig, ax = plt.subplots(figsize=size)
    for (integrator, label), colour in zip(INTEGRATORS.items(), ("C3", "C0", "C2")):
        run = numbers[integrator]
        slopes = ", ".join(f"{s:.2f}" for s in run["slopes"])
        ax.loglog(run["dt"], run["error"], "-o", color=colour, label=f"{label}: slopes {slopes}")
        for order, style in ((1, ":"), (2, "--")):
            if (integrator, order) in GUIDES:                       # a guide through its coarsest point
                guide = [run["error"][0] * (dt / DTS[0]) ** order for dt in DTS]
                ax.loglog(DTS, guide, style, color="grey", lw=1, label=f"slope {order}")
    ax.set_xlabel("time step dt (s)")
    ax.set_ylabel("largest position error (m)")
    ax.set_title(f"a spinning, twisting bar after {SECONDS:g} s, against the same integrator at "
                 f"dt {REFERENCE_DT:g} s (float64)", fontsize=9)
    ax.legend(fontsize=7)

    def save(file):
        fig.tight_layout()
        fig.savefig(file, format="png", dpi=dpi)
        plt.close(fig)
    return save, numbers
