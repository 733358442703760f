"""First against second order: each integrator's position error against dt, and its observed order.

A free 2 x 0.5 x 0.5 m bar (E 2 kPa: soft enough that dt 0.02 s resolves its fastest mode)
spins and twists for 0.4 s; each integrator runs at DTS and at REFERENCE_DT, and its error at
a dt is the largest distance of a vertex from its own reference run. The slope of log error
against log dt is the observed order: 1 for backward Euler, 2 for BDF2 and the trapezoidal rule
(`main.py figures --only integrator_order`; docs/experiments.md, experiment 9).

The same bar, undamped and free, keeps its energy for DRIFT_SECONDS with the conserving scheme
(the trapezoidal rule with the energy projection, docs/method.md section 6); BDF2 and backward
Euler lose some of it each step, as their formulas say (`energy_drift`; `main.py figures --only
energy_drift`). Each run counts the steps the safeguard trimmed: 0 on this smooth motion.
"""

import math

import numpy as np

import fem
from assets.generators import box
from fem.scene import Body, Effects, Material, Scene, SolverSettings

DTS = (0.02, 0.01, 0.005)       # s
REFERENCE_DT = 0.00125          # s: the same integrator, 16 times finer than the coarsest
SECONDS = 0.4
INTEGRATORS = {"backward-euler": "backward Euler", "bdf2": "BDF2", "trapezoidal": "trapezoidal"}
GUIDES = (("backward-euler", 1), ("bdf2", 2))   # the slopes drawn, each through one integrator's coarsest point


def twisting_state(dt, integrator, tolerance=1e-10, step="newton", effects=None, rho_infinity=None):
    """(scene, x, v): the spinning, twisting bar at dt, its state at t = 0 (fem.init first);
    effects: fem.scene.Effects (default none); rho_infinity: SolverSettings' (None: by the scene)."""
    mesh = box(size=(2.0, 0.5, 0.5), cells=(4, 1, 1), split=6)
    solver = SolverSettings(dt=dt, integrator=integrator, step=step, tolerance=tolerance, newton_tolerance=1e-12,
                            max_newton=100, max_iterations=1000, sleep=False, rho_infinity=rho_infinity)
    scene = Scene("twisting bar", [Body("bar", mesh, Material(2e3, 0.3, 1000.0), "corotational")], solver=solver,
                  effects=effects or Effects())
    x = mesh.vertices.astype(np.float64)
    v = np.cross([1.0, 2.0, 0.0], x - x.mean(0)) + np.cross([3.0, 0.0, 0.0], x) * x[:, :1]
    return scene, x, v - v.mean(0)


def twisting_bar(dt, integrator, step="newton", effects=None, rho_infinity=None):
    """Positions (n, 3) of the spinning, twisting bar after SECONDS at dt (fem.init first)."""
    scene, x, v = twisting_state(dt, integrator, step=step, effects=effects, rho_infinity=rho_infinity)
    sim = fem.Simulation(scene)
    sim.set_state(x, v)
    for _ in range(round(SECONDS / dt)):
        sim.step()
    return sim.positions()


DRIFT_SECONDS, DRIFT_DT = 10.0, 0.02     # s
DRIFT_SAMPLE = 5                         # steps between the energies drawn


def in_f64(measure, *args):
    """measure(*args) with Taichi in float64 (restarted for it and back, which ends every
    Simulation made before)."""
    arch, precision, debug = fem.runtime.requested() or ("cpu", "f32", False)
    if precision == "f64":
        return measure(*args)
    fem.init(arch, "f64", debug=debug)
    try:
        return measure(*args)
    finally:
        fem.init(arch, precision, debug=debug)


def energy_drift(seconds=DRIFT_SECONDS, integrators=tuple(INTEGRATORS)):
    """{integrator: {"t": [...] (s), "energy": [...] (E / E_0, every DRIFT_SAMPLE steps),
    "angular_momentum": L / L_0 at the end, "trimmed": steps the safeguard trimmed}} over
    `seconds` at DRIFT_DT, float64."""
    return in_f64(measured_drift, seconds, integrators)


def measured_drift(seconds, integrators):
    out = {}
    for integrator in integrators:
        scene, x, v = twisting_state(DRIFT_DT, integrator, tolerance=1e-8)
        sim = fem.Simulation(scene)
        sim.set_state(x, v)
        start = sim.stats()
        times, energies, trimmed = [0.0], [1.0], 0
        for k in range(1, round(seconds / DRIFT_DT) + 1):
            info = sim.step()
            trimmed += info["energy_limited"]
            if k % DRIFT_SAMPLE == 0:
                times.append(sim.t)
                energies.append(sim.stats()["total_energy"] / start["total_energy"])
        spin = np.linalg.norm(angular_momentum(sim)) / np.linalg.norm(angular_momentum(sim, x, v))
        out[integrator] = {"t": times, "energy": energies, "angular_momentum": float(spin), "trimmed": int(trimmed)}
    return out


def angular_momentum(sim, x=None, v=None):
    """L = sum m x cross v about the origin (kg m^2/s) of the state (x, v), or the simulation's."""
    x = sim.positions() if x is None else x
    v = sim.velocities() if v is None else v
    return (sim.model.mass_np[:, None] * np.cross(x, v)).sum(0)


def drift_figure(size, dpi, seconds=DRIFT_SECONDS):
    """(save(file), numbers): E / E_0 against time for each integrator over `seconds`."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    numbers = energy_drift(seconds)
    fig, ax = plt.subplots(figsize=size)
    for (integrator, label), colour in zip(INTEGRATORS.items(), ("C3", "C0", "C2")):
        run = numbers[integrator]
        ax.plot(run["t"], run["energy"], color=colour,
                label=f"{label}: E keeps {run['energy'][-1]:.4f}, L {run['angular_momentum']:.4f}, "
                      f"{run['trimmed']} steps trimmed")
    ax.set_xlabel("time (s)")
    ax.set_ylabel("total energy / its start")
    ax.set_title(f"a free spinning, twisting bar, undamped, dt {DRIFT_DT:g} s (float64)", fontsize=9)
    ax.set_xlim(0.0, seconds)
    ax.legend(fontsize=7)
    return saver(fig, dpi), numbers


def observed_order(step="newton", integrators=tuple(INTEGRATORS)):
    """{integrator: {"dt": [...], "error": [...] (m), "slopes": [...]}}, each integrator's `step`
    against its own converged (Newton) run at REFERENCE_DT, in float64: in f32 each step of the
    reference stops at the round-off floor of the convergence test, and over its 320 steps that
    adds up to about 1e-4 m, more than the trapezoidal rule's error at dt 0.005 s. Taichi
    restarts in f64 for it and back, which ends every Simulation made before."""
    return in_f64(measured_order, step, integrators)


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
    return saver(fig, dpi), numbers


def saver(fig, dpi):
    """save(file): writes the figure as a PNG at dpi, then closes it."""
    import matplotlib.pyplot as plt

    def save(file):
        fig.tight_layout()
        fig.savefig(file, format="png", dpi=dpi)
        plt.close(fig)
    return save
