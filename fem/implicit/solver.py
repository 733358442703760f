"""The implicit step, composed: `ImplicitSolver.step(state_in, state_out, dt)` reads top to bottom.

The solver makes its parts once per Model and `Switches` (fem/pool.py) and hands each the
parts it reads; each part owns its fields and kernels (fem/implicit/__init__.py lists them).
What the step remembers between steps: the rotations (warm starts, and after a Newton step
those of where it ended: the next step's R(x_n)), the last velocity change (the first guess),
the integrator's history and which bodies sleep.
"""

import math
import time
from dataclasses import dataclass, replace

import numpy as np
import taichi as ti

from fem.implicit.contact import Contact
from fem.implicit.effects import Effects
from fem.implicit.elasticity import Elasticity
from fem.implicit.bend import Bend
from fem.implicit.energy_momentum import PASSES, TIGHTER, EnergyMomentum
from fem.implicit.integrators import TRAPEZOIDAL, History, chosen, default_rho, spin_law
from fem.implicit.islands import Islands
from fem.implicit.linear import LinearSolver
from fem.implicit.newton import Newton
from fem.implicit.potential import GRADIENT_ROUNDOFF, ROUNDOFF, VOLUME_ROUNDOFF, IncrementalPotential, damping_dominates
from fem.implicit.preconditioner import Preconditioner
from fem.implicit.rotations import Rotations
from fem.implicit.safeguards import BEFORE, Ending, Safeguards
from fem.implicit.sleep import Sleep
from fem.runtime import epsilon, precision, serial_loops


@dataclass
class StepInfo:
    """What one implicit step did.

    finite: every new position and velocity is finite (else the caller keeps the old state).
    converged: every body's gradient met the tolerance (single step: the linear solve did);
        a Newton step that stopped for another reason (velocities settled, max_newton) did not,
        nor did one where some body was trimmed (energy_limited).
    residual: max over bodies of |grad_b E| / s_b at the answer, dimensionless (s_b: the size of the
        body's terms): <= tolerance when converged, unless the step stopped at round-off
        (`at_floor`). The one-solve step: its linear solve's residual.
    at_floor: converged because every gradient the tolerance did not meet is below its body's
        round-off floor (float32, near-incompressible or stiff bodies): residual > tolerance.
    newton_iters: Newton iterations (1 for a single step).
    solver_iters: CG or Jacobi iterations summed over the Newton iterations.
    solver_capped: Newton iterations whose linear solve stopped at max_iterations, unconverged.
    line_search_steps: step halvings summed over the Newton iterations.
    energy_limited: bodies trimmed: a rise the energy projection could not pay for, where the
        body took a rigid step instead (fem/implicit/safeguards.py). The projection itself (onto
        the energy and angular momentum of the conserving scheme; a rise taken out of any other
        Newton step) is part of the scheme and is not counted.
    rotation_ms, solve_ms: wall time in rotation extraction and in the rest of the step (ms).
    restarted: 1 where this step is backward Euler's because the step before was second order and
        its solve failed for a body that began it strained (`Safeguards.strained`: an inverted
        start, a strained body spinning at dt 0.5 s); that body took a rigid step there, counted
        in its energy_limited, and backward Euler damps what the second-order rule could not
        follow. `integrator` then says "backward-euler".
    """

    finite: bool
    converged: bool
    residual: float | None
    newton_iters: int
    solver_iters: int
    line_search_steps: int
    energy_limited: int
    rotation_ms: float
    solve_ms: float
    integrator: str = "backward-euler"    # the step's own: a two-step integrator restarts with backward Euler
    restarted: int = 0
    at_floor: bool = False
    solver_capped: int = 0


@dataclass(frozen=True)
class Switches:
    """What a solver compiles in or out: the effects a scene calls for (gravity, ground,
    stiffness damping, pins), whether its loops run on one thread (small meshes), and whether
    some body's stiffness damping outweighs its inertia at the scene's dt (`damping_dominates`:
    the line search then holds the damping's frame, IncrementalPotential.holds_frame)."""

    gravity: bool
    ground: bool
    stiffness_damping: bool
    pins: bool
    serial_tets: bool
    serial_vertices: bool
    contact: bool = False             # between bodies and within one (fem/implicit/contact.py)
    damping_dominates: bool = False

    @classmethod
    def of(cls, effects, n_vertices, n_tets, has_pins, bodies, dt):
        return cls(effects.gravity is not None, effects.ground is not None, effects.beta > 0, has_pins,
                   serial_loops(n_tets, "tets"), serial_loops(n_vertices, "vertices"), effects.contact is not None,
                   damping_dominates(bodies, dt, effects.beta))


