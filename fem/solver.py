"""Backward Euler as a minimisation, solved matrix-free (method.md, "The step as a minimisation").

With x = x_n + dt v, one step finds the velocity v that minimises the incremental potential

    E(v) = 1/2 |v - v_n|_M^2 + dt/2 v^T D v - dt v^T M g + Psi(x_n + dt v)        (J)

(D = alpha M + beta K_n: Rayleigh damping with the stiffness frozen at the step's start;
Psi: the elastic energy, corotated linear or linear per body). Its stationarity condition
M (v - v_n) + dt D v - dt M g - dt f(x) = 0 is exactly backward Euler with damping.

Newton iterations minimise E: each solves H d = -grad E with the positive definite

    H = (1 + dt alpha) M + (dt beta + dt^2) K(R),     R: rotations at the current iterate,

by preconditioned CG (block Jacobi, plus the rigid patches of fem/coarse.py on large
meshes) or weighted Jacobi iteration, never assembling H: the
stiffness product runs tet by tet and per-vertex sums gather over the model's adjacency
(no atomics, so every run is the same bit for bit). A backtracking line search on E
(Armijo) accepts only iterates that lower E, with E summed in float64 whatever the
fields' precision. The first Newton iteration from v = 0 is the classical one-solve
(stiffness-warping) step: `step = "single"` stops there, without line search.

Convergence is tested per body: body b has converged when |grad_b E| <= tol * s_b, with
s_b the size of the step's own terms (momentum M v_n, elastic and gravity impulses) and a
floor from the body's size, mass and stiffness at the precision's round-off, so a body at
rest needs no iteration and a violently pushed body does not set the scale for a quiet one.

Effects a scene leaves off are not compiled: gravity, pins, ground contact and stiffness
damping are `ti.static` branches fixed when the solver is made, and rotations are only
extracted while some body is corotational. Linear and corotational tets share every
kernel: corotation only changes the per-tet matrix `rotated_Bm` = Bm R^T.
"""

import math
import time
from dataclasses import dataclass

import numpy as np
import taichi as ti

from fem.coarse import Patches
from fem.elastic import (corner_forces, edge_matrix, energy_density, is_finite, linear_stress,
                         stiffness_block)
from fem.rotation import (conjugate, newton_rotation, polar_rotation, quaternion_matrix, quaternion_of,
                          quaternion_product)
from fem.runtime import epsilon, serial_loops

ARMIJO = 1e-4            # sufficient decrease: E(v + a d) <= E(v) + ARMIJO a grad.d
MAX_HALVINGS = 12        # line search: a >= 2^-12
FORCING = 0.1            # inexact Newton: CG reduces the gradient by this factor (at least)
ROUNDOFF = 30.0          # per-body floor of the stopping test, in units of the precision's epsilon
CG_UNROLL = 2            # PCG iterations per kernel launch: fewer launches, same iterates
TWO_LEVEL_VERTICES = 2000   # "auto": below, block Jacobi is as fast (its iterations cost less; measured)
BEFORE, AFTER = 0, 1     # rows of ImplicitSolver.body_total
TET_CHUNK = 16           # tets a thread sums per body before adding to a per-body total
NAIVE = 2                # Model.method(e) of a tet of the naive variant (fem.scene.METHODS)
STALE_TURN = 0.2         # rad: PCG's block-Jacobi blocks are rebuilt once some tet turned this far


@ti.func
def twist_stiffness(trace_S, mu, lam):
    """lam_t = max(0, (psi_i + psi_j) / (s_i + s_j)) with every s_i = tr S / 3 (Pa), where
    psi_i = 2 mu (s_i - 1) + lam (tr S - 3): the twist curvature of the corotated energy."""
    pair = 2.0 * trace_S / 3.0
    lam_t = 0.0
    if pair > 0:
        lam_t = ti.max(0.0, (2.0 * mu * (pair - 2.0) + 2.0 * lam * (trace_S - 3.0)) / pair)
    return lam_t


