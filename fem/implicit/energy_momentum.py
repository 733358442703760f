"""The conserving scheme's step: an energy-momentum step for the corotated energy (method.md, section 6).

The trapezoidal rule keeps energy exactly only where forces are linear. A stiff body turning
0.2 rad a step rings in modes dt cannot follow, and on the corotated energy the rule pumps energy
into them faster than any projection can take it out (a 0.5 m cube at E 1e8 spinning at 10
rad/s: 3e-3 to 7e-3 J a step, more than all its internal energy). The energy-momentum step
(Simo & Tarnow 1992, with Gonzalez's discrete gradient, 1996) replaces f(x_(n+1)) and f(x_n)
by one algorithmic force per tet,

    x_(n+1) = x_n + dt (v_n + v_(n+1)) / 2,   M (v_(n+1) - v_n) = dt (f_algo + M g),
    f_algo = -W (F_mid S_algo) Bm^T (corner_forces),  F_mid = (F_n + F_(n+1)) / 2,
    S_algo = (S_n + S_(n+1)) / 2 + kappa dC,  dC = C_(n+1) - C_n,  C = F^T F,
    kappa = 2 (Psi_(n+1) - Psi_n - W S_mid : dC / 2) / (W |dC|^2),

with S = U^-1 sigma(U - I) the second Piola stress of the corotated energy (F = R U). Since
dC = F_mid^T dF + dF^T F_mid, f_algo . (x_(n+1) - x_n) = -(Psi_(n+1) - Psi_n) exactly: the step
keeps energy; F_mid S_algo F_mid^T is symmetric, so f_algo has no torque about the midpoint: it
keeps angular momentum; and a rigid turn has dC = 0 and S = 0: no strain, however far it turns.
Where |dC| is at round-off kappa is 0 (the energy it leaves out is of order E W |dC|^3). Linear
tets keep the trapezoidal rule, (f_n + f_(n+1)) / 2, exact on their quadratic energy, and so do
tets near inverting (det F <= UPRIGHT at either end), where U^-1 is unbounded and the corotated
energy is no function of C (C forgets the sign of det F): the energy projection has them.

It is solved by the step's own minimisation. With v^ = v_n + h a* (h = dt / 2), the trapezoidal
potential's gradient M (v - v^) - h M g - h f(x) is the step's residual when
a* = g + M^-1 (2 f_algo(x_n, x) - f(x)): `target` sets v^ from the iterate x, and Newton
minimises again from there until that residual meets the tolerance (the solver's loop). What
is lagged, 2 f_algo - f(x) = f(x_n) + O(dx^2), changes little with x: a stiff spinning cube
needs 2 or 3 passes. Only bodies too stiff for dt to follow take it (`body_stiff`); a soft body's
trapezoidal rule loses nothing the projection cannot give back.

With mass damping the step is the theta rule's (`target`'s lagged form): f_algo takes the place of
the rule's average of f_n and f(x), and the rule keeps its own dissipation, (theta - 1/2)(f(x) - f_n).
Not with stiffness damping, whose line search stalls on a stiff turning body (method.md, section 6).

Fields (m tets, bodies of the capacity), made on the first step that needs them (body_stiff at once):
    start_piola (m, 3x3)    P_n, the tet's first Piola stress at x_n (Pa)
    start_stress (m, 3x3)   S_n of a corotational tet (Pa), 0 near inverting
    start_energy (m,)       Psi_n of the tet, J (float64)
    body_error (bodies,)    e_b, the energy error a body's answer leaves the projection (`energy_error`), J
    body_stiff (bodies,)    1: a corotational body too stiff for dt to follow (Model.stiff), which takes
                            the algorithmic force; the others keep the trapezoidal rule (2: in shear
                            too, and its Newton trials take the arc, bend.py)
"""

import taichi as ti

from fem.elastic import corner_forces, is_finite
from fem.rotation import quaternion_matrix
from fem.runtime import epsilon

COROTATIONAL = 1         # Model.method(e) (fem.scene.METHODS)
PASSES = 8               # the solver's passes at most: v^ set anew from where the last one ended
SHARE = 0.2              # the energy error a step leaves the projection, at most this share of the deformation's kinetic energy
TIGHTER = 0.01           # where it is more, the next pass's tolerance is this much smaller
UPRIGHT = 0.1            # det F above which a tet takes the algorithmic force (`follows`)
F64 = ti.f64


@ti.func
def second_piola(F, R, mu, lam):
    """S = U^-1 sigma(U - I) with U = sym(R^T F), R the polar rotation of F (float64): the second
    Piola stress of the corotated energy, symmetric (U and sigma(U - I) commute)."""
    U = R.transpose() @ F
    U = 0.5 * (U + U.transpose())
    eps = U - ti.Matrix.identity(F64, 3)
    S = U.inverse() @ (2.0 * mu * eps + lam * eps.trace() * ti.Matrix.identity(F64, 3))
    return 0.5 * (S + S.transpose())


