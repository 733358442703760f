"""A running scene: the driver that schedules impulses, times steps and reports.

    sim = Simulation(scene, method="linear")
    info = sim.step()            # newton_iters, solver_iters, residual, wall_ms, ...
    x = sim.positions()          # (n, 3) numpy
    sim.stats()                  # + energies, volume ratios, inverted tets

The step itself is `ImplicitSolver.step(state_in, state_out, dt)` (fem/implicit/solver.py);
two States take turns, and a rejected step is simply not swapped in.
"""

import sys
import time
from decimal import Decimal
from dataclasses import asdict, replace

import numpy as np
import taichi as ti

from fem import pool
from fem.builder import initial_state, model_arrays, start_state
from fem.errors import FemError
from fem.scene import METHODS, Material, check_precision, select_vertices
from fem.implicit.integrators import penalty_note
from fem.implicit.potential import ROUNDOFF
from fem.runtime import epsilon
from fem.implicit.solver import StepInfo

# A body sleeps after QUIET_STEPS steps in a row in which no vertex moved more than
# QUIET_MOTION of the body's size, or ROUNDOFF eps of it where that is more (float32: 3.6e-6;
# a damped f32 cube at rest jitters by 1e-6 of its size a step, round-off's floor, and slept
# or not by chance): its velocities are set to 0 and steps leave it exactly
# as it is, at no cost, until an impulse (a click), a new state, material or method wakes it.
# A body pressed into the ground, or touching another body (contact), is quiet below the smoothed
# friction's creep speed too (the scene's stick_speed, fem/implicit/effects.py): friction holds it, up to
# that creep.
QUIET_STEPS = 25
QUIET_MOTION = 1e-6
# A step that ends with a vertex deeper below the ground than SUNK of its body's size (and deeper
# than it began) is taken again as two steps of dt / 2, and so on, at most MAX_SPLITS halvings deep.
# The ground is a penalty whose stiffness falls as 1 / dt^2 (fem/implicit/effects.py): a body at rest
# sinks by about g dt^2 / 1000 per vertex above its bottom, 1 m at dt 10 s. A step still too deep
# after the last halving is kept and counted (`sunk` in its stats row).
SUNK = 0.1
MAX_SPLITS = 4


def added(first, second):
    """The StepInfo of two sub-steps taken as one: counts and times added, finite and converged
    where both were, the larger residual, the second's integrator."""
    out = {}
    for key, a in asdict(first).items():
        b = getattr(second, key)
        if isinstance(a, bool):
            out[key] = a and b
        elif key == "residual":
            out[key] = None if a is None or b is None else max(a, b)
        elif isinstance(a, (int, float)):
            out[key] = a + b
    return replace(second, **out)


@ti.kernel
def add_velocity(v: ti.template(), free: ti.template(), ids: ti.types.ndarray(), dv: ti.types.ndarray()):
    """v[ids[k]] += dv[k] for unpinned vertices."""
    for k in range(ids.shape[0]):
        i = ids[k]
        v[i] += free[i] * ti.Vector([dv[k, 0], dv[k, 1], dv[k, 2]])