@dataclass
class StepInfo:
    """What one implicit step did.

    finite: every new position and velocity is finite (else the caller keeps the old state).
    converged: every body's gradient met the tolerance (single step: the linear solve did).
    residual: sqrt(sum over bodies of (|grad_b E| / s_b)^2), dimensionless; <= tolerance when converged.
    newton_iters: Newton iterations (1 for a single step or an all-linear scene).
    solver_iters: CG or Jacobi iterations summed over the Newton iterations.
    line_search_steps: step halvings summed over the Newton iterations.
    energy_limited: bodies whose total energy the step would have raised, so that their
        velocities relative to their centre of mass were scaled back to the energy they had.
    rotation_ms, solve_ms: wall time in rotation extraction and in the rest of the step (ms).
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


@dataclass(frozen=True)
class Switches:
    """What a solver compiles in or out: the effects a scene calls for (gravity, ground,
    stiffness damping, pins), and whether its loops run on one thread (small meshes)."""

    gravity: bool
    ground: bool
    stiffness_damping: bool
    pins: bool
    serial_tets: bool
    serial_vertices: bool

    @classmethod
    def of(cls, effects, n_vertices, n_tets, has_pins):
        return cls(effects.gravity is not None, effects.ground is not None, effects.beta > 0, has_pins,
                   serial_loops(n_tets, "tets"), serial_loops(n_vertices, "vertices"))


@ti.data_oriented
class ImplicitSolver:
    """Work fields and kernels of the implicit step for one model; `step` is the whole step.

    Made once per Model and `Switches` (fem/pool.py), then `load`ed for each scene. Loops over
    bodies run on one thread: for a few bodies a second thread costs more than it saves.
    """

    def __init__(self, model, switches):
        n, m, nb = model.capacity.vertices, model.capacity.tets, model.capacity.bodies
        self.model, self.switches = model, switches
        self.has_gravity, self.has_ground = switches.gravity, switches.ground     # compile-time switches
        self.has_stiffness_damping = switches.stiffness_damping                   # D includes beta K_n
        self.pins = switches.pins
        self.serial_tets, self.serial_vertices = switches.serial_tets, switches.serial_vertices
        vec = lambda size: ti.Vector.field(3, float, size)   # noqa: E731
        self.mass_damping = ti.field(float, ())               # alpha, 1/s
        self.stiffness_damping = ti.field(float, ())          # beta, s
        self.gravity = ti.Vector.field(3, float, ())          # m/s^2
        self.ground = ti.field(float, ())                     # plane height y, m
        self.friction = ti.field(float, ())                   # share of tangential velocity lost on contact
        self.rotated_Bm = ti.Matrix.field(3, 3, float, m)     # Bm R^T at the current iterate
        damped = m if self.has_stiffness_damping else 1
        self.damping_frame = ti.Vector.field(4, float, damped)   # R_n as (x, y, z, w): the damping's frame
        self.quaternions = ti.Vector.field(4, float, m)       # R as (x, y, z, w): the next warm start
        self.turn = ti.Vector.field(3, float, m)              # (x, y, z) of R_n R_(n-1)^-1, the last turn
        self.twist = ti.field(float, m)                       # twist stiffness of the Newton matrix, Pa
        self.needs_svd = ti.field(ti.i8, m)                   # 1: the tet's R comes from the SVD
        self.largest_turn = ti.field(float, ())               # largest |turn|^2 this step: sin^2(angle / 2)
        self.corner = vec(4 * m)                              # per-corner values before the gather
        self.x0, self.v0 = vec(n), vec(n)                     # the step's start x_n (m), v_n (m/s)
        self.x, self.v = vec(n), vec(n)                       # the iterate x = x_n + dt v, v
        self.velocity = vec(n)                                # v of the accepted Newton iterate, m/s
        self.rhs = vec(n)                                     # -grad E at that iterate (unfiltered), N s
        self.solution = vec(n)                                # the Newton direction d, m/s
        self.change = vec(n)                                  # v_n - v_(n-1), the last step's change, m/s
        self.r, self.z, self.p, self.Ap = vec(n), vec(n), vec(n), vec(n)
        self.block_inverse = ti.Vector.field(6, float, n)     # Jacobi preconditioner: inverse 3x3 blocks
                                                              # of H, symmetric: (xx, xy, xz, yy, yz, zz)
        self.contact = ti.field(ti.i32, n if self.has_ground else 1)   # 1: on the ground this step
        self.pressed = ti.field(ti.i32, n if self.has_ground else 1)   # 1: the ground pushed it last step
        self.body_floor = ti.field(ti.f64, nb)                # (N s)^2: round-off floor of |grad_b|^2
        self.body_scale = ti.field(ti.f64, nb)                # (N s)^2: s_b^2 of this step
        self.body_weight = ti.field(float, nb)                # 1 / (tol^2 s_b^2 + floor_b)
        self.body_gradient = ti.field(ti.f64, nb)             # |grad_b E|^2
        self.body_change = ti.field(ti.f64, nb)               # |a d_b|_M^2 of the last Newton iteration, J
        self.body_momentum = ti.field(ti.f64, nb)             # |v_b|_M^2, J
        self.body_speed_floor = ti.field(ti.f64, nb)          # round-off floor of |v_b|_M^2, J
        self.body_E = ti.field(ti.f64, nb)                    # E_b at the last trial iterate, J
        self.body_E_accepted = ti.field(ti.f64, nb)           # E_b at the accepted iterate, J
        self.body_resolution = ti.field(ti.f64, nb)           # J: changes of E_b below this are round-off
        self.body_slope = ti.field(ti.f64, nb)                # grad_b E . d_b, J (< 0: d descends for body b)
        self.body_step = ti.field(float, nb)                  # a_b: body b's step along d in the line search
        self.searching = ti.field(ti.i32, nb)                 # 1: body b has not found its decrease yet
        self.body_total = ti.field(ti.f64, (2, nb))           # each body's total energy [BEFORE, AFTER] the step, J
        self.body_total_size = ti.field(ti.f64, (2, nb))      # sum of the sizes of its terms, J
        self.body_mass = ti.field(ti.f64, nb)                 # kg (free vertices only)
        self.body_momentum_vector = ti.Vector.field(3, ti.f64, nb)   # kg m/s
        self.body_pinned = ti.field(ti.i32, nb)               # 1: the body has pinned vertices
        self.awake = ti.field(ti.i32, nb)                     # 0: the body sleeps, the step leaves it be
        self.rz = ti.field(float, ())                         # PCG scalars stay on the device
        self.rr = ti.field(float, ())
        self.cg_beta = ti.field(float, ())
        self.iterations = ti.field(ti.i32, ())
        self.active = ti.field(ti.i32, ())                    # 1 while PCG iterates
        self.dt = ti.field(float, ())                         # s, of the step under way
        self.patches = None                                   # the coarse level (fem/coarse.py), made on first use

    def load(self, effects, settings):
        """Start on the model's current scene: its effects' values and the solver settings
        (read at every step: a window may change them live)."""
        model = self.model
        assert Switches.of(effects, model.n_vertices, model.n_tets, model.has_pins) == self.switches
        self.effects, self.settings = effects, settings
        self.mass_damping[None], self.stiffness_damping[None] = effects.alpha, effects.beta
        self.gravity[None] = effects.gravity or (0.0, 0.0, 0.0)
        self.ground[None] = effects.ground or 0.0
        self.friction[None] = effects.friction
        # the per-body inputs of the kernels, kept here and written together (write_bodies)
        self.pinned_np = np.array([(model.free_np[b.vertices] == 0).any() for b in model.bodies], np.int32)
        self.awake_np = np.ones(len(model.bodies), np.int32)
        self.floor_np = self.speed_floor_np = np.zeros(len(model.bodies))      # set by refresh
        self.model_version = None                             # (model edit, dt) the cached data is for
        self.preconditioner_key = None
        self.omega_key, self.omega = None, None
        self.patches_loaded = False
        self.reset()

    def wake(self, awake):
        """Which bodies the step moves: (bodies,) of 0 (asleep: left exactly as they are) or 1."""
        self.awake_np = np.asarray(awake, np.int32)
        self.write_bodies()
        self.preconditioner_key = None                        # a body that wakes has no blocks yet

    def write_bodies(self):
        """The per-body inputs (pinned, awake, round-off floors) into their fields, in one kernel."""
        self._write_bodies(self.pinned_np, self.awake_np, self.floor_np, self.speed_floor_np)

    def reset(self):
        """Forget everything from earlier steps: rotations, warm starts, ground contacts, sleep."""
        self.wake(np.ones(len(self.model.bodies)))
        self.reset_rotations()
        self.rotated = False
        self.forget_change(contacts=True)
        if self.patches is not None:
            self.patches.reset()

    def forget_change(self, contacts=False):
        """The next step starts its solve from v_n itself: after a new state, the last step's
        velocity change says nothing about the next one. contacts: forget the ground's too."""
        self.clear_history(int(contacts))
        self.preconditioner_key = None                        # the blocks are for other rotations
        self.turned = 0.0                                     # rad: most any tet turned since then
        self.change_dt = 0.0                                  # s, the dt of the step that made `change`
        self.extrapolation = 0.0                              # dt / change_dt: how far to extrapolate

    # ------------------------------------------------------------ the step

    @property
    def preconditioner(self):
        """The PCG preconditioner in use: "two-level" or "jacobi" (block Jacobi); None for Jacobi iteration.
        "auto" takes the two-level one from TWO_LEVEL_VERTICES up, where it wins (docs/benchmark.md)."""
        settings = self.settings
        if settings.method != "pcg":
            return None
        if settings.preconditioner == "auto":
            return "two-level" if self.model.n_vertices >= TWO_LEVEL_VERTICES else "jacobi"
        return settings.preconditioner

    @property
    def two_level(self):
        return self.preconditioner == "two-level"

    def prepare_patches(self, cM, cK, corotational):
        """The coarse level for this step: patches split once per scene, A_c^-1 once per
        materials and dt, the patches' rotations at x_n every corotational step."""
        if self.patches is None:
            self.patches = Patches(self.model, self.serial_vertices)
        if not self.patches_loaded:
            self.patches.load()
            self.patches_loaded = True
        self.patches.refresh(cM, cK)
        if corotational:
            self.patches.update_frames(self.x)

    def coefficients(self, dt):
        """(cM, cK) of H = cM M + cK K: backward Euler with Rayleigh damping."""
        return 1 + dt * self.effects.alpha, dt * self.effects.beta + dt * dt

    def step(self, state_in, state_out, dt):
        """One backward Euler step from state_in into state_out; returns a StepInfo.

        state_in is never written. When the result is not finite, state_out holds garbage
        and the caller keeps state_in (a rejected step is a step not swapped in). The step
        works on the solver's own copies (x0, v0: the start; x, v: the iterate), so every
        kernel is compiled once, not once per State.
        """
        start = time.perf_counter()
        settings, model = self.settings, self.model
        corotational = model.any_corotational
        # linear: one Newton iteration is exact; the naive variant has no energy to minimise
        newton = settings.step == "newton" and corotational and not model.any_naive
        cM, cK = self.coefficients(dt)
        self.refresh(cM, cK, dt)
        self.dt[None] = dt
        self.extrapolation = dt / self.change_dt if self.change_dt > 0 else 0.0   # of the last step's change

        self.begin(state_in.x, state_in.v)
        rotation_ms = self.update_rotations(self.x, corotational, first=True)    # R(x_n)
        if newton:
            self.body_energy(self.x, self.v, BEFORE)          # x, v = x_n, v_n still
        self.start_iterate(self.x0, self.v0, self.x, self.v, dt)
        # Block Jacobi's blocks follow the tets' rotations. PCG only needs them close: in the
        # one-solve step they are rebuilt once some tet turned STALE_TURN since they were built.
        # Newton's twist stiffness changes with the stretch, and Jacobi iteration's weight
        # needs the exact blocks: those rebuild every step. Linear: built once, as H never changes.
        stale = corotational and (newton or settings.method != "pcg" or self.turned > STALE_TURN)
        if stale or self.preconditioner_key != (cM, cK):
            self.build_preconditioner(cM, cK)
            self.preconditioner_key = None if newton else (cM, cK)
            self.turned = 0.0
        if self.two_level:
            self.prepare_patches(cM, cK, corotational)
        tolerance = max(settings.tolerance, ROUNDOFF * epsilon())   # none below round-off
        if newton:
            self.energy(self.v0, self.x, self.v, dt, first=True)   # E_b of every body at the first iterate
            rho = self.gradient_vertices(self.v0, self.v, dt, tolerance, 1)   # its tet terms came with E
            self.accept(self.v, 1)
        else:
            rho = self.gradient(self.v0, self.x, self.v, dt, tolerance, True)

        newton_iters = solver_iters = halvings = 0
        settled = False
        while rho > 1.0 and newton_iters < (settings.max_newton if newton else 1):
            target = 1.0 if not newton else max(1.0, FORCING ** 2 * rho)
            solver_iters += self.solve(self.v0, cM, cK, target, warm=newton_iters == 0)
            newton_iters += 1
            if not newton:
                rho = float(self.rr[None])                    # the linear solve's own residual
                self.try_step(self.x0, self.x, self.v, dt, 0)
                break
            # A line search per body: bodies never interact, so E is a sum of their E_b, and
            # each body halves its own step until its own E_b falls enough (Armijo).
            if self.start_search() == 0:                      # no body's decrement above round-off
                settled = True
                break
            for _ in range(MAX_HALVINGS + 1):
                self.try_step(self.x0, self.x, self.v, dt, 1)
                rotation_ms += self.update_rotations(self.x, True)
                self.energy(self.v0, self.x, self.v, dt)
                if self.armijo() == 0:
                    break
                halvings += 1
            else:                                             # some found no decrease at this precision
                moved = self.give_up()                        # they keep the last iterate
                self.try_step(self.x0, self.x, self.v, dt, 1)
                rotation_ms += self.update_rotations(self.x, True)
                if moved == 0:
                    break
                self.energy(self.v0, self.x, self.v, dt)
            self.accept(self.v, 0)
            change = self.velocity_change(settings.newton_tolerance)
            rho = self.gradient_vertices(self.v0, self.v, dt, tolerance, 0)   # tet terms: with the last E
            if change <= 1.0:                                 # every body's velocity has settled
                settled = True
                break

        if self.has_ground:
            self.ground_reaction(cM, cK, newton)
        bad = self.check_finite(self.x, self.v)
        if not math.isfinite(rho):                            # a NaN in state_in: nothing to trust
            bad = max(bad, 1)
        if bad == 0 and self.has_ground:
            self.ground_contact(self.x, self.v)
        limited = 0
        if bad == 0 and not self.has_ground:
            self.restore_momentum(self.v0, self.x0, self.x, self.v, dt)
        if bad == 0 and newton:
            self.body_energy(self.x, self.v, AFTER)
            limited = self.limit_energy(self.x0, self.x, self.v)
        self.finish(state_out.x, state_out.v, int(bad == 0))
        self.change_dt = dt
        ti.sync()
        residual = tolerance * math.sqrt(max(rho, 0.0))
        wall_ms = 1e3 * (time.perf_counter() - start)
        return StepInfo(finite=bad == 0, converged=bool(rho <= 1.0 or settled),
                        residual=residual if math.isfinite(residual) else None,
                        newton_iters=max(newton_iters, 1), solver_iters=solver_iters,
                        line_search_steps=halvings, energy_limited=limited, rotation_ms=rotation_ms,
                        solve_ms=wall_ms - rotation_ms)

    def refresh(self, cM, cK, dt):
        """Re-derive what depends on the model's methods and materials after a live edit."""
        if (self.model.version, dt) != self.model_version:
            self.model_version = (self.model.version, dt)
            self.preconditioner_key = self.omega_key = None
            self.floor_np = self.model.body_floor(ROUNDOFF * epsilon(), dt)
            self.speed_floor_np = self.model.body_speed_floor(ROUNDOFF * epsilon(), dt)
            self.write_bodies()
            if not self.model.any_corotational and self.rotated:
                self.reset_rotations()                        # every body switched to linear: unrotate
                self.rotated = False
        if self.settings.method == "jacobi":
            self.jacobi_weight(cM, cK)

    def update_rotations(self, x, corotational, first=False):
        """Rotations at positions x (when some body is corotational); returns the time spent (ms).
        first: at x_n, the step's first; its Newton steps start from the last step's turn, extrapolated."""
        if not corotational:
            return 0.0
        start = time.perf_counter()
        newton = int(self.settings.step == "newton" and not self.model.any_naive)   # twist stiffness
        svd = self.settings.rotations == "svd"
        left = self.extract_rotations(x, svd, newton, int(first), self.extrapolation)
        if left > 0:
            self.svd_rotations(x, newton, int(first))
        if first:                                             # how far the blocks' rotations are off, at most
            turn = math.sqrt(min(float(self.largest_turn[None]), 1.0))
            self.turned = math.inf if left > 0 else self.turned + 2.0 * math.asin(turn)
        self.rotated = True
        ti.sync()
        return 1e3 * (time.perf_counter() - start)

    def solve(self, v0, cM, cK, target, warm):
        """H d = -grad E until the weighted residual sum_b |r_b|^2 w_b <= target; returns iterations."""
        self.start_direction(v0, int(warm), self.extrapolation)
        if self.settings.method == "pcg":
            two_level = self.two_level
            self.stiffness_product(self.solution)
            if self.start_residual(cM, cK, two_level) > target:
                while self.cg_iterations(cM, cK, target, self.settings.max_iterations, CG_UNROLL, two_level):
                    pass
            return int(self.iterations[None])
        iterations = 0
        while iterations < self.settings.max_iterations:
            self.stiffness_product(self.solution)
            self.rr[None] = self.jacobi_update(cM, cK, self.omega)
            iterations += 1
            if self.rr[None] <= target:
                break
        return iterations

    def jacobi_weight(self, cM, cK):
        """omega = 1.5 / lambda_max(P H), lambda_max from 30 power iterations (rotations ignored:
        they barely move the spectrum), so the iteration cannot diverge (needs omega < 2 / lambda_max)."""
        if self.settings.jacobi_omega:
            self.omega = self.settings.jacobi_omega
            return
        key = (cM, cK)
        if key != self.omega_key:
            self.build_preconditioner(cM, cK)
            self.preconditioner_key = None
            P = self.block_inverses()
            u = np.random.default_rng(0).standard_normal((self.model.n_vertices, 3))
            lam = 1.0
            for _ in range(30):
                u /= np.linalg.norm(u)
                w = np.einsum("nij,nj->ni", P, self.apply_matrix(u, cM, cK))
                lam = float(np.vdot(u, w)) if np.vdot(u, u) > 0 else 1.0
                u = w
            self.omega, self.omega_key = 1.5 / max(lam, 1e-12), key

    def apply_matrix(self, u, cM, cK):
        """H u for a (n, 3) numpy array u with the current rotations (for checks and tests)."""
        self.model.write(self.p, u)
        self.stiffness_product(self.p)
        self.matrix_product(self.p, self.Ap, cM, cK)
        return self.Ap.to_numpy()[:self.model.n_vertices].astype(np.float64)

    def apply_preconditioner(self, r):
        """P r for a (n, 3) numpy array r, with the preconditioner of the last step (for checks and tests)."""
        self.model.write(self.r, r)
        self.preconditioner_product(self.two_level)
        return self.z.to_numpy()[:self.model.n_vertices].astype(np.float64)

    @ti.kernel
    def preconditioner_product(self, two_level: ti.template()):
        if ti.static(two_level):
            self.two_level_precondition(1)
        else:
            for i in range(self.model.vertex_count[None]):
                self.z[i] = self.filtered(i, self.jacobi(i, self.r[i]))

    # ------------------------------------------------------------ per-tet kernels

    @ti.kernel
    def reset_rotations(self):
        """Every tet unrotated: R = I and rotated_Bm = Bm (what linear tets always use)."""
        ti.loop_config(serialize=self.serial_tets)
        for e in range(self.model.tet_count[None]):
            self.quaternions[e] = ti.Vector([0.0, 0.0, 0.0, 1.0])
            if ti.static(self.has_stiffness_damping):
                self.damping_frame[e] = self.quaternions[e]
            self.turn[e] = ti.Vector.zero(float, 3)
            self.rotated_Bm[e] = self.model.Bm[e]
            self.twist[e] = 0.0

    @ti.func
    def tet_awake(self, e):
        return self.awake[self.model.tet_body[e]]

    @ti.func
    def edges(self, x: ti.template(), e):
        """Ds of tet e for the vertex values x (positions, velocities or directions)."""
        t = self.model.tets[e]
        return edge_matrix(x[t[0]], x[t[1]], x[t[2]], x[t[3]])

    @ti.kernel
    def extract_rotations(self, x: ti.template(), svd: ti.template(), newton: ti.i32, first: ti.i32,
                          scale: float) -> ti.i32:
        """R = polar rotation of F for every corotational tet, kept as rotated_Bm = Bm R^T.

        svd=False: warm-started Newton steps from last time's R; a tet where they do not
        certify their answer (a start far off, an inverted tet) is left for `svd_rotations`.
        first=1 (at x_n): they start from last time's R turned on by the last step's turn
        (times `scale`, the ratio of the dts; 0: no last step) and record this step's turn,
        and R_n as the frame of the step's stiffness damping.
        On a turning body one step then certifies R where the last R alone needs two.
        svd=True: every corotational tet is left for it (the reference).
        newton=1 also sets each tet's twist stiffness (below); 0 leaves it 0 (the one-solve step).
        Returns how many tets were left. The SVD lives in its own kernel, compiled only when a
        run first needs it: it is most of the compile time.
        """
        left = 0
        self.largest_turn[None] = 0.0
        ti.loop_config(serialize=self.serial_tets)
        for e in range(self.model.tet_count[None]):
            self.needs_svd[e] = 0
            if not self.tet_awake(e):            # a sleeping body keeps its rotations
                continue
            if self.model.method(e):
                if ti.static(svd):
                    self.needs_svd[e] = 1
                    left += 1
                else:
                    F = self.edges(x, e) @ self.model.Bm[e]
                    last = self.quaternions[e]
                    start = last
                    if first:
                        start = quaternion_product(self.turn_quaternion(e, scale), last).normalized()
                    q, converged = newton_rotation(F, start)
                    self.set_rotation(e, F, quaternion_matrix(q), q, newton, first)
                    if first:
                        turn = quaternion_product(q, conjugate(last))
                        if turn[3] < 0:                  # -p is the same turn: keep w >= 0
                            turn = -turn
                        t = ti.Vector([turn[0], turn[1], turn[2]]) * (scale > 0 and converged)
                        self.turn[e] = t
                        ti.atomic_max(self.largest_turn[None], t.norm_sqr())
                    if not converged:
                        self.needs_svd[e] = 1
                        left += 1
            else:
                self.turn[e] = ti.Vector.zero(float, 3)
                self.twist[e] = 0.0
                self.quaternions[e] = ti.Vector([0.0, 0.0, 0.0, 1.0])
                if ti.static(self.has_stiffness_damping):
                    self.damping_frame[e] = self.quaternions[e]
                self.rotated_Bm[e] = self.model.Bm[e]
        return left

    @ti.func
    def turn_quaternion(self, e, scale):
        """The last step's turn of tet e, its angle times `scale`, as a unit quaternion."""
        v = scale * self.turn[e]
        return ti.Vector([v[0], v[1], v[2], ti.sqrt(ti.max(1.0 - v.norm_sqr(), 0.0))])

    @ti.kernel
    def svd_rotations(self, x: ti.template(), newton: ti.i32, first: ti.i32):
        """The polar rotation from the SVD (`polar_rotation`) for the tets left by extract_rotations."""
        ti.loop_config(serialize=self.serial_tets)
        for e in range(self.model.tet_count[None]):
            if self.needs_svd[e]:
                F = self.edges(x, e) @ self.model.Bm[e]
                R = polar_rotation(F)
                self.set_rotation(e, F, R, quaternion_of(R), newton, first)

    @ti.func
    def set_rotation(self, e, F, R, q, newton, first):
        self.quaternions[e] = q                               # the next warm start
        if ti.static(self.has_stiffness_damping):
            if first:
                self.damping_frame[e] = q                     # D = alpha M + beta K(R_n) for the whole step
        self.rotated_Bm[e] = self.model.Bm[e] @ R.transpose()
        twist = 0.0
        if newton:
            twist = twist_stiffness((R.transpose() @ F).trace(), self.model.mu(e), self.model.lam(e))
        self.twist[e] = twist

    # The Newton matrix R Ke R^T misses the curvature of Psi when a tet turns: the "twist"
    # modes (skew parts of R^T dF) get none, where the exact Hessian of the corotated energy
    # gives (psi_i + psi_j) / (s_i + s_j) for singular values s_i, s_j (Smith et al. 2019,
    # "Analytic eigensystems for isotropic distortion energies"): positive in a stretched
    # tet, and for a near-incompressible one far larger than mu. Without it Newton overshoots
    # and the line search halves every step; `twist` adds it, projected to >= 0 and with all
    # s_i taken equal to their mean (tr S / 3), as lam_t |skew(R^T dF)|^2.

    @ti.func
    def damping_Bm(self, e):
        """Bm R_n^T of tet e: the damping stiffness K_n uses the rotations at the step's start."""
        return self.model.Bm[e] @ quaternion_matrix(self.damping_frame[e]).transpose()

    # Corotational FEM without a rotation in the inner loop: sigma is isotropic, so
    #     R sigma(sym(R^T F) - I) Bm^T = sigma(sym(Ds Bm R^T) - I) (Bm R^T)^T,
    # i.e. f = -R Ke (R^T x - X) is the linear formula with Bm replaced by Bm R^T
    # (rotated_Bm). Linear tets keep rotated_Bm = Bm.

    @ti.func
    def tet_stiffness(self, e, u: ti.template(), w: ti.template(), beta):
        """corner <- one tet's share of K(R) d for the direction d = u + beta w (N/m times m/s).
        Taking d = z + beta p here fuses the CG direction update into this pass."""
        t = self.model.tets[e]
        d0, d1 = u[t[0]] + beta * w[t[0]], u[t[1]] + beta * w[t[1]]
        d2, d3 = u[t[2]] + beta * w[t[2]], u[t[3]] + beta * w[t[3]]
        B = self.rotated_Bm[e]
        dF = edge_matrix(d0, d1, d2, d3) @ B
        eps = 0.5 * (dF + dF.transpose())
        P = linear_stress(eps, self.model.mu(e), self.model.lam(e)) + self.twist[e] * (dF - eps)
        self.store_corners(e, corner_forces(-P, B, self.model.rest_volume[e]))

    @ti.kernel
    def stiffness_product(self, u: ti.template()):
        """corner <- (K(R) u)_e per tet."""
        ti.loop_config(serialize=self.serial_tets)
        for e in range(self.model.tet_count[None]):
            if self.tet_awake(e):
                self.tet_stiffness(e, u, u, 0.0)

    @ti.func
    def store_corners(self, e, f: ti.template()):
        for k in ti.static(range(4)):
            self.corner[4 * e + k] = f[k]

    @ti.func
    def elastic_stress(self, x: ti.template(), e):
        """sigma(sym(F R^T) - I) of tet e at positions x: the stress in the tet's rotated frame (Pa).

        The naive variant f = -R Ke R^T (x - X) rotates the rest shape too: its strain is
        sym(R^T (F - I)), in this frame sym(F R^T) - sym(R^T), not zero under a pure rotation."""
        F = self.edges(x, e) @ self.rotated_Bm[e]               # F R^T
        unstrained = ti.Matrix.identity(float, 3)
        if self.model.method(e) == NAIVE:
            Rt = quaternion_matrix(self.quaternions[e]).transpose()
            unstrained = 0.5 * (Rt + Rt.transpose())
        eps = 0.5 * (F + F.transpose()) - unstrained
        return linear_stress(eps, self.model.mu(e), self.model.lam(e))

    @ti.kernel
    def gradient_corners(self, x: ti.template(), v: ti.template(), dt: float, moving: ti.i32):
        """corner <- the tet terms of grad E: -dt f_e(x) + dt beta (K_n v)_e.
        moving=0: v is 0 (the step's first iterate, no ground), so the damping term is too."""
        ti.loop_config(serialize=self.serial_tets)
        for e in range(self.model.tet_count[None]):
            self.gradient_tet(x, v, dt, moving, e)

    @ti.func
    def gradient_tet(self, x: ti.template(), v: ti.template(), dt, moving, e):
        """corner <- tet e's terms of grad E (gradient_corners). Returns the Bm R_n^T its damping
        term used (0 without one), for energy_tets to reuse."""
        W = self.model.rest_volume[e] * self.tet_awake(e)           # a sleeping body's tets add nothing
        self.store_corners(e, corner_forces(-dt * self.elastic_stress(x, e), self.rotated_Bm[e], W))
        B = ti.Matrix.zero(float, 3, 3)
        if ti.static(self.has_stiffness_damping) and moving:
            B = self.damping_Bm(e)
            dF = self.edges(v, e) @ B
            eps = 0.5 * (dF + dF.transpose())
            P = linear_stress(eps, self.model.mu(e), self.model.lam(e))
            f = corner_forces(-dt * self.stiffness_damping[None] * P, B, W)
            for k in ti.static(range(4)):
                self.corner[4 * e + k] += f[k]
        return B

    @ti.kernel
    def energy_tets(self, x: ti.template(), v: ti.template(), dt: float, moving: ti.i32):
        """body_E[b] += Psi_b(x) + dt beta/2 v_b^T K_n v_b, summed in float64 (J), a chunk of
        tets at a time (as in body_energy); corner <- the tet terms of grad E at (x, v), in the
        same pass: a trial iterate the line search accepts needs its gradient next.
        moving=0: v is 0 (as in gradient_corners), so the damping terms are too."""
        n = self.model.tet_count[None]
        ti.loop_config(serialize=self.serial_tets)
        for c in range((n + TET_CHUNK - 1) // TET_CHUNK):
            body, total = -1, ti.cast(0.0, ti.f64)
            for e in range(c * TET_CHUNK, ti.min(n, (c + 1) * TET_CHUNK)):
                if self.model.tet_body[e] != body:
                    if body >= 0:
                        self.body_E[body] += total
                    body, total = self.model.tet_body[e], 0.0
                B = self.gradient_tet(x, v, dt, moving, e)
                awake = ti.cast(self.tet_awake(e), ti.f64)
                total += awake * self.elastic_energy(x, e)
                if ti.static(self.has_stiffness_damping) and moving:
                    W = ti.cast(self.model.rest_volume[e], ti.f64)
                    mu, lam = ti.cast(self.model.mu(e), ti.f64), ti.cast(self.model.lam(e), ti.f64)
                    dF = ti.cast(self.edges(v, e), ti.f64) @ ti.cast(B, ti.f64)
                    beta = ti.cast(dt * self.stiffness_damping[None], ti.f64)
                    total += awake * beta * W * energy_density(dF, mu, lam, 0.0)
            if body >= 0:
                self.body_E[body] += total

    @ti.func
    def elastic_energy(self, x: ti.template(), e):
        """Psi_e(x) = W psi(F R^T) of tet e at positions x, in float64 (J), R as extracted."""
        F = ti.cast(self.edges(x, e), ti.f64) @ ti.cast(self.rotated_Bm[e], ti.f64)
        return ti.cast(self.model.rest_volume[e], ti.f64) * energy_density(
            F, ti.cast(self.model.mu(e), ti.f64), ti.cast(self.model.lam(e), ti.f64), 1.0)

    # ------------------------------------------------------------ per-vertex kernels

    @ti.func
    def gather(self, i):
        """Sum of the corner values of every tet around vertex i."""
        s = ti.Vector.zero(float, 3)
        for j in range(self.model.adjacency_start[i], self.model.adjacency_start[i + 1]):
            s += self.corner[self.model.adjacency[j]]
        return s

    @ti.func
    def filtered(self, i, a):
        """Zero the constrained rows: pinned vertices, and the normal of those on the ground
        (filtered CG, Baraff & Witkin 1998)."""
        if ti.static(self.pins):
            a *= self.model.free[i]
        if ti.static(self.has_ground):
            if self.contact[i]:
                a[1] = 0.0
        return a * self.awake[self.model.vertex_body[i]]    # a sleeping body is held like a pinned one

    @ti.func
    def apply_H(self, i, u: ti.template(), cM, cK):
        """(H u)_i = cM m_i u_i + cK (K u)_i, filtered; K u gathered from `corner`."""
        return self.filtered(i, cM * self.model.mass[i] * u[i] + cK * self.gather(i))

    @ti.func
    def gravity_vector(self):
        return self.gravity[None]

    @ti.kernel
    def finish(self, x: ti.template(), v: ti.template(), good: ti.i32):
        """state_out <- the iterate; change <- v - v_n for the next step's first guess
        (0 after a step whose result is not finite)."""
        ti.loop_config(serialize=self.serial_vertices)
        for i in range(self.model.vertex_count[None]):
            x[i], v[i] = self.x[i], self.v[i]
            dv = ti.Vector.zero(float, 3)
            if good:
                dv = self.v[i] - self.v0[i]
            self.change[i] = dv

    @ti.kernel
    def begin(self, x: ti.template(), v: ti.template()):
        """x0, v0 <- the step's start; the iterate x, v too (also how checks copy a state in)."""
        ti.loop_config(serialize=self.serial_vertices)
        for i in range(self.model.vertex_count[None]):
            self.x0[i], self.v0[i] = x[i], v[i]
            self.x[i], self.v[i] = x[i], v[i]

    @ti.kernel
    def start_iterate(self, x0: ti.template(), v0: ti.template(), x: ti.template(), v: ti.template(),
                      dt: float):
        """The first Newton iterate: v = 0, except the normal velocity of vertices on the ground,
        prescribed so that they land on the plane (the ground's active set is chosen here)."""
        ti.loop_config(serialize=self.serial_vertices)
        for i in range(self.model.vertex_count[None]):
            u = ti.Vector.zero(float, 3)
            if ti.static(self.has_ground):
                self.contact[i] = 0
                awake = self.awake[self.model.vertex_body[i]]
                if awake and self.model.free[i] > 0 and (x0[i][1] + dt * v0[i][1] < self.ground[None]
                                                         or self.pressed[i]):
                    self.contact[i] = 1
                    u[1] = (self.ground[None] - x0[i][1]) / dt
            self.velocity[i] = u
            v[i] = u
            x[i] = x0[i] + dt * u

    @ti.kernel
    def gradient_vertices(self, v0: ti.template(), v: ti.template(), dt: float, tolerance: ti.f64,
                          first: ti.i32) -> ti.f64:
        """rhs <- -grad E = M v_n + dt M g - (1 + dt alpha) M v - (gathered tet terms), and the
        per-body |grad_b|^2; on the step's first call also the per-body scale s_b^2.
        Returns `gradient_norm`."""
        ti.loop_config(serialize=True)
        for b in range(self.model.body_count[None]):
            self.body_gradient[b] = 0.0
            if first:
                self.body_scale[b], self.body_momentum[b] = 0.0, 0.0
        ti.loop_config(serialize=self.serial_vertices)
        for i in range(self.model.vertex_count[None]):
            m = self.model.mass[i]
            g = ti.Vector.zero(float, 3)
            if ti.static(self.has_gravity):
                g = dt * m * self.gravity_vector()
            tets = self.gather(i)
            rhs = m * v0[i] + g - (1.0 + dt * self.mass_damping[None]) * m * v[i] - tets
            self.rhs[i] = rhs
            b = self.model.vertex_body[i]
            self.body_gradient[b] += ti.cast(self.filtered(i, rhs).norm_sqr(), ti.f64)
            if first:   # |M v_n|^2 + |dt f|^2 + |dt M g|^2: not |rhs|^2, which is ~0 at rest
                momentum = ti.cast(self.filtered(i, m * v0[i]).norm_sqr(), ti.f64)
                self.body_momentum[b] += momentum
                self.body_scale[b] += momentum + ti.cast(self.filtered(i, tets).norm_sqr()
                                                         + self.filtered(i, g).norm_sqr(), ti.f64)
        return self.gradient_norm(tolerance, first)

    @ti.func
    def gradient_norm(self, tolerance, first):
        """sum_b |grad_b|^2 / (tol^2 s_b^2 + floor_b): <= 1 exactly when every body has
        converged, relative to its own scale s_b or below its round-off floor.
        On the first call a body whose momentum |M v_n| is above the floor counts as not
        converged: v = 0 is no answer for a moving body, even one so stiff (in f32) that its
        whole gradient is below the floor; it would stop dead."""
        rho = ti.cast(0.0, ti.f64)
        ti.loop_config(serialize=True)
        for b in range(self.model.body_count[None]):
            if first:
                self.body_weight[b] = ti.cast(1.0 / (tolerance * tolerance * self.body_scale[b]
                                                     + self.body_floor[b]), float)
                if self.body_momentum[b] > self.body_floor[b]:
                    rho += 2.0
            rho += self.body_gradient[b] / (tolerance * tolerance * self.body_scale[b] + self.body_floor[b])
        return rho

    def gradient(self, v0, x, v, dt, tolerance, first):
        """-grad E at (x, v) into rhs; returns the weighted norm rho (converged: rho <= 1)."""
        self.gradient_corners(x, v, dt, int(not first or self.has_ground))   # first: v = 0 off the ground
        return self.gradient_vertices(v0, v, dt, tolerance, int(first))

    @ti.kernel
    def energy_vertices(self, v0: ti.template(), v: ti.template(), dt: float):
        """body_E[b] <- 1/2 |v_b - v_n|_M^2 + dt alpha/2 |v_b|_M^2 - dt v_b^T M g, in float64 (J)."""
        ti.loop_config(serialize=True)
        for b in range(self.model.body_count[None]):
            self.body_E[b] = 0.0
        ti.loop_config(serialize=self.serial_vertices)
        for i in range(self.model.vertex_count[None]):
            m = ti.cast(self.model.mass[i], ti.f64)
            u, u0 = ti.cast(v[i], ti.f64), ti.cast(v0[i], ti.f64)
            e = 0.5 * m * ((u - u0).norm_sqr() + dt * self.mass_damping[None] * u.norm_sqr())
            if ti.static(self.has_gravity):
                e -= dt * m * u.dot(ti.cast(self.gravity_vector(), ti.f64))
            self.body_E[self.model.vertex_body[i]] += e

    def energy(self, v0, x, v, dt, first=False):
        """E_b(v) of every body at x = x_n + dt v into body_E (J, float64), with the rotations at
        x already extracted, and the tet terms of grad E there (gradient_vertices finishes it).
        E = sum_b E_b is what a Newton iteration minimises."""
        self.energy_vertices(v0, v, dt)
        self.energy_tets(x, v, dt, int(not first or self.has_ground))   # first: v = 0 off the ground

    @ti.kernel
    def velocity_change(self, tolerance: ti.f64) -> ti.f64:
        """sum_b |a_b d_b|_M^2 / (tol^2 |v_b|_M^2 + floor_b): <= 1 exactly when no body's velocity
        moved by more than tol of its size (or by round-off) in the last Newton iteration."""
        ti.loop_config(serialize=True)
        for b in range(self.model.body_count[None]):
            self.body_change[b], self.body_momentum[b] = 0.0, 0.0
        ti.loop_config(serialize=self.serial_vertices)
        for i in range(self.model.vertex_count[None]):
            m = ti.cast(self.model.mass[i], ti.f64)
            b = self.model.vertex_body[i]
            self.body_change[b] += m * ti.cast(self.body_step[b] * self.solution[i], ti.f64).norm_sqr()
            self.body_momentum[b] += m * ti.cast(self.velocity[i], ti.f64).norm_sqr()
        change = ti.cast(0.0, ti.f64)
        ti.loop_config(serialize=True)
        for b in range(self.model.body_count[None]):
            change += self.body_change[b] / (tolerance * tolerance * self.body_momentum[b] + self.body_speed_floor[b])
        return change

    # Backward Euler with a non-convex energy (corotated elasticity is not convex: a compressed
    # tet's twist curvature is negative) can end a step with more energy than it began,
    # even when solved exactly: thin, bending or buckling bodies do. The promise that total
    # energy never rises is kept by a last safeguard: a body whose kinetic + elastic +
    # gravitational energy rose has its velocities relative to its centre of mass scaled
    # down by just enough (positions and linear momentum untouched); a body whose rise is
    # more than that motion holds (nearly at rest) keeps its old positions, at rest.
    # StepInfo counts both.

    @ti.kernel
    def body_energy(self, x: ti.template(), v: ti.template(), when: ti.i32):
        """body_total[when, b] <- kinetic + elastic + gravitational energy of body b (J, float64),
        elastic with the rotations extracted at x; body_total_size[when, b] <- the sum of the
        sizes of its terms (J), the scale of its round-off. when: BEFORE or AFTER the step."""
        ti.loop_config(serialize=True)
        for b in range(self.model.body_count[None]):
            self.body_total[when, b], self.body_total_size[when, b] = 0.0, 0.0
        # A body's tets are contiguous: each chunk of tets sums into a running total and adds it
        # to body_total once per body it meets, not once per tet (threads would fight over it).
        n = self.model.tet_count[None]
        ti.loop_config(serialize=self.serial_tets)
        for c in range((n + TET_CHUNK - 1) // TET_CHUNK):
            body, elastic = -1, ti.cast(0.0, ti.f64)
            for e in range(c * TET_CHUNK, ti.min(n, (c + 1) * TET_CHUNK)):
                if self.model.tet_body[e] != body:
                    if body >= 0:
                        self.body_total[when, body] += elastic
                        self.body_total_size[when, body] += elastic
                    body, elastic = self.model.tet_body[e], 0.0
                elastic += self.elastic_energy(x, e)
            if body >= 0:
                self.body_total[when, body] += elastic
                self.body_total_size[when, body] += elastic
        ti.loop_config(serialize=self.serial_vertices)
        for i in range(self.model.vertex_count[None]):
            m = ti.cast(self.model.mass[i], ti.f64)
            kinetic, potential = 0.5 * m * ti.cast(v[i], ti.f64).norm_sqr(), ti.cast(0.0, ti.f64)
            if ti.static(self.has_gravity):
                potential = -m * ti.cast(self.gravity_vector(), ti.f64).dot(ti.cast(x[i], ti.f64))
            self.body_total[when, self.model.vertex_body[i]] += kinetic + potential
            self.body_total_size[when, self.model.vertex_body[i]] += kinetic + ti.abs(potential)

    @ti.kernel
    def limit_energy(self, x0: ti.template(), x: ti.template(), v: ti.template()) -> ti.i32:
        """Scale v - v_cm of every body whose energy rose (v_cm = 0 for pinned bodies) so that
        its kinetic energy falls by the rise. Where the rise exceeds that kinetic energy (a body
        nearly at rest in a non-convex state), the body stays where it was, at rest.
        Returns how many bodies were limited."""
        ti.loop_config(serialize=True)
        for b in range(self.model.body_count[None]):
            self.body_mass[b] = 0.0
            self.body_momentum_vector[b] = ti.Vector.zero(ti.f64, 3)
            self.body_change[b] = 0.0
        ti.loop_config(serialize=self.serial_vertices)
        for i in range(self.model.vertex_count[None]):
            m = ti.cast(self.model.mass[i] * self.model.free[i], ti.f64)
            b = self.model.vertex_body[i]
            self.body_mass[b] += m
            self.body_momentum_vector[b] += m * ti.cast(v[i], ti.f64)
        ti.loop_config(serialize=self.serial_vertices)
        for i in range(self.model.vertex_count[None]):     # kinetic energy of the motion relative to the centre of mass
            b = self.model.vertex_body[i]
            m = ti.cast(self.model.mass[i] * self.model.free[i], ti.f64)
            u = ti.cast(v[i], ti.f64) - self.centre_velocity(b)
            self.body_change[b] += 0.5 * m * u.norm_sqr()
        limited = 0
        ti.loop_config(serialize=True)
        for b in range(self.model.body_count[None]):
            rise = self.body_total[AFTER, b] - self.body_total[BEFORE, b]
            noise = ti.static(ROUNDOFF * epsilon()) * ti.max(self.body_total_size[BEFORE, b],
                                                               self.body_total_size[AFTER, b])
            scale = ti.cast(1.0, ti.f64)
            if rise > noise:                     # a rise within round-off is no rise
                limited += 1
                if self.body_change[b] > rise:
                    scale = ti.sqrt(1.0 - rise / self.body_change[b])
                else:
                    scale = -1.0                 # cannot be absorbed: keep x_n, at rest
            self.body_change[b] = scale          # reused: the factor per body
        ti.loop_config(serialize=self.serial_vertices)
        for i in range(self.model.vertex_count[None]):
            b = self.model.vertex_body[i]
            if self.body_change[b] < 0.0:
                c = ti.cast(self.centre_velocity(b), float) * self.model.free[i]
                x[i], v[i] = x0[i] + self.dt[None] * c, c
            elif self.body_change[b] < 1.0:
                c = self.centre_velocity(b)
                v[i] = ti.cast((c + self.body_change[b] * (ti.cast(v[i], ti.f64) - c)) * self.model.free[i], float)
        return limited

    @ti.kernel
    def restore_momentum(self, v0: ti.template(), x0: ti.template(), x: ti.template(), v: ti.template(),
                         dt: float):
        """Shift each unpinned body's velocity uniformly so that its momentum is exactly backward
        Euler's, (1 + dt alpha) sum m v = sum m v_n + dt M g: an inexact Newton solve leaves a
        residual whose sum is not zero, and internal forces can never change momentum."""
        ti.loop_config(serialize=True)
        for b in range(self.model.body_count[None]):
            self.body_mass[b] = 0.0
            self.body_momentum_vector[b] = ti.Vector.zero(ti.f64, 3)
        ti.loop_config(serialize=self.serial_vertices)
        for i in range(self.model.vertex_count[None]):
            m = ti.cast(self.model.mass[i], ti.f64)
            b = self.model.vertex_body[i]
            g = ti.Vector.zero(ti.f64, 3)
            if ti.static(self.has_gravity):
                g = dt * ti.cast(self.gravity_vector(), ti.f64)
            self.body_mass[b] += m
            self.body_momentum_vector[b] += m * ((ti.cast(v0[i], ti.f64) + g) / (1.0 + dt * self.mass_damping[None])
                                                 - ti.cast(v[i], ti.f64))
        ti.loop_config(serialize=self.serial_vertices)
        for i in range(self.model.vertex_count[None]):
            b = self.model.vertex_body[i]
            if self.body_pinned[b] == 0 and self.body_mass[b] > 0 and self.awake[b]:
                u = ti.cast(self.body_momentum_vector[b] / self.body_mass[b], float)
                v[i] += u
                x[i] = x0[i] + dt * v[i]

    @ti.func
    def centre_velocity(self, b):
        c = ti.Vector.zero(ti.f64, 3)
        if self.body_pinned[b] == 0 and self.body_mass[b] > 0:
            c = self.body_momentum_vector[b] / self.body_mass[b]
        return c

    @ti.kernel
    def start_search(self) -> ti.i32:
        """body_slope[b] <- grad_b E . d_b (J, < 0 where d descends). A body whose decrease
        -slope_b is above the round-off of its E_b searches, from a_b = 1; the others have
        nothing left to gain (a_b = 0). Returns how many bodies search."""
        ti.loop_config(serialize=True)
        for b in range(self.model.body_count[None]):
            self.body_slope[b] = 0.0
        ti.loop_config(serialize=self.serial_vertices)
        for i in range(self.model.vertex_count[None]):
            slope = -self.filtered(i, self.rhs[i]).dot(self.solution[i])
            self.body_slope[self.model.vertex_body[i]] += ti.cast(slope, ti.f64)
        count = 0
        ti.loop_config(serialize=True)
        for b in range(self.model.body_count[None]):
            self.searching[b] = int(-self.body_slope[b] > self.body_resolution[b])
            self.body_step[b] = self.searching[b]
            count += self.searching[b]
        return count

    @ti.kernel
    def armijo(self) -> ti.i32:
        """A searching body whose E_b fell by at least ARMIJO a_b |slope_b| is done; the others
        halve a_b. Returns how many still search."""
        left = 0
        ti.loop_config(serialize=True)
        for b in range(self.model.body_count[None]):
            if self.searching[b]:
                if self.body_E[b] <= self.body_E_accepted[b] + ARMIJO * self.body_step[b] * self.body_slope[b]:
                    self.searching[b] = 0
                else:
                    self.body_step[b] *= 0.5
                    left += 1
        return left

    @ti.kernel
    def give_up(self) -> ti.i32:
        """Bodies that found no decrease (at this precision) stay where they are: a_b = 0.
        Returns how many bodies still move."""
        moving = 0
        ti.loop_config(serialize=True)
        for b in range(self.model.body_count[None]):
            if self.searching[b]:
                self.body_step[b] = 0.0
            moving += int(self.body_step[b] > 0)
        return moving

    @ti.kernel
    def try_step(self, x0: ti.template(), x: ti.template(), v: ti.template(), dt: float, each: ti.i32):
        """v <- velocity + a d, x <- x_n + dt v: a point on the Newton direction, a = 1 for
        every body, or (each = 1) each body's own step a_b."""
        ti.loop_config(serialize=self.serial_vertices)
        for i in range(self.model.vertex_count[None]):
            a = 1.0
            if each:
                a = self.body_step[self.model.vertex_body[i]]
            u = self.velocity[i] + a * self.solution[i]
            v[i] = u
            x[i] = x0[i] + dt * u

    @ti.kernel
    def accept(self, v: ti.template(), first: ti.i32):
        """The iterate v (and its energies E_b) becomes the accepted one; on the step's first
        iterate E_b also sets its resolution, the round-off of a float64 sum of that size."""
        ti.loop_config(serialize=True)
        for b in range(self.model.body_count[None]):
            self.body_E_accepted[b] = self.body_E[b]
            if first:
                self.body_resolution[b] = ti.static(ROUNDOFF * epsilon()) * ti.abs(self.body_E[b])
        ti.loop_config(serialize=self.serial_vertices)
        for i in range(self.model.vertex_count[None]):
            self.velocity[i] = v[i]

    @ti.kernel
    def start_direction(self, v0: ti.template(), warm: ti.i32, scale: float):
        """d <- filtered v_n + scale (v_n - v_(n-1)) - v, or 0. On the first Newton iteration
        the velocity extrapolated with the last step's change (scaled by the ratio of the dts)
        is a good guess: on a turning body it takes a quarter to a third of PCG's iterations
        off (docs/method.md, section 7)."""
        ti.loop_config(serialize=self.serial_vertices)
        for i in range(self.model.vertex_count[None]):
            d = ti.Vector.zero(float, 3)
            if warm:
                d = self.filtered(i, v0[i] + scale * self.change[i] - self.velocity[i])
            self.solution[i] = d

    @ti.kernel
    def build_preconditioner(self, cM: float, cK: float):
        """block_inverse <- inverse of the 3x3 diagonal blocks of H = cM M + cK K(R).
        A loop over vertices with the work of a loop over tets (every corner): threaded like one."""
        ti.loop_config(serialize=self.serial_tets)
        for i in range(self.model.vertex_count[None]):
            if not self.awake[self.model.vertex_body[i]]:      # filtered to 0 while asleep
                continue
            # a pinned vertex keeps an identity block, so the inverse exists even where mass is 0
            block = (cM * self.model.mass[i] + 1.0 - self.model.free[i]) * ti.Matrix.identity(float, 3)
            for j in range(self.model.adjacency_start[i], self.model.adjacency_start[i + 1]):
                slot = self.model.adjacency[j]
                e, k = slot // 4, slot % 4
                B = self.rotated_Bm[e]
                h = -(B[0, :] + B[1, :] + B[2, :])       # rotated shape gradient of corner k
                if k < 3:
                    h = B[k, :]
                W = self.model.rest_volume[e]
                block += cK * (stiffness_block(h, W, self.model.mu(e), self.model.lam(e))
                               + 0.5 * W * self.twist[e] * (h.dot(h) * ti.Matrix.identity(float, 3)
                                                            - h.outer_product(h)))
            inv = block.inverse()
            self.block_inverse[i] = ti.Vector([inv[0, 0], inv[0, 1], inv[0, 2],
                                               inv[1, 1], inv[1, 2], inv[2, 2]])

    @ti.func
    def jacobi(self, i, r):
        """D_i^-1 r: vertex i's inverse diagonal block of H times r."""
        s = self.block_inverse[i]
        return ti.Vector([s[0] * r[0] + s[1] * r[1] + s[2] * r[2],
                          s[1] * r[0] + s[3] * r[1] + s[4] * r[2],
                          s[2] * r[0] + s[4] * r[1] + s[5] * r[2]])

    def block_inverses(self):
        """(n, 3, 3) numpy: every vertex's D_i^-1 (for checks and tests)."""
        s = self.block_inverse.to_numpy()[:self.model.n_vertices].astype(np.float64)
        return s[:, [[0, 1, 2], [1, 3, 4], [2, 4, 5]]]

    @ti.kernel
    def start_residual(self, cM: float, cK: float, two_level: ti.template()) -> float:
        """r <- filtered(rhs) - H d, z <- P r, rz <- r.z (after stiffness_product(d)).
        Returns the weighted residual sum_i w_b(i) |r_i|^2."""
        rz, rr = 0.0, 0.0
        ti.loop_config(serialize=self.serial_vertices)
        for i in range(self.model.vertex_count[None]):
            r = self.filtered(i, self.rhs[i]) - self.apply_H(i, self.solution, cM, cK)
            self.r[i] = r
            self.p[i] = ti.Vector.zero(float, 3)
            if ti.static(not two_level):
                z = self.filtered(i, self.jacobi(i, r))
                self.z[i] = z
                rz += r.dot(z)
            rr += self.body_weight[self.model.vertex_body[i]] * r.dot(r)
        if ti.static(two_level):
            rz = self.two_level_precondition(1)
        self.rz[None] = rz
        self.rr[None] = rr
        self.cg_beta[None] = 0.0
        self.iterations[None] = 0
        self.active[None] = 1
        return rr

    @ti.func
    def two_level_precondition(self, on):
        """z <- filtered(D^-1 r + Q A_c^-1 Q^T r): block Jacobi plus the coarse level's correction
        (fem/coarse.py), three passes; returns r.z. `on` = 0 loops over nothing."""
        self.patches.restrict(self.r, on)
        self.patches.solve(on)
        rz = 0.0
        ti.loop_config(serialize=self.serial_vertices)
        for i in range(self.model.vertex_count[None] * on):
            r = self.r[i]
            z = self.filtered(i, self.jacobi(i, r) + self.patches.prolong(i))
            self.z[i] = z
            rz += r.dot(z)
        return rz

    @ti.kernel
    def cg_iterations(self, cM: float, cK: float, target: float, cap: ti.i32, unroll: ti.template(),
                      two_level: ti.template()) -> ti.i32:
        """Up to `unroll` PCG iterations in one launch.

        Each iteration is three parallel passes (tets: K d; vertices: p, Ap and p.Ap;
        vertices: d, r, z and r.z, weighted r.r; two-level: z and r.z in three more,
        `two_level_precondition`) with the scalar steps between them run serially on the
        device. Once the weighted |r|^2 <= target or `cap` iterations are done, `active`
        drops to 0 and the remaining passes loop over nothing, so the iteration count is
        exact while Python launches one kernel per `unroll`. Returns `active`.
        """
        n_tets, n = self.model.tet_count[None], self.model.vertex_count[None]
        for _ in ti.static(range(unroll)):
            on = self.active[None]
            beta = self.cg_beta[None]
            ti.loop_config(serialize=self.serial_tets)
            for e in range(n_tets * on):
                if self.tet_awake(e):
                    self.tet_stiffness(e, self.z, self.p, beta)
            pAp = 0.0
            ti.loop_config(serialize=self.serial_vertices)
            for i in range(n * on):
                p = self.z[i] + beta * self.p[i]
                self.p[i] = p
                Ap = self.apply_H(i, self.p, cM, cK)
                self.Ap[i] = Ap
                pAp += p.dot(Ap)
            step = 0.0
            if pAp > 0:
                step = self.rz[None] / pAp
            rz, rr = 0.0, 0.0
            ti.loop_config(serialize=self.serial_vertices)
            for i in range(n * on):
                self.solution[i] += step * self.p[i]
                r = self.r[i] - step * self.Ap[i]
                self.r[i] = r
                if ti.static(not two_level):              # block Jacobi: z in the same pass
                    z = self.filtered(i, self.jacobi(i, r))
                    self.z[i] = z
                    rz += r.dot(z)
                rr += self.body_weight[self.model.vertex_body[i]] * r.dot(r)
            if ti.static(two_level):
                rz = self.two_level_precondition(on)
            if on:
                self.cg_beta[None] = 0.0
                if self.rz[None] > 0:
                    self.cg_beta[None] = rz / self.rz[None]
                self.rz[None] = rz
                self.rr[None] = rr
                self.iterations[None] += 1
                if not (rr > target and self.iterations[None] < cap):
                    self.active[None] = 0
        return self.active[None]

    @ti.kernel
    def jacobi_update(self, cM: float, cK: float, omega: float) -> float:
        """d += omega P (rhs - H d) (after stiffness_product(d)). Returns the weighted
        |rhs - H d|^2 before the update."""
        rr = 0.0
        ti.loop_config(serialize=self.serial_vertices)
        for i in range(self.model.vertex_count[None]):
            r = self.filtered(i, self.rhs[i]) - self.apply_H(i, self.solution, cM, cK)
            self.solution[i] += omega * self.filtered(i, self.jacobi(i, r))
            rr += self.body_weight[self.model.vertex_body[i]] * r.dot(r)
        return rr

    @ti.kernel
    def check_finite(self, x: ti.template(), v: ti.template()) -> ti.i32:
        """The count of vertices with a non-finite position or velocity."""
        bad = 0
        ti.loop_config(serialize=self.serial_vertices)
        for i in range(self.model.vertex_count[None]):
            if not is_finite(x[i].sum() + v[i].sum()):
                bad += 1
        return bad

    @ti.kernel
    def body_speeds(self, v: ti.template(), speed: ti.types.ndarray()):
        """speed[b] <- the largest |v_i|^2 over body b's vertices, (m/s)^2 (speed: (bodies,) float64)."""
        ti.loop_config(serialize=True)
        for b in range(speed.shape[0]):
            speed[b] = 0.0
        ti.loop_config(serialize=self.serial_vertices)
        for i in range(self.model.vertex_count[None]):
            ti.atomic_max(speed[self.model.vertex_body[i]], ti.cast(v[i].norm_sqr(), ti.f64))

    @ti.kernel
    def _write_bodies(self, pinned: ti.types.ndarray(), awake: ti.types.ndarray(),
                      floor: ti.types.ndarray(), speed_floor: ti.types.ndarray()):
        ti.loop_config(serialize=True)
        for b in range(pinned.shape[0]):
            self.body_pinned[b], self.awake[b] = pinned[b], awake[b]
            self.body_floor[b], self.body_speed_floor[b] = floor[b], speed_floor[b]

    @ti.kernel
    def clear_history(self, contacts: ti.i32):
        """The last step's velocity change <- 0; with contacts, which vertices the ground pressed too."""
        ti.loop_config(serialize=self.serial_vertices)
        for i in range(self.model.vertex_count[None]):
            self.change[i] = ti.Vector.zero(float, 3)
            if ti.static(self.has_ground):
                if contacts:
                    self.pressed[i] = 0

    @ti.kernel
    def hold(self, v: ti.template(), start: ti.i32, stop: ti.i32):
        """v <- 0 on vertices start..stop-1: a body put to sleep rests exactly."""
        for i in range(start, stop):
            v[i] = ti.Vector.zero(float, 3)

    def ground_reaction(self, cM, cK, newton):
        """pressed <- vertices in contact that the plane pushes up: the normal component of
        grad E is positive there (E would fall if they went down). After a Newton step rhs
        is -grad E at the result; after a single solve the linear model's gradient is
        -rhs + H d, so K d is formed first."""
        if not newton:
            self.stiffness_product(self.solution)
        self.mark_pressed(cM, cK, newton)

    @ti.kernel
    def mark_pressed(self, cM: float, cK: float, newton: ti.template()):
        ti.loop_config(serialize=self.serial_vertices)
        for i in range(self.model.vertex_count[None]):
            if not self.awake[self.model.vertex_body[i]]:     # asleep: keeps its contacts for waking
                continue
            self.pressed[i] = 0
            if self.contact[i]:
                g = -self.rhs[i]
                if ti.static(not newton):
                    g += cM * self.model.mass[i] * self.solution[i] + cK * self.gather(i)
                if g[1] > 0:
                    self.pressed[i] = 1

    @ti.kernel
    def ground_contact(self, x: ti.template(), v: ti.template()):
        """Friction on the vertices in contact (removes part of the tangential velocity),
        and no vertex left below the plane."""
        ti.loop_config(serialize=self.serial_vertices)
        for i in range(self.model.vertex_count[None]):
            if x[i][1] < self.ground[None]:
                self.pressed[i] = 1      # caught below the plane: in contact next step
            if self.contact[i] or x[i][1] < self.ground[None]:
                x[i][1] = ti.max(x[i][1], self.ground[None])
                v[i][1] = ti.max(v[i][1], 0.0)
                v[i][0] *= 1.0 - self.friction[None]
                v[i][2] *= 1.0 - self.friction[None]

    @ti.kernel
    def matrix_product(self, u: ti.template(), out: ti.template(), cM: float, cK: float):
        """out <- H u, gathered from `corner` after stiffness_product(u)."""
        ti.loop_config(serialize=self.serial_vertices)
        for i in range(self.model.vertex_count[None]):
            out[i] = self.apply_H(i, u, cM, cK)

    @ti.kernel
    def elastic_forces(self, x: ti.template(), out: ti.template()):
        """out <- f(x), the elastic force on every vertex (N), with the current rotations."""
        ti.loop_config(serialize=self.serial_tets)
        for e in range(self.model.tet_count[None]):
            self.store_corners(e, corner_forces(self.elastic_stress(x, e), self.rotated_Bm[e],
                                                self.model.rest_volume[e]))
        ti.loop_config(serialize=self.serial_vertices)
        for i in range(self.model.vertex_count[None]):
            out[i] = self.gather(i)
