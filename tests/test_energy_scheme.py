"""Energy kept by the integrator, not by trimming (issue 34), checked against analytic answers:

- a body released at rest falls as its integrator's own formula for a constant acceleration
  says: 1/2 g t^2 for the trapezoidal rule and BDF2 (no backward Euler start), g dt^2 N(N+1)/2
  for backward Euler; with the ground far below, too;
- the conserving scheme (the trapezoidal rule, projected onto the energy it began with) keeps
  a free spinning, twisting body's total energy and angular momentum over 10 s, and trims no
  step;
- "converged" is measured at the answer: a converged step's residual, recomputed from the
  states by an independent numpy sum, is within the tolerance.
"""

import numpy as np
import pytest

import fem
from app.bench.direct import DirectSolver
from fem.implicit.potential import GRADIENT_ROUNDOFF
from fem.scene import Body, Effects, Material, Scene, SolverSettings
from conftest import make_scene
from scenes.hard_cases import cube
from test_step_promises import angular_momentum

G = 9.81


def centre_height(sim):
    m = sim.model.mass.to_numpy()[:sim.model.n_vertices].astype(np.float64)
    return float((m * sim.positions()[:, 1]).sum() / m.sum())


def fall(E, integrator, step, ground=None, dt=0.02, steps=25):
    """How far a 1.2 m bar released at rest falls in `steps` steps (m), and the steps trimmed."""
    effects = Effects(gravity=(0.0, -G, 0.0), ground=ground)
    scene = make_scene(cube(cells=3, size=(1.2, 0.2, 0.2)), E=E, effects=effects,
                       solver=SolverSettings(dt=dt, integrator=integrator, step=step), position=(0, 3.0, 0))
    sim = fem.Simulation(scene)
    start, trimmed = centre_height(sim), 0
    for _ in range(steps):
        info = sim.step()
        trimmed += info["energy_limited"]
        assert not any(sim.asleep), "a falling body never sleeps"
    return start - centre_height(sim), trimmed


@pytest.mark.parametrize("precision", ["f32", "f64"])
def test_a_released_body_falls_as_its_integrator_says(precision):
    fem.init("cpu", precision)
    dt, n = 0.02, 25
    exact = {"auto": 0.5 * G * (n * dt) ** 2, "bdf2": 0.5 * G * (n * dt) ** 2,
             "backward-euler": G * dt * dt * n * (n + 1) / 2}
    for E in (1e3, 1e7, 1e11):
        for integrator, step in (("auto", "newton"), ("auto", "single"), ("bdf2", "newton"),
                                 ("backward-euler", "newton")):
            for ground in (None, -10.0):
                fallen, trimmed = fall(E, integrator, step, ground)
                case = (precision, E, integrator, step, ground, fallen, exact[integrator])
                assert abs(fallen - exact[integrator]) <= 1e-3 * exact[integrator], case
                # f32 at E 1e11: the bar's strains round by more than its energy's band; the
                # trimmed steps are rigid steps, which carry the fall on (checked above)
                if (precision, E) != ("f32", 1e11):
                    assert trimmed == 0, case


def twisting_bar(dt, tolerance=1e-8):
    """The spinning, twisting bar of app/bench/order.py, undamped, trapezoidal, float64."""
    from app.bench.order import twisting_state
    scene, x, v = twisting_state(dt, "trapezoidal", tolerance)
    sim = fem.Simulation(scene)
    sim.set_state(x, v)
    return sim


def test_the_conserving_scheme_keeps_energy_and_angular_momentum_over_ten_seconds(f64):
    sim = twisting_bar(0.02)
    E0, L0 = sim.stats()["total_energy"], angular_momentum(sim)
    trimmed, energies = 0, []
    for _ in range(500):
        info = sim.step()
        trimmed += info["energy_limited"]
        energies.append(sim.stats()["total_energy"])
    L = angular_momentum(sim)
    assert trimmed == 0
    assert max(abs(e - E0) for e in energies) <= 1e-6 * E0, (E0, min(energies), max(energies))
    assert np.linalg.norm(L - L0) <= 1e-6 * np.linalg.norm(L0), (L0, L)


def forces(sim, reference):
    """The elastic forces at sim's positions (n, 3, N), from the assembled numpy model
    (app/bench/direct.py: its own polar rotations and element matrices)."""
    reference.x = sim.positions()
    return reference.elastic_forces(reference.rotations())