class Simulation:
    """Steps one scene with an implicit integrator; see fem.implicit for the maths.

    method: None keeps each body's own method, "linear" / "corotational" overrides all.
    solver ("pcg" | "jacobi"), step ("newton" | "single"), integrator ("auto" | "trapezoidal" |
    "bdf2" | "backward-euler"), dt (s), tolerance, max_iterations: override the scene's solver
    settings where not None.
    """

    def __init__(self, scene, method=None, solver=None, dt=None, tolerance=None, max_iterations=None,
                 step=None, integrator=None):
        if method is not None:
            if method not in METHODS:
                raise FemError(f"method must be one of {METHODS}, got {method!r}")
            scene = scene.with_method(method)
        overrides = {"method": solver, "dt": dt, "tolerance": tolerance, "max_iterations": max_iterations,
                     "step": step, "integrator": integrator}
        settings = replace(scene.solver, **{k: v for k, v in overrides.items() if v is not None})
        settings.check(scene.path or scene.name)
        check_precision(scene, "f64" if ti.lang.impl.get_runtime().default_fp == ti.f64 else "f32")
        self.scene = scene                      # the description; never edited
        arrays = model_arrays(scene)
        bodies, X, T, mass, free = arrays
        if scene.effects.contact is not None:
            from fem.contact_start import check_start     # scipy's k-d trees: 0.3 s of imports a scene without contact skips
            check_start(scene, start_state(scene, bodies, X, mass, free)[0], bodies, T)
        if scene.effects.ground is not None or scene.effects.contact is not None:
            note = penalty_note(settings, scene.path or scene.name)   # what the trapezoidal rule becomes there
            if note:
                print(note, file=sys.stderr)
        parts = pool.borrow(self, arrays, scene.effects, settings)   # fields, kernels compiled
        self.model, self.solver, self.measure = parts.model, parts.solver, parts.measure
        self.state, self.spare = parts.states
        offsets = [b.vertices.start for b in self.model.bodies]
        self.impulses = []
        for k, imp in enumerate(scene.impulses):
            picks = select_vertices(imp.selection, scene.bodies, f"{scene.path}: impulse[{k}]")
            ids = np.concatenate([ids + offsets[b] for b, ids in picks])
            self.impulses.append((imp.time, ids, imp.delta_v))
        self.warned_nonfinite = False
        self.reset()

    # ------------------------------------------------------------ sleeping bodies

    @property
    def asleep(self):
        """(bodies,) True for the bodies that sleep now."""
        return [not a for a in self.awake]

    def wake(self, bodies=None):
        """Wake the given body ids (None: all); they move again from exactly where they rest."""
        for b in range(len(self.model.bodies)) if bodies is None else bodies:
            self.awake[b], self.quiet[b] = True, 0
        self.solver.wake(self.awake)

    def fall_asleep(self):
        """After a step: count each awake body's quiet steps; put those quiet long enough to sleep."""
        if not self.settings.sleep:
            return
        speed = np.zeros(len(self.awake))
        self.solver.sleep.body_speeds(self.state.v, speed)
        speed = np.sqrt(speed)
        creep = np.zeros(len(self.awake), np.int32)
        if self.solver.switches.ground:
            self.solver.effects.body_grounded(self.state.x, creep)
        if self.solver.switches.contact:                     # resting on another body: its friction
            self.solver.effects.contact.broad.touching(self.state.x, creep)
        fell = False
        for b, body in enumerate(self.model.bodies):
            quiet_speed = max(max(QUIET_MOTION, ROUNDOFF * epsilon()) * body.size / self.settings.dt,
                              self.scene.effects.stick_speed * creep[b])
            quiet = self.awake[b] and speed[b] <= quiet_speed
            self.quiet_speeds[b] = quiet_speed
            self.quiet[b] = self.quiet[b] + 1 if quiet else 0
            if self.quiet[b] >= QUIET_STEPS:
                self.awake[b], fell = False, True
                self.solver.sleep.hold(self.state.v, body.vertices.start, body.vertices.stop)
        if fell:
            self.solver.wake(self.awake)

    def wake_the_hit(self, dt):
        """Before a step with contact: wake each sleeping body that a moving one can reach in it
        (closer than d_hat + 2 dt |v|max), so that it is pushed rather than met as a wall."""
        if not (self.solver.switches.contact and any(self.awake) and not all(self.awake)):
            return
        speed = np.zeros(len(self.awake))
        self.solver.sleep.body_speeds(self.state.v, speed)
        speed = np.where(self.awake, np.sqrt(speed), 0.0)
        motion = np.where(speed > self.quiet_speeds, 2, np.asarray(self.awake, np.int32)).astype(np.int32)
        woken = np.zeros(len(self.awake), np.int32)
        radius = float(self.solver.effects.contact.distance[None]) + 2.0 * dt * float(speed.max())
        self.solver.effects.contact.broad.meeting(self.state.x, radius, motion, woken)
        if woken.any():
            self.wake(np.flatnonzero(woken).tolist())

    # ------------------------------------------------------------ running

    def reset(self):
        """Back to t = 0 with the scene's initial conditions."""
        self.state.load(*initial_state(self.scene, self.model))
        self.solver.reset()
        self.awake = [True] * len(self.model.bodies)
        self.quiet = [0] * len(self.model.bodies)
        self.quiet_speeds = np.zeros(len(self.model.bodies))     # m/s: slower, a body is quiet
        self.t, self.elapsed = 0.0, Decimal(0)
        self.steps = 0
        self.pending = sorted(self.impulses, key=lambda imp: imp[0])
        self.last = {}
        self.contact_record = {"most_pairs": 0, "smallest_distance": None, "interpenetrating_steps": 0}
        self.ground_record = {"split_steps": 0, "sunk_steps": 0}      # steps taken in sub-steps; still too deep
        self.contact_points = np.zeros((0, 3))

    @property
    def settings(self):
        """The SolverSettings the solver reads at every step (replace or edit them live)."""
        return self.solver.settings

    @settings.setter
    def settings(self, value):
        self.solver.settings = value

    @property
    def coefficients(self):
        """(cM, cK) of the Newton matrix H = cM M + cK K at the current dt."""
        return self.solver.potential.coefficients(self.settings.dt)

    def step(self):
        """Advance one time step; returns what the step did (dict)."""
        start = time.perf_counter()
        dt = self.settings.dt
        while self.pending and self.pending[0][0] <= self.t + 0.5 * dt:
            _, ids, dv = self.pending.pop(0)
            self.apply_impulse(ids, dv)
        self.wake_the_hit(dt)
        substeps = {"substeps": 1, "sunk": 0} if self.solver.switches.ground else {}
        if any(self.awake):
            info = self.take(dt, MAX_SPLITS, substeps)
        else:                                   # everything sleeps: the step would change nothing
            info = StepInfo(True, True, 0.0, 0, 0, 0, 0, 0.0, 0.0)
            self.solver.history.forget()
        self.steps += 1
        if info.finite:
            if any(self.awake):
                self.fall_asleep()
            # summed in decimal, each dt as it is written: t = 0.94 s after 47 steps of 0.02 s, not
            # the 0.9400000000000006 of float sums (which stats rows and figure files would show)
            self.elapsed += Decimal(repr(float(dt)))
            self.t = float(self.elapsed)
        elif not self.warned_nonfinite:
            print(f"warning: step {self.steps} (t = {self.t:g} s) gave non-finite values; "
                  "rejected it and kept the previous state", file=sys.stderr)
            self.warned_nonfinite = True
        self.last = {"step": self.steps, "t": self.t, "wall_ms": 1e3 * (time.perf_counter() - start),
                     "solver": self.settings.method, "preconditioner": self.solver.preconditioner,
                     "step_kind": self.step_kind, **asdict(info),
                     "corotational": [b.method == "corotational" for b in self.model.bodies],
                     "asleep": self.asleep, **substeps}
        if substeps:
            self.ground_record["split_steps"] += int(substeps["substeps"] > 1)
            self.ground_record["sunk_steps"] += int(substeps["sunk"] > 0)
        if self.solver.switches.contact:
            self.last.update(self.contact_stats())
        return self.last

    def take(self, dt, splits, substeps):
        """The solver's step of dt from self.state, copied in when finite. Where the ground is on and
        the step would end with a vertex sunk too deep (`sunk`), it is taken again as two of dt / 2,
        each split the same way at most `splits` times more; the StepInfo then adds up the sub-steps'.
        substeps: {"substeps", "sunk"} counts the sub-steps taken and the vertices left too deep."""
        x, v = (self.positions(), self.velocities()) if substeps else (None, None)
        info = self.solver.step(self.state, self.spare, dt)
        if not info.finite:
            return info
        deep = self.sunk(x) if substeps else 0
        if deep == 0 or splits == 0:
            self.state.take(self.spare)
            if deep:
                substeps["sunk"] += deep
            return info
        self.solver.forget_change()              # its warm starts are of the step not taken
        substeps["substeps"] += 1
        first = self.take(dt / 2, splits - 1, substeps)
        second = self.take(dt / 2, splits - 1, substeps) if first.finite else None
        if second is None or not second.finite:  # all or nothing: the step is rejected whole
            self.state.load(x, v)
            self.solver.forget_change()
            return first if second is None else second
        return added(first, second)

    def sunk(self, before):
        """How many vertices of the solver's new positions (self.spare) lie deeper below the ground
        than SUNK of their body's size and than they were `before` ((n, 3) m)."""
        n = self.model.n_vertices
        after = self.spare.x.to_numpy()[:n, 1].astype(np.float64)
        ground = self.scene.effects.ground
        allowed = np.maximum(SUNK * np.array([b.size for b in self.model.bodies])[self.model.vertex_body_np[:n]],
                             ground - before[:, 1])
        return int((ground - after > allowed).sum())

    def contact_stats(self):
        """Contact between bodies now (fem/implicit/contact.py): contact_pairs, the pairs closer than
        the contact distance; smallest_distance (m, None without a pair near); interpenetrating, the
        pairs whose vertex is behind its triangle's face. Also kept over the run in contact_record;
        contact_points (k, 3), m, the midpoints of the touching pairs' closest points, for pictures."""
        contact = self.solver.effects.contact
        points = np.zeros((max(int(contact.pair_count[None]), 1), 3))
        contact.measure(self.state.x, points)
        points = points[:int(contact.touching[None])]
        self.contact_points = points[np.lexsort(points.T[::-1])]         # in one order, run after run
        smallest = float(contact.smallest[None])
        row = {"contact_pairs": int(contact.touching[None]),
               "smallest_distance": smallest if smallest <= float(contact.distance[None]) else None,
               "interpenetrating": int(contact.crossing[None])}
        record = self.contact_record
        record["most_pairs"] = max(record["most_pairs"], row["contact_pairs"])
        if row["smallest_distance"] is not None:
            record["smallest_distance"] = min(record["smallest_distance"] or smallest, smallest)
        record["interpenetrating_steps"] += int(row["interpenetrating"] > 0)
        if contact.overflow[None] and not record.get("warned_overflow"):
            print(f"warning: step {self.steps}: more contact pairs than room for them "
                  f"({contact.pair_capacity}); some were dropped", file=sys.stderr)
            record["warned_overflow"] = True
        return row

    @property
    def step_kind(self):
        """The step taken: the settings' "newton" or "single"; always "single" while some body
        uses the naive variant, whose forces have no energy for Newton to minimise."""
        return "single" if self.model.any_naive else self.settings.step

    # ------------------------------------------------------------ interaction: the one path for live edits

    def apply_impulse(self, ids, delta_v):
        """Add delta_v (m/s; (3,) or (k, 3)) to the velocities of global vertex ids (k,)."""
        ids = np.asarray(ids, np.int32).ravel()
        dv = np.broadcast_to(np.asarray(delta_v, np.float64), (len(ids), 3)).copy()
        if len(ids):
            self.wake(np.unique(self.model.vertex_body_np[ids]).tolist())
            add_velocity(self.state.v, self.model.free, ids, dv)
            self.solver.history.forget()          # v jumped: a two-step integrator starts again

    def set_state(self, x, v):
        """Replace the positions x (m) and velocities v (m/s), (n, 3) numpy each."""
        self.state.load(np.asarray(x, np.float64), np.asarray(v, np.float64))
        self.solver.forget_change()
        self.wake()

    def set_method(self, method, body=None):
        """Switch one body (or all) between linear and corotational, live."""
        if method not in METHODS:
            raise FemError(f"method must be one of {METHODS}, got {method!r}")
        for i in range(len(self.model.bodies)) if body is None else [body]:
            self.model.set_method(i, method)
        self.wake(None if body is None else [body])

    def set_material(self, body, E, nu):
        """Young's modulus E (Pa) and Poisson ratio nu of one body, live."""
        self.model.set_material(body, Material(E, nu, self.model.bodies[body].material.density))
        self.wake([body])

    # ------------------------------------------------------------ the engine's maths, for checks

    def _work(self, x=None):
        """The solver's iterate (IncrementalPotential.x, v) holding positions x ((n, 3) numpy) and
        zero velocities, or (x None) a copy of the current state: every kernel then runs on the
        same fields."""
        work = self.solver.potential
        if x is None:
            work.begin(self.state.x, self.state.v, self.solver.x_end)   # the step's own arguments: compiled once
        else:
            self.model.write(work.x, np.asarray(x, np.float64))
            work.v.fill(0.0)
        return work

    def _rotate(self, x):
        """The solver's rotations at positions x; the next step then knows nothing of the last
        step's turn, as they are overwritten. Returns the work state."""
        work = self._work(x)
        self.solver.forget_change()
        self.solver.update_rotations(work.x, self.model.any_corotational)
        return work

    def rotations(self, x=None):
        """(m, 3, 3) the rotation R of every tet at positions x, as the solver extracts it
        (identity for linear tets); leaves the solver's rotations there."""
        self._rotate(x)
        m = self.model.n_tets
        rotated_Bm = self.solver.rotations.rotated_Bm.to_numpy()[:m].astype(np.float64)
        Dm = np.linalg.inv(self.model.Bm.to_numpy()[:m].astype(np.float64))
        return np.transpose(Dm @ rotated_Bm, (0, 2, 1))            # R = (Dm Bm R^T)^T

    def forces(self, x=None):
        """(n, 3) elastic forces f(x) = -grad Psi(x) (N) at positions x (None: the current ones)."""
        work = self._rotate(x)
        out = self.solver.linear.Ap
        self.solver.elasticity.elastic_forces(work.x, out)
        return out.to_numpy()[:self.model.n_vertices].astype(np.float64)

    def energy(self, x=None):
        """Elastic energy Psi(x) (J, float64) at positions x (None: the current ones)."""
        work = self._work(x)
        return self.measure.read(work.x, work.v)["elastic_energy"]

    def apply_matrix(self, u, cM=None, cK=None, x=None):
        """H u = cM M u + cK K(R) u for a (n, 3) numpy u, with the rotations at positions x
        (None: the current ones); (cM, cK) default to the step's."""
        if cM is None:
            cM, cK = self.coefficients
        self._rotate(x)
        return self.solver.linear.apply_matrix(np.asarray(u, np.float64), cM, cK)

    # ------------------------------------------------------------ reading

    def positions(self):
        """(n, 3) float64 vertex positions, m."""
        return self.state.x.to_numpy()[:self.model.n_vertices].astype(np.float64)

    def velocities(self):
        """(n, 3) float64 vertex velocities, m/s."""
        return self.state.v.to_numpy()[:self.model.n_vertices].astype(np.float64)

    def stats(self):
        """The last step's numbers plus energies (J), volume ratios and inverted tets now."""
        out = {"step": self.steps, "t": self.t, "solver": self.settings.method}
        out.update(self.last)
        out["corotational"] = [b.method == "corotational" for b in self.model.bodies]   # now, after toggles
        out["asleep"] = self.asleep
        work = self._work()
        out.update(self.measure.read(work.x, work.v))
        return out

    def tet_values(self):
        """Per-tet (volume ratio J, strain energy density J/m^3), for colouring; (m,) each."""
        work = self._work()
        self.measure.measure(work.x, work.v)
        m = self.model.n_tets
        return self.measure.tet_volume_ratio.to_numpy()[:m], self.measure.tet_energy_density.to_numpy()[:m]