@ti.data_oriented
class EnergyMomentum:
    """The energy-momentum step's algorithmic force for one model: its start (`begin`) and the
    inertia target it gives an iterate (`target`), with the parts the potential uses."""

    def __init__(self, model, potential, elasticity, rotations, effects, safeguards, sleep, switches):
        self.model, self.potential, self.elasticity = model, potential, elasticity
        self.rotations, self.effects, self.safeguards, self.sleep = rotations, effects, safeguards, sleep
        self.has_gravity = switches.gravity
        self.serial_tets, self.serial_vertices = switches.serial_tets, switches.serial_vertices
        self.body_stiff = ti.field(ti.i32, model.capacity.bodies)    # 1: the body takes the algorithmic force
        self.start_piola = self.start_stress = self.start_energy = self.body_error = None

    def begin(self, x_n):
        """Keep P_n, S_n and Psi_n of every tet at the step's start x_n (R(x_n) extracted)."""
        if self.start_stress is None:
            m, nb = self.model.capacity.tets, self.model.capacity.bodies
            self.start_piola = ti.Matrix.field(3, 3, float, m)
            self.start_stress = ti.Matrix.field(3, 3, float, m)
            self.start_energy = ti.field(F64, m)
            self.body_error = ti.field(F64, nb)
        self._begin(x_n)

    @ti.kernel
    def _begin(self, x_n: ti.template()):
        ti.loop_config(serialize=self.serial_tets)
        for e in range(self.model.tet_count[None]):
            R = quaternion_matrix(self.rotations.quaternions[e])       # I for a linear tet
            self.start_piola[e] = self.elasticity.elastic_stress(x_n, e) @ R
            S = ti.Matrix.zero(float, 3, 3)
            if self.follows(x_n, e):
                S = ti.cast(self.stress(x_n, e), float)
            self.start_stress[e] = S
            self.start_energy[e] = self.elasticity.elastic_energy(x_n, e)

    @ti.func
    def follows(self, x: ti.template(), e):
        """Tet e takes the algorithmic force at x: corotational, of a stiff body (`body_stiff`), and far
        from inverting (det F > UPRIGHT: U^-1 is bounded, and the energy is a function of C = F^T F,
        which forgets det F's sign)."""
        F = self.model.edges(x, e) @ self.model.Bm[e]
        return self.model.method(e) == COROTATIONAL and self.body_stiff[self.model.tet_body[e]] >= 1 \
            and F.determinant() > UPRIGHT

    @ti.func
    def stress(self, x: ti.template(), e):
        """S of corotational tet e at x with its extracted rotation (float64)."""
        F = ti.cast(self.model.edges(x, e) @ self.model.Bm[e], F64)
        R = ti.cast(quaternion_matrix(self.rotations.quaternions[e]), F64)
        return second_piola(F, R, ti.cast(self.model.mu(e), F64), ti.cast(self.model.lam(e), F64))

    @ti.kernel
    def target(self, x_n: ti.template(), v_n: ti.template(), x: ti.template(), h: float, rho: float,
               a_n: ti.template(), lagged: ti.template()):
        """The potential's v^ at the iterate x, with R at x extracted (a sleeping body keeps v^ = v_n).

        The trapezoidal rule (lagged 0, h = dt / 2): v^ <- v_n + h a*, a* = g + M^-1 (2 f_algo(x_n, x)
        - f(x)). A linear tet, or one near inverting at either end, keeps the rule's
        f_algo = (f_n + f(x)) / 2: its share of a* is f_n.
        The theta rule (lagged 1: rho_infinity rho < 1, a damped scene; h = dt / (1 + rho)): its
        v^ = v_n + rho h a_n (a_n, every force at x_n, damping too: the history's) and
        (1 - theta) f_n + theta f(x) of the elastic force become f_algo + (theta - 1/2) (f(x) - f_n):
        v^ gains dt M^-1 (f_algo - (f_n + f(x)) / 2), dt = (1 + rho) h. The rule's own dissipation
        of what dt cannot follow stays; what the rule alone pumps into a stiff turning body does
        not (a 0.5 m cube at E 1e8 and 10 rad/s, alpha 0.1, lost 95 % of its energy in 1 s)."""
        ti.loop_config(serialize=self.serial_tets)
        for e in range(self.model.tet_count[None]):
            W = self.model.rest_volume[e] * self.sleep.tet_awake(e)
            P = self.start_piola[e]
            twice, own = 1.0, 0.0
            if ti.static(lagged):
                twice = 0.0              # the history's a_n holds f_n
            if self.follows(x_n, e) and self.follows(x, e):
                algorithmic = ti.cast(self.algorithmic_stress(x_n, x, e), float)
                if is_finite(algorithmic.sum()):
                    P, twice, own = algorithmic, 2.0, 1.0
                    if ti.static(lagged):
                        twice, own = 1.0 + rho, 0.5 * (1.0 + rho)
            f = corner_forces(P, self.model.Bm[e], W)
            f_x = corner_forces(self.elasticity.elastic_stress(x, e), self.rotations.rotated_Bm[e], W)
            if ti.static(lagged):        # f_n's share, own of it: -(1 + rho) / 2 f_n where f is f_algo
                f_n = corner_forces(self.start_piola[e], self.model.Bm[e], W)
                for k in ti.static(range(4)):
                    self.elasticity.corner[4 * e + k] = twice * f[k] - own * (f_x[k] + f_n[k])
            else:
                for k in ti.static(range(4)):
                    self.elasticity.corner[4 * e + k] = twice * f[k] - own * f_x[k]
        ti.loop_config(serialize=self.serial_vertices)
        for i in range(self.model.vertex_count[None]):
            if self.sleep.awake[self.model.vertex_body[i]]:
                a = self.elasticity.gather(i) / self.model.mass[i]
                if ti.static(lagged):
                    a += rho * a_n[i]
                elif ti.static(self.has_gravity):
                    a += self.effects.gravity_vector()
                self.potential.v0[i] = v_n[i] + h * a

    @ti.func
    def algorithmic_stress(self, x_n: ti.template(), x: ti.template(), e):
        """F_mid S_algo of corotational tet e between x_n and x (float64, Pa): the first Piola
        stress whose work over the step is the change of the tet's energy."""
        F0 = ti.cast(self.model.edges(x_n, e) @ self.model.Bm[e], F64)
        F1 = ti.cast(self.model.edges(x, e) @ self.model.Bm[e], F64)
        dC = F1.transpose() @ F1 - F0.transpose() @ F0
        S = 0.5 * (ti.cast(self.start_stress[e], F64) + self.stress(x, e))
        W = ti.cast(self.model.rest_volume[e], F64)
        size = (dC * dC).sum()
        if size > ti.static((100.0 * epsilon()) ** 2) and W > 0:
            missing = self.elasticity.elastic_energy(x, e) - self.start_energy[e] - 0.5 * W * (S * dC).sum()
            S += (2.0 * missing / (W * size)) * dC
        return 0.5 * (F0 + F1) @ S

    @ti.kernel
    def energy_error(self, x_n: ti.template(), dt: float) -> F64:
        """max over bodies of |e_b| / (SHARE K_b + the body's round-off at rest): e_b, the energy
        error the step's residual leaves for the projection, against K_b, the kinetic energy of
        the body's deformation at the iterate (what the projection scales to pay for it). With
        the residual r = M (v - v_n) - dt (f_algo + M g) (grad E at the iterate, where `target` set
        v^) the step changes the energy by exactly -sum r . (x - x_n) / dt. The projection puts the
        body's momentum and angular momentum right by a rigid velocity, which pays back the part
        of that error along v_c + omega x (x_mid - c), the body's rigid motion at the iterate;
        e_b is what is left. At the default tolerance a stiff body spinning fast (318 J turning,
        1e-4 J deforming) left the projection more than its deformation could pay every few steps."""
        self.safeguards.rigid_motion(self.potential.x, self.potential.v)
        self.sleep.sums.reduce(self.deformation_work, self.store_error, (x_n, dt))
        ratio = ti.cast(0.0, F64)
        ti.loop_config(serialize=True)
        for b in range(self.model.body_count[None]):
            allowed = SHARE * self.safeguards.body_deformation[b] + \
                self.safeguards.body_quiet[b] * self.potential.body_far[b]
            if allowed > 0 and self.body_stiff[b] >= 1:
                ratio = ti.max(ratio, ti.abs(self.body_error[b]) / allowed)
        return ratio

    @ti.func
    def deformation_work(self, i, b, data: ti.template()):
        """Vertex i's share of e_b, r_i . (chord - v_c - omega x (x_mid - c)), J."""
        x_n = ti.static(data[0])
        dt = data[1]
        x, start = ti.cast(self.potential.x[i], F64), ti.cast(x_n[i], F64)
        w = self.safeguards.deformation_velocity(b, 0.5 * (x + start), (x - start) / dt)
        e = -ti.cast(self.effects.filtered(i, self.potential.rhs[i]), F64).dot(w)
        return ti.Vector([e, 0, 0, 0, 0, 0, 0, 0, 0, 0], F64)

    @ti.func
    def store_error(self, b, total, data: ti.template()):
        self.body_error[b] = total[0]