def converged_steps_checked(sim, dt, tolerance, bodies, steps=12, floor=None):
    """Steps `sim`, and checks each step that reports `converged` at the answer: for every body
    (a slice of the vertices), the residual of M (v - v^) = h f(x) recomputed from the states
    alone, with numpy's forces (its own polar rotations and element matrices), against
    |M v^| + |h f(x)|, the body's physical scale, is at most the tolerance (or, given
    `floor(h, x_n)`, the bodies' round-off floors of |grad|^2 for positions x_n, below that floor). BDF2's first step,
    and its first after a trim, take v_(n-1) = v_n - dt a_n; a trimmed step, which took a rigid
    step instead, is skipped, and so is one the energy projection scaled: that is no longer the
    solve's answer. Returns (steps checked, steps not converged)."""
    reference = DirectSolver(sim)
    m = sim.model.mass.to_numpy()[:sim.model.n_vertices].astype(np.float64)[:, None]
    v_prev, v_n, checked, unconverged, restart = None, sim.velocities(), 0, 0, True
    for k in range(steps):
        if restart:            # BDF2's history from the start's forces: v_(n-1) = v_n - dt a_n
            v_prev = v_n - dt * forces(sim, reference) / m
        x_n = sim.positions()
        info = sim.step()
        v = sim.velocities()
        v_hat, h = None, None
        if info["integrator"] == "backward-euler":
            v_hat, h = v_n, dt
        elif info["integrator"] == "bdf2":
            v_hat, h = (4 * v_n - v_prev) / 3, 2 * dt / 3
        # the energy projection (BDF2's rise taken out) scaled the solve's answer: not the solve's
        projected = (sim.solver.safeguards.body_deformation.to_numpy()[:len(bodies)] != 1.0).any()
        unconverged += not info["converged"]
        if info["converged"] and info["energy_limited"] == 0 and v_hat is not None and not projected:
            f = forces(sim, reference)
            for b, body in enumerate(bodies):
                residual = np.linalg.norm((m * (v - v_hat) - h * f)[body])
                scale = np.sqrt(((m * v_hat)[body] ** 2).sum() + ((h * f)[body] ** 2).sum())
                allowed = np.sqrt((tolerance * scale) ** 2 + (0.0 if floor is None else floor(h, x_n)[b]))
                assert residual <= 1.05 * allowed, (k, b, residual / scale, info["residual"])
            checked += 1
        restart = info["energy_limited"] > 0 or info["integrator"] == "backward-euler"   # the history starts again
        v_prev, v_n = v_n, v
    return checked, unconverged


@pytest.mark.parametrize("integrator", ["backward-euler", "bdf2"])
@pytest.mark.parametrize("E, nu, dt", [(1e5, 0.3, 0.02), (1e8, 0.3, 0.02), (1e5, 0.499, 0.02), (1e5, 0.3, 0.1)])
def test_converged_means_within_the_tolerance_at_the_answer(f64, integrator, E, nu, dt):
    """A step that reports `converged` solved M (v - v^) = h f(x) to its tolerance, measured at
    the answer (`converged_steps_checked`)."""
    tolerance = 1e-4
    scene = make_scene(cube(cells=3), E=E, nu=nu,
                       solver=SolverSettings(dt=dt, tolerance=tolerance, integrator=integrator))
    sim = fem.Simulation(scene)
    x = sim.positions()
    sim.set_state(x, np.cross([0.0, 3.0, 0.0], x - x.mean(0)) + 0.3 * np.cross([1.0, 0.0, 0.0], x) * x[:, :1])
    checked, _ = converged_steps_checked(sim, dt, tolerance, [slice(None)])
    assert checked >= 4


@pytest.mark.parametrize("integrator", ["backward-euler", "bdf2"])
def test_a_step_converges_when_every_body_has(f32, integrator):
    """Two bars spinning and twisting apart, in f32: a step is converged when each body is within
    its own tolerance, or below f32's round-off floor (checked from the states, per body), not
    when their sum is. With the sum, Newton stopped for want of anything either body could gain
    at this precision and reported the step unconverged (here 14 and 2 of 60 steps; fertility's
    two statues: 11 of 40 trapezoidal steps). The floor is the model's documented one
    (`Model.body_floor`: GRADIENT_ROUNDOFF epsilon h E L^2 per body; here about 45 times the
    gradient's actual f32 round-off, 0.22 eps h E L^2 against numpy's float64 sum at the same iterate)."""
    tolerance, dt = 1e-4, 0.02
    bars = [cube(cells=3, size=(1.2, 0.3, 0.3)) for _ in range(2)]
    scene = Scene("two bars", [Body(f"bar {k}", type(bar)(bar.vertices + [0.0, 0.0, 2.0 * k], bar.tets, bar.source),
                                    Material(5e4, 0.4, 1000.0), "corotational") for k, bar in enumerate(bars)],
                  solver=SolverSettings(dt=dt, tolerance=tolerance, integrator=integrator))
    sim = fem.Simulation(scene)
    x, n = sim.positions(), len(bars[0].vertices)
    v = np.zeros_like(x)
    bodies = [slice(0, n), slice(n, 2 * n)]
    for body, spin in zip(bodies, (2.0, 3.0)):
        r = x[body] - x[body].mean(0)
        v[body] = np.cross([0.0, spin, 0.0], r) + 0.5 * spin * np.cross([1.0, 0.0, 0.0], r) * r[:, :1]
    sim.set_state(x, v)
    m = sim.model.mass.to_numpy()[:2 * n].astype(np.float64)

    def floor(h, x):
        """Model.body_floor, times max(1, D^2 / L^2) for a body whose root-mean-square distance D from the
        origin is above its size L: positions carry round-off relative to D (docs/method.md)."""
        near = sim.model.body_floor(GRADIENT_ROUNDOFF["f32"] * np.finfo(np.float32).eps, h)
        far = [max(1.0, (m[body] * (x[body] ** 2).sum(1)).sum() / m[body].sum() / sim.model.bodies[b].size ** 2)
               for b, body in enumerate(bodies)]
        return near * np.array(far)

    checked, unconverged = converged_steps_checked(sim, dt, tolerance, bodies, steps=60, floor=floor)
    assert unconverged == 0 and checked >= 30, (checked, unconverged)