@ti.data_oriented
class ImplicitSolver:
    """The implicit step for one model; `load`ed for each scene, then `step` is the whole step.
    Loops over bodies run on one thread: for a few bodies a second thread costs more than it saves."""

    def __init__(self, model, switches):
        self.model, self.switches = model, switches
        self.serial_vertices = switches.serial_vertices
        self.sleep = Sleep(model, switches.serial_vertices, switches.serial_tets)
        self.rotations = Rotations(model, self.sleep, switches)
        self.elasticity = Elasticity(model, self.rotations, self.sleep, switches)
        self.effects = Effects(model, self.elasticity, self.sleep, switches)
        if switches.contact:                                  # between bodies, part of the effects
            self.effects.contact = Contact(model, self.effects, switches)
        self.potential = IncrementalPotential(model, self.elasticity, self.rotations, self.effects, self.sleep,
                                              switches)
        self.preconditioning = Preconditioner(model, self.rotations, self.effects, self.sleep, switches)
        self.linear = LinearSolver(model, self.potential, self.elasticity, self.preconditioning, self.effects,
                                   self.sleep, switches)
        self.newton = Newton(model, self.potential, self.linear, self.rotations, self.effects, self.sleep, switches)
        if switches.contact:                                  # bodies that contact couples search together
            self.newton.islands = Islands(model, self.newton, self.effects.contact)
        self.history = History(model, self.sleep, switches)
        self.safeguards = Safeguards(model, self.potential, self.history, self.elasticity, self.effects, self.sleep,
                                     switches)
        self.energy_momentum = EnergyMomentum(model, self.potential, self.elasticity, self.rotations, self.effects,
                                              self.safeguards, self.sleep, switches)
        self.newton.bend = Bend(model, self.energy_momentum.body_stiff, self.effects, self.sleep)
        self.x_end = ti.Vector.field(3, float, model.capacity.vertices)   # m: where the last step ended
        self.rates_from_start = 0                             # what potential.rate_from_start holds

    @property
    def parts(self):
        """Every part holding fields (the coarse level once made)."""
        parts = (self.sleep, self.rotations, self.elasticity, self.effects, self.potential,
                 self.preconditioning, self.linear, self.newton, self.safeguards, self.history)
        return parts + ((self.patches,) if self.patches is not None else ())

    def step(self, state_in, state_out, dt):
        """One implicit step from state_in into state_out; returns a StepInfo.

        A second-order step whose solve failed for a body far from its rest shape (the safeguards
        found a rise no projection can pay for and gave it a rigid step, which keeps its strain:
        `Safeguards.strained`) is reported as such, and the next step is backward Euler's
        (`restart`): that damps what the second-order rule could not follow (an inverted start at
        dt 0.5 s), and the step after it starts the history anew. A failed body that mostly moves
        (a stiff spinning or falling body) only takes the rigid step, which keeps its motion.

        state_in is never written. When the result is not finite, state_out holds garbage
        and the caller keeps state_in (a rejected step is a step not swapped in). The step
        works on the potential's own copies (x0, v0: the inertia target; x, v: the iterate),
        so every kernel is compiled once, not once per State.
        """
        start = time.perf_counter()
        settings, model, p, damped = self.settings, self.model, self.potential, self.effects.damped
        if (restarted := self.restart):
            self.history.forget()
        corotational, ground, contact = model.any_corotational, self.switches.ground, self.switches.contact
        # every body minimises E; the naive variant has no energy to minimise: one solve
        newton = settings.step == "newton" and not model.any_naive
        integrator = "backward-euler" if restarted else chosen(settings.integrator, ground or contact)
        rho = settings.rho_infinity   # None: by the scene, rest where damped, no ringing on a ground's or contact's penalty
        rho = default_rho(dt, damped, ground or contact) if rho is None else rho
        target = self.history.target(integrator, dt, model.version, rho, damped)
        h = target.h_per_dt * dt                                        # the integrator's effective step
        cM, cK = p.coefficients(h)
        self.refresh(cM, cK, h, dt)
        scale = dt / self.last_dt if self.last_dt > 0 else 0.0          # extrapolate the last change this far
        tolerance, newton_tolerance = settings.tolerances_at(dt)       # tighter below dt 0.02 s
        tolerance = max(tolerance, ROUNDOFF * epsilon())                # none below round-off
        settings = replace(settings, newton_tolerance=newton_tolerance)

        # where the step starts, its energy, the guess, the integrator's inertia target, the first iterate
        moved = p.begin(state_in.x, state_in.v, self.x_end)
        if contact:
            self.effects.contact.find(state_in.x)                      # the pairs touching at x_n
        # a Newton step that starts where the last one ended has R(x_n) and the elastic energies
        # there already: its last trial's (the rotations extracted at the last step's end)
        ended_here = newton and moved == 0 and self.end_known == model.version
        rotation_ms, turned = 0.0, 0.0
        if not ended_here:
            rotation_ms, turned = self.update_rotations(p.x, corotational, first=True,    # R(x_n)
                                                        scale=scale if self.turn_known else 0.0)
        self.turn_known = not ended_here                                # the turn of this step, recorded
        self.measure_rates_from_start(integrator == "backward-euler" and corotational)
        # the conserving scheme: the undamped trapezoidal rule off the ground. There, and under the theta rule with mass
        # damping, stiff corotational bodies take the energy-momentum step (energy_momentum.py); with stiffness damping
        # every free body's spin is the drag's (Safeguards.spin_by_law)
        conserve = int(target == TRAPEZOIDAL and not (ground or contact) and not self.effects.damped)
        free = newton and target.one_step and not (ground or contact)
        momentum_step = free and not self.switches.stiffness_damping and corotational and model.any_stiff(dt)
        self.safeguards.keep_spin_by(spin_law(target, dt, self.effects.alpha) * self.switches.stiffness_damping * free)
        if momentum_step:
            self.energy_momentum.begin(state_in.x)                     # S_n, Psi_n with R(x_n)
        if newton:
            self.safeguards.body_energy(p.x, p.v, BEFORE, int(not ended_here))   # x, v = x_n, v_n still
        if self.history.fresh:                                          # a_n from the forces at x_n, v_n
            self.start_acceleration(state_in.x, h, dt)
        self.history.apply(target, integrator, p, state_in.x, state_in.v, h, dt)   # x^, v^ (backward Euler: x_n, v_n)
        # the guess for v, and the first iterate: backward Euler's at x_n (v = 0), a multistep one's at the guess
        a_n = self.history.acceleration() if target.one_step else None    # a closer guess
        self.newton.first_iterate(p.x0, p.x, p.v, h, target.from_history, state_in.v, scale, a_n, dt)
        # a stiff turning body starts on its rigid turn (`arc_first_iterate`); in shear too, its trials (bend.py)
        stiff = newton and corotational and not contact and model.any_stiff(dt)
        bend = stiff and model.any_stiff(dt, shear=True)
        arc = stiff and self.safeguards.arc_first_iterate(state_in.x, self.newton.velocity, self.newton.guess, h,
                                                          dt, int(target.from_history)) > 0
        if arc:
            self.newton.from_guess = True                               # v != 0: its damping terms count
        if contact:                                                     # contact: the first iterate is x_n
            self.effects.contact.hold_start(p.x0, p.x, p.v, state_in.x, h)
        if target.from_history or arc:
            rotation_ms += self.update_rotations(p.x, corotational)[0]  # R at the first iterate
        if ground:
            self.effects.start_contacts(state_in.x, p.x, h, dt)         # friction's normal forces at x_n
        if contact:
            self.effects.contact.start(p.x, p.v, h, p.body_E)           # lagged friction, the first Hessian
        # the blocks follow H: every step where the rotations or the contacts change it
        exact = (newton and corotational) or settings.method != "pcg" or ground or contact
        self.preconditioning.update(p.x, cM, cK, turned, corotational, exact=exact, reuse=not exact,
                                    two_level=self.preconditioner == "two-level")

        # minimise E: Newton, or the one-solve step (on the ground: Newton with the first iterate's rotations)
        if momentum_step:
            solved = self.energy_momentum_solve(state_in, cM, cK, h, target.c, tolerance, scale, settings)
        elif newton:
            if bend and ground:                                         # which bodies the ground may turn
                self.newton.bend.begin(state_in.x, state_in.v, dt)
            solved = self.newton.solve(cM, cK, h, tolerance, scale, settings, self.preconditioner, bend=bend)
        elif (ground or contact) and not model.any_naive:
            solved = self.newton.solve(cM, cK, h, tolerance, scale, settings, self.preconditioner, frozen=True)
        else:
            solved = self.newton.one_solve(cM, cK, h, tolerance, scale, settings, self.preconditioner)

        # the safeguards: finite, momentum (of bodies no ground pushes), energy: the conserving scheme
        # is projected onto the energy it began with
        ending = Ending(newton, int(target.one_step), conserve, math.isfinite(solved.rho),
                        tolerance if solved.rho <= 1.0 else 0.0)
        ended = self.safeguards.end_step(state_in, h, dt, ending, lambda x: self.update_rotations(x, corotational)[0])
        finite, trimmed, rigid = ended.finite, ended.trimmed, ended.rigid
        rotation_ms += ended.rotation_ms
        # a strained body's second-order solve failed: the next step is backward Euler's
        self.restart = finite and ended.strained > 0 and newton and not contact and integrator != "backward-euler"
        # the rotations and elastic energies the next step can reuse: those of its x_n (the
        # projection scales velocities and shifts bodies whole: strains stay), unless a body
        # fell back to its start, whose a_n the next step takes from the forces there too
        self.end_known = model.version if newton and finite and rigid == 0 else None
        self.finish(state_in.v, state_out.x, state_out.v, int(finite), int(a_n is not None))
        if finite and rigid == 0:
            self.history.remember(integrator, dt, model.version)
        else:
            self.history.forget()
        self.last_dt = dt
        ti.sync()

        converged = bool(solved.rho <= 1.0) and trimmed == 0    # a trimmed body's solve failed
        if newton or ((ground or contact) and not model.any_naive):   # the gradient at the answer, no floor
            residual = math.sqrt(max(p.relative[None], 0.0))
        else:
            residual = tolerance * math.sqrt(max(solved.rho, 0.0))
        rotation_ms += solved.rotation_ms
        wall_ms = 1e3 * (time.perf_counter() - start)
        return StepInfo(finite=finite, converged=converged, integrator=target.name,
                        at_floor=converged and residual > tolerance,
                        residual=residual if math.isfinite(residual) else None,
                        newton_iters=max(solved.newton_iters, 1), solver_iters=solved.solver_iters,
                        line_search_steps=solved.halvings, energy_limited=trimmed, rotation_ms=rotation_ms,
                        solve_ms=wall_ms - rotation_ms, restarted=int(restarted), solver_capped=solved.capped)

    def energy_momentum_solve(self, state_in, cM, cK, h, rho, tolerance, scale, settings):
        """The energy-momentum step: Newton minimises the trapezoidal potential whose v^ the
        algorithmic force at the iterate sets (`EnergyMomentum.target`), from the first iterate,
        then again from each answer with v^ set there, until that answer meets the tolerance as it
        is (a pass with no Newton iteration: the step's own residual is within it), or after PASSES;
        in float32 also once a pass ends unconverged: a stiff, nearly incompressible body's residual
        is then at what float32 resolves, and passes again only repeat it (152 Newton iterations a
        step on a 1 m box at E 1e10, nu 0.49995, for the same trims; 20 now).
        Where an answer leaves the energy projection more than a small share of a body's
        deformation energy to pay (`energy_error`), the next pass has a smaller tolerance; the
        step's own tolerance still says whether it converged. Returns the passes' Solved, summed."""
        em, floor, asked = self.energy_momentum, ROUNDOFF * epsilon(), tolerance
        solved, single = None, precision() == "f32"
        for _ in range(PASSES):
            em.target(state_in.x, state_in.v, self.potential.x, h, rho, self.history.acceleration(),
                      rho != 1.0 or self.effects.damped)
            again = self.newton.solve(cM, cK, h, tolerance, scale, settings, self.preconditioner,
                                      warm=solved is None, bend=True)
            done = again.rho <= 1.0 and again.newton_iters == 0
            if solved is not None:
                again.newton_iters += solved.newton_iters
                again.solver_iters += solved.solver_iters
                again.halvings += solved.halvings
                again.rotation_ms += solved.rotation_ms
                again.capped += solved.capped
            solved = again
            error = em.energy_error(state_in.x, 2.0 * h) if done and tolerance > floor else 0.0
            if error > 1.0:                         # the deformation's energy asks for a closer answer
                done = False
                tolerance = max(TIGHTER * tolerance, floor)
                settings = replace(settings, newton_tolerance=TIGHTER * settings.newton_tolerance)
            if done or again.rho > 1.0 and single:      # float32 resolves no closer answer
                break
        if tolerance < asked and solved.rho > 1.0:      # converged is the step's tolerance's word
            solved.rho = float(self.newton.evaluate_first(h, asked, 1))
        return solved

    def measure_rates_from_start(self, chords):
        """With stiffness damping, a step whose velocities are chords (backward Euler's, of a
        corotational body) measures strain rates against the rotations R(x_n) it starts from
        (IncrementalPotential.turn_rate); one launch where that changes, one to keep R(x_n)."""
        on = int(chords and self.switches.stiffness_damping)
        if on:
            self.rotations.keep_start()
        if on != self.rates_from_start:
            self.potential.rate_from_start[None] = self.rates_from_start = on

    def start_acceleration(self, x_n, h, dt):
        """The trapezoidal rule's a_n where the history gives none: M a_n = f(x_n) - D v_n + M g
        (+ the ground's force), the forces at the step's start, from -grad E at v = v^ = v_n with
        x = x_n (R(x_n) already extracted), where it is h M a_n."""
        p = self.potential
        if self.switches.ground:
            self.effects.start_contacts(x_n, p.x, h, dt)
            self.effects.release_deep()
        if self.switches.contact:
            self.effects.contact.clear_forces()
        p.gradient(p.v0, p.x, p.v, h, 1.0, False)
        self.store_acceleration(self.history.acceleration(), h)

    @ti.kernel
    def store_acceleration(self, accel: ti.template(), h: float):
        """accel <- -grad E / (h m), filtered (a pinned vertex does not accelerate)."""
        ti.loop_config(serialize=self.serial_vertices)
        for i in range(self.model.vertex_count[None]):
            accel[i] = self.effects.filtered(i, self.potential.rhs[i]) / (h * self.model.mass[i])

    # ------------------------------------------------------------ a scene, live edits, memory

    def load(self, effects, settings):
        """Start on the model's current scene: its effects' values and the solver settings
        (read at every step: a window may change them live)."""
        model = self.model
        assert Switches.of(effects, model.n_vertices, model.n_tets, model.has_pins, model.bodies,
                           settings.dt) == self.switches
        self.settings = settings
        self.effects.load(effects)
        self.effects.set_dt(settings.dt, settings.dt)
        # the per-body inputs of the kernels, kept here and written together (write_bodies)
        self.pinned_np = np.array([(model.free_np[b.vertices] == 0).any() for b in model.bodies], np.int32)
        self.awake_np = np.ones(len(model.bodies), np.int32)
        self.floor_np = self.speed_floor_np = self.quiet_np = np.zeros(len(model.bodies))   # set by refresh
        self.stiff_np = np.zeros(len(model.bodies), np.int32)
        self.size_np = np.array([b.size for b in model.bodies], np.float64)   # L, m: the floors' size
        self.model_version = None                             # (model edit, dt) the cached data is for
        self.preconditioning.load()
        self.linear.load()
        self.sleep.load()
        self.reset()

    def reset(self):
        """Forget everything from earlier steps: rotations, warm starts, the integrator's
        history, sleep."""
        self.wake(np.ones(len(self.model.bodies)))
        self.rotations.unrotate()
        self.forget_change()
        self.preconditioning.reset()

    def wake(self, awake):
        """Which bodies the step moves: (bodies,) of 0 (asleep: left exactly as they are) or 1."""
        self.awake_np = np.asarray(awake, np.int32)
        self.write_bodies()
        self.preconditioning.rebuild()                        # a body that wakes has no blocks yet

    def forget_change(self):
        """The next step starts its solve from v_n itself, and a two-step integrator starts
        again: after a new state, the last step says nothing about the next one."""
        self.newton.forget_change()
        self.history.forget()
        self.preconditioning.forget()                         # the blocks are for other rotations
        self.safeguards.forget_band()                         # energy is measured from the new state
        self.last_dt = 0.0                                    # s, the dt of the step that made the change
        self.end_known = None         # the model version whose R and elastic energies at x_n are known
        self.turn_known = False       # the rotations' turn field holds the last step's turn
        self.restart = False          # the next step is backward Euler's (`step`)

    def refresh(self, cM, cK, h, dt):
        """Re-derive what depends on the model's methods and materials (after a live edit), the
        integrator's step h and dt."""
        if (self.model.version, h, dt, self.settings.dt) != self.model_version:
            self.model_version = (self.model.version, h, dt, self.settings.dt)
            self.preconditioning.rebuild()
            self.linear.forget_weight()
            self.effects.set_dt(dt, self.settings.dt)
            self.floor_np = self.model.body_floor(GRADIENT_ROUNDOFF[precision()] * epsilon(), h,
                                                  VOLUME_ROUNDOFF[precision()])
            # a velocity change below eps L / h moves no position: what x = x^ + h v can represent
            self.speed_floor_np = self.model.body_speed_floor(epsilon(), h)
            self.quiet_np = self.model.body_quiet(ROUNDOFF * epsilon(), dt)
            self.stiff_np = self.model.stiff(dt).astype(np.int32) * (1 + self.model.stiff(dt, shear=True))  # 2: shear
            self.write_bodies()
            if not self.model.any_corotational and self.rotations.rotated:
                self.rotations.unrotate()                     # every body switched to linear
        if self.settings.method == "jacobi":
            self.linear.jacobi_weight(cM, cK, self.settings.jacobi_omega)

    def update_rotations(self, x, corotational, first=False, scale=0.0):
        """Rotations at positions x, when some body is corotational: (ms, rad turned), as
        Rotations.update with the settings' SVD choice and twist stiffness (Newton's)."""
        if not corotational:
            return 0.0, 0.0
        twist = self.settings.step == "newton" and not self.model.any_naive
        return self.rotations.update(x, self.settings.rotations == "svd", twist, first, scale)

    @property
    def preconditioner(self):
        """The PCG preconditioner in use: "two-level" or "jacobi" (block Jacobi); None for Jacobi iteration."""
        return Preconditioner.kind(self.settings, self.model.n_vertices)

    @property
    def patches(self):
        """The coarse level (fem/coarse.py), None until a two-level solve made it."""
        return self.preconditioning.patches

    def write_bodies(self):
        """The per-body inputs (pinned, awake, round-off floors) into their parts' fields, in one kernel."""
        self._write_bodies(self.pinned_np, self.awake_np, self.floor_np, self.speed_floor_np, self.quiet_np,
                           self.size_np, self.stiff_np)

    @ti.kernel
    def _write_bodies(self, pinned: ti.types.ndarray(), awake: ti.types.ndarray(),
                      floor: ti.types.ndarray(), speed_floor: ti.types.ndarray(), quiet: ti.types.ndarray(),
                      size: ti.types.ndarray(), stiff: ti.types.ndarray()):
        ti.loop_config(serialize=True)
        for b in range(pinned.shape[0]):
            self.safeguards.body_pinned[b], self.sleep.awake[b] = pinned[b], awake[b]
            self.potential.body_near_floor[b], self.newton.body_speed_floor[b] = floor[b], speed_floor[b]
            self.potential.body_floor[b], self.potential.body_far[b] = floor[b], 1.0
            self.potential.body_size_sq[b] = size[b] ** 2
            self.safeguards.body_quiet[b] = quiet[b]
            self.energy_momentum.body_stiff[b] = stiff[b]

    @ti.kernel
    def finish(self, v_n: ti.template(), x: ti.template(), v: ti.template(), good: ti.i32, fit: ti.i32):
        """state_out <- the iterate (and x_end <- its x); the last change <- v - v_n for the next
        step's guess, and after a trapezoidal step (fit) each body's blend (Newton.remember_change)."""
        ti.loop_config(serialize=self.serial_vertices)
        for i in range(self.model.vertex_count[None]):
            x[i], v[i] = self.potential.x[i], self.potential.v[i]
            self.x_end[i] = self.potential.x[i]
        self.newton.remember_change(v_n, self.potential.v, good, fit)
