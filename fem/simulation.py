"""A running scene: model + state + solver, stepped in time.

    sim = Simulation(load_scene("cube86"), method="linear")
    info = sim.step()            # solver_iters, residual, wall_ms, ...
    x = sim.positions()          # (n, 3) numpy
    sim.stats()                  # + energies, volume ratios, inverted tets
"""

import math
import sys
import time
from dataclasses import replace

import numpy as np
import taichi as ti

from fem.errors import FemError
from fem.measure import Measure
from fem.model import Model, State
from fem.scene import METHODS, select_vertices
from fem.solver import ImplicitSolver


@ti.kernel
def add_velocity(v: ti.template(), free: ti.template(), ids: ti.types.ndarray(), dv: ti.types.ndarray()):
    """v[ids[k]] += dv[k] for unpinned vertices."""
    for k in range(ids.shape[0]):
        i = ids[k]
        v[i] += free[i] * ti.Vector([dv[k, 0], dv[k, 1], dv[k, 2]])


CG_UNROLL = 2   # PCG iterations per kernel launch: fewer launches, same iteration count


class Simulation:
    """Steps one scene with backward Euler; see fem.solver for the maths.

    method: None keeps each body's own method, "linear" / "corotational" overrides all.
    solver ("pcg" | "jacobi"), dt (s), tolerance, max_iterations: override the scene's
    solver settings where not None.
    """

    def __init__(self, scene, method=None, solver=None, dt=None, tolerance=None, max_iterations=None):
        if method is not None:
            if method not in METHODS:
                raise FemError(f"method must be one of {METHODS}, got {method!r}")
            scene = scene.with_method(method)
        overrides = {"method": solver, "dt": dt, "tolerance": tolerance, "max_iterations": max_iterations}
        self.settings = replace(scene.solver, **{k: v for k, v in overrides.items() if v is not None})
        self.settings.check(scene.path or scene.name)
        self.scene = scene
        self.model = Model(scene)
        self.state = State(self.model.n_vertices)
        self.solver = ImplicitSolver(self.model, scene.effects)
        self.measure = Measure(self.model)
        offsets = [b.vertices.start for b in self.model.bodies]
        self.impulses = []
        for k, imp in enumerate(scene.impulses):
            picks = select_vertices(imp.selection, scene.bodies, f"{scene.path}: impulse[{k}]")
            ids = np.concatenate([ids + offsets[b] for b, ids in picks])
            self.impulses.append((imp.time, ids, imp.delta_v))
        self.warned_nonfinite = False
        self.reset()

    # ------------------------------------------------------------ running

    def reset(self):
        """Back to t = 0 with the scene's initial conditions."""
        self.state.load(*self.model.initial_state())
        self.solver.reset_rotations()
        self.rotated = False                 # rotated_Bm holds Bm
        self.solver.pressed.fill(0)          # no vertex starts out pushed by the ground
        self.t = 0.0
        self.steps = 0
        self.pending = sorted(self.impulses, key=lambda imp: imp[0])
        self.preconditioner_key = None
        self.omega_key, self.omega = None, None
        self.last = {}

    @property
    def coefficients(self):
        """(cM, cK) of A = cM M + cK K: backward Euler with Rayleigh damping."""
        dt, e = self.settings.dt, self.scene.effects
        return 1 + dt * e.alpha, dt * e.beta + dt * dt

    def step(self):
        """Advance one time step; returns what the step did (dict)."""
        start = time.perf_counter()
        s, x, v = self.solver, self.state.x, self.state.v
        dt = self.settings.dt
        while self.pending and self.pending[0][0] <= self.t + 0.5 * dt:
            _, ids, dv = self.pending.pop(0)
            self.apply_impulse(ids, dv)
        corot = self.model.any_corotational
        cM, cK = self.coefficients

        if corot:
            s.extract_rotations(x, self.settings.rotations == "svd")
            self.rotated = True
            ti.sync()
        elif self.rotated:                      # every body switched to linear: unrotate
            s.reset_rotations()
            self.rotated = False
        rotation_ms = 1e3 * (time.perf_counter() - start)
        if self.settings.method == "jacobi":
            self.jacobi_weight(cM, cK)
        key = (cM, cK, corot, self.model.material_version)
        if corot or key != self.preconditioner_key:
            s.build_preconditioner(cM, cK)   # linear: once, as A never changes
            self.preconditioner_key = key
        if self.scene.effects.ground is not None:
            s.detect_contacts(x, v, dt)
        s.elastic_forces(x)
        bb = s.assemble_rhs(x, v, dt)
        if self.settings.method == "pcg":
            iterations, rr = self.solve_pcg(bb, cM, cK)
        else:
            iterations, rr = self.solve_jacobi(bb, cM, cK)
        if self.scene.effects.ground is not None:
            s.beta[None] = 0.0
            s.stiffness_product(s.solution, s.solution)
            s.ground_reaction(cM, cK)
        bad = s.commit(x, v, dt)
        finite = bad == 0
        if finite:
            if self.scene.effects.ground is not None:
                s.ground_contact(x, v)
            self.t += dt
        else:
            s.restore(x, v)
            if not self.warned_nonfinite:
                print(f"warning: step {self.steps} gave non-finite values in {bad} vertices; "
                      "rejected it and kept the previous state", file=sys.stderr)
                self.warned_nonfinite = True
        ti.sync()
        self.steps += 1
        wall_ms = 1e3 * (time.perf_counter() - start)
        residual = math.sqrt(rr / bb) if bb > 0 else math.sqrt(rr)
        self.last = {
            "step": self.steps,
            "t": self.t,
            "wall_ms": wall_ms,
            "rotation_ms": rotation_ms if corot else 0.0,
            "solve_ms": wall_ms - (rotation_ms if corot else 0.0),
            "solver": self.settings.method,
            "solver_iters": iterations,
            "residual": residual if math.isfinite(residual) else None,
            "converged": bool(residual <= self.settings.tolerance),
            "corotational": [b.method == "corotational" for b in self.scene.bodies],
            "finite": finite,
        }
        return self.last

    def solve_pcg(self, scale, cM, cK):
        """Jacobi-preconditioned CG from the warm start v; returns (iterations, |r|^2)."""
        s = self.solver
        target = self.settings.tolerance ** 2 * (scale if scale > 0 else 1.0)
        s.stiffness_product(s.solution, s.solution)
        rr = s.start_residual(cM, cK)
        if rr > target:
            while s.active[None]:
                rr = s.cg_iterations(cM, cK, target, self.settings.max_iterations, CG_UNROLL)
        return s.iterations[None], rr

    def solve_jacobi(self, bb, cM, cK):
        """Weighted block-Jacobi iteration; returns (iterations, |r|^2 of the last checked iterate)."""
        s = self.solver
        target = self.settings.tolerance ** 2 * (bb if bb > 0 else 1.0)
        omega = self.settings.jacobi_omega or self.omega
        iterations, rr = 0, math.inf
        while iterations < self.settings.max_iterations:
            s.stiffness_product(s.solution, s.solution)
            rr = s.jacobi_update(cM, cK, omega)
            iterations += 1
            if rr <= target:
                break
        return iterations, rr

    def jacobi_weight(self, cM, cK):
        """omega = 1.5 / lambda_max(P A), lambda_max from 30 power iterations (rotations ignored:
        they barely move the spectrum), so the iteration cannot diverge (needs omega < 2 / lambda_max)."""
        key = (cM, cK, self.model.material_version)
        if key != self.omega_key:
            s = self.solver
            s.build_preconditioner(cM, cK)
            self.preconditioner_key = None
            P = s.block_inverse.to_numpy()
            u = np.random.default_rng(0).standard_normal((self.model.n_vertices, 3))
            lam = 1.0
            for _ in range(30):
                u /= np.linalg.norm(u)
                Au = self.apply_matrix(u, cM, cK)
                w = np.einsum("nij,nj->ni", P, Au)
                lam = float(np.vdot(u, w)) if np.vdot(u, u) > 0 else 1.0
                u = w
            self.omega, self.omega_key = 1.5 / max(lam, 1e-12), key
        return self.omega

    def apply_matrix(self, u, cM=None, cK=None):
        """A u for a (n, 3) numpy array u, through the same kernels as the solver (for checks)."""
        s = self.solver
        if cM is None:
            cM, cK = self.coefficients
        s.p.from_numpy(u)
        s.beta[None] = 0.0
        s.stiffness_product(s.p, s.p)
        s.matrix_product(s.p, s.Ap, cM, cK)
        return s.Ap.to_numpy().astype(np.float64)

    # ------------------------------------------------------------ interaction

    def apply_impulse(self, ids, delta_v):
        """Add delta_v (m/s; (3,) or (k, 3)) to the velocities of global vertex ids (k,)."""
        ids = np.asarray(ids, np.int32).ravel()
        dv = np.broadcast_to(np.asarray(delta_v, np.float64), (len(ids), 3)).copy()
        if len(ids):
            add_velocity(self.state.v, self.model.free, ids, dv)

    def set_method(self, method, body=None):
        """Switch one body (or all) between linear and corotational, live."""
        if method not in METHODS:
            raise FemError(f"method must be one of {METHODS}, got {method!r}")
        for i in range(len(self.model.bodies)) if body is None else [body]:
            self.model.set_method(i, method)

    def set_material(self, body, E, nu):
        from fem.scene import Material
        Material(E, nu, self.scene.bodies[body].material.density).check(f"body {body}")
        self.model.set_material(body, E, nu)

    # ------------------------------------------------------------ reading

    def positions(self):
        """(n, 3) float64 vertex positions, m."""
        return self.state.x.to_numpy().astype(np.float64)

    def velocities(self):
        return self.state.v.to_numpy().astype(np.float64)

    def stats(self):
        """The last step's numbers plus energies (J), volume ratios and inverted tets now."""
        out = {"step": self.steps, "t": self.t, "solver": self.settings.method}
        out.update(self.last)
        out["corotational"] = [b.method == "corotational" for b in self.scene.bodies]   # now, after toggles
        out.update(self.measure.read(self.state.x, self.state.v))
        return out

    def tet_values(self):
        """Per-tet (volume ratio J, strain energy density J/m^3), for colouring; (m,) each."""
        self.measure.measure(self.state.x, self.state.v)
        return self.measure.tet_volume_ratio.to_numpy(), self.measure.tet_energy_density.to_numpy()
