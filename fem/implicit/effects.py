"""The effects a scene switches on: gravity, Rayleigh damping, pins and ground contact.

Each is a `ti.static` branch fixed when the solver is made (`Switches`): an effect a scene
leaves off compiles to nothing. Gravity, damping and the ground are terms of the incremental
potential E(v) (fem/implicit/potential.py adds them up); pins and sleeping bodies are
constraints, applied by zeroing rows (`filtered`, filtered CG, Baraff & Witkin 1998).

The ground is an energy, so the line search that lowers E lowers it too (method.md, section 6):

    contact   C(x) = sum_i k m_i / 2 min(0, y_i - y_g)^2,   k = CONTACT_STIFFNESS / dt^2   (J)
    friction  h mu sum_i lambda_i f0(|u_i|),   u_i the tangential velocity (x, z) (J)

C is a penalty: a vertex below the plane y_g is pushed up by k m_i (y_g - y_i), so a body at
rest sinks by about (vertices above a bottom vertex) g dt^2 / CONTACT_STIFFNESS (0.04 mm for a
column of ten at dt 0.02 s). It is part of the total energy the step never raises. A vertex
deeper than one step of RECOVERY_SPEED (a body placed into the ground) is not shot out by the
energy stored there: within a step its plane is RECOVERY_SPEED dt above where it starts
(`plane`), so it rises at that speed, releasing the stored energy as it goes. Friction is
Coulomb's, lagged as in IPC (Li et al. 2020): lambda_i is the normal force at the step's start
(N), mu the coefficient, and f0 smooths |u| below the scene's stick speed eps (`[effects]
stick_speed`, FRICTION_SPEED unless set; `friction_shape`, IPC's cubic), so a vertex that slides
loses mu lambda_i of force and one nearly at rest sticks. It only dissipates. Sticking is
smoothed: a vertex held by friction against a tangential force F < mu lambda_i creeps below eps
(at about eps F / (2 mu lambda_i) for a small F), so a body resting on the ground counts as
quiet below that speed (fem/simulation.py puts it to sleep).

Fields (n vertices of the capacity; one entry when the scene has no ground):
    mass_damping ()       alpha, 1/s
    stiffness_damping ()  beta, s
    gravity ()            g, m/s^2
    ground ()             plane height y_g, m
    friction ()           mu, Coulomb's coefficient
    stick_speed ()        eps, m/s: friction's smoothing speed, below which it holds (float64)
    contact_stiffness ()  k, 1/s^2 (per unit mass)
    energy_stiffness ()   k at the scene's dt: the contact energy measured (`contact_energy`)
    plane (n,)            the plane's height for vertex i in this step, m: y_g, or lower for a
                          vertex deep below it
    normal_force (n,)     lambda_i at the step's start, N
    majorize ()           1: friction's Hessian takes its curvature across the slide along it too
                          (fem/implicit/newton.py sets it for a contact step's first iterations)
    contact_hessian (n, 4)  the contact's and friction's Hessian at the accepted iterate,
                          (xx, yy, zz, xz), kg/s (H-units: N s per m/s): a vertex's own block
"""

import taichi as ti

CONTACT_STIFFNESS = 1000.0   # k dt^2: the penalty's stiffness in units of a vertex's inertia over one step
FRICTION_SPEED = 1e-3        # m/s: the default stick speed: below this tangential speed friction is smoothed
                             # (sticking); a body it holds may creep at up to this speed (fem/simulation.py)
RECOVERY_SPEED = 1.0         # m/s: how fast a vertex placed deep in the ground rises out of it
UNREACHABLE = 1e30           # m: a plane no vertex is below


@ti.func
def friction_shape(s, eps):
    """IPC's smoothing of a speed s = |u| for lagged friction (Li et al. 2020) below eps (the stick speed,
    of s's type):
    f0(s) = s^2 / eps - s^3 / (3 eps^2) below eps, s - eps / 3 above, so the force mu lambda f1(s),
    f1 = f0' = 2 s / eps - s^2 / eps^2, rises from 0 to Coulomb's mu lambda at eps with no kink
    (f0 is twice differentiable: Newton's model holds across sticking and sliding). Returns
    (f0(s), f1(s) / s, f1'(s)): the energy, and the Hessian's curvatures across and along u."""
    f0, across, along = s - eps / 3.0, 1.0 / ti.max(s, eps), 0.0 * s
    if s < eps:
        f0 = s * s / eps - s * s * s / (3.0 * eps * eps)
        across = 2.0 / eps - s / (eps * eps)
        along = 2.0 / eps - 2.0 * s / (eps * eps)
    return f0, across, along


@ti.data_oriented
class Effects:
    """The effects' values on the device for one model; `load` takes a scene's (fem.scene.Effects)."""

    def __init__(self, model, elasticity, sleep, switches):
        n = model.capacity.vertices
        self.model, self.elasticity, self.sleep = model, elasticity, sleep
        self.has_gravity, self.has_ground = switches.gravity, switches.ground     # compile-time switches
        self.has_stiffness_damping = switches.stiffness_damping                   # D includes beta K(R)
        self.pins = switches.pins
        self.serial_vertices = switches.serial_vertices
        self.mass_damping = ti.field(float, ())
        self.stick_speed = ti.field(ti.f64, ())
        self.majorize = ti.field(ti.i32, ())
        self.stiffness_damping = ti.field(float, ())
        self.gravity = ti.Vector.field(3, float, ())
        self.ground = ti.field(float, ())
        self.friction = ti.field(float, ())
        self.contact_stiffness = ti.field(float, ())
        self.energy_stiffness = ti.field(float, ())
        self.normal_force = ti.field(float, n if self.has_ground else 1)
        self.plane = ti.field(float, n if self.has_ground else 1)
        self.contact_hessian = ti.Vector.field(4, float, n if self.has_ground else 1)
        self.has_contact = switches.contact                  # between bodies: fem/implicit/contact.py
        self.contact = None                                  # the solver adds its Contact where it is on

    def load(self, effects):
        """A scene's effects (fem.scene.Effects); alpha and beta are also kept for the host."""
        self.alpha, self.beta = effects.alpha, effects.beta
        self.mass_damping[None], self.stiffness_damping[None] = effects.alpha, effects.beta
        self.gravity[None] = effects.gravity or (0.0, 0.0, 0.0)
        self.ground[None] = effects.ground or 0.0
        self.friction[None] = effects.friction
        self.stick_speed[None] = effects.stick_speed
        if self.has_contact:
            self.contact.load(effects.contact)

    @property
    def damped(self):
        """Rayleigh damping is on: the step dissipates by its own design."""
        return self.alpha > 0 or self.beta > 0

    def set_dt(self, dt, scene_dt):
        """The contact's stiffness follows the step's dt (not an integrator's own h), so that
        the contact energy of a state does not change from one step to the next. The energy the
        safeguards and the stats measure takes the scene's dt (`energy_stiffness`): a step the
        simulation splits in two of dt / 2 (a vertex sunk too deep, fem/simulation.py: take)
        presses with a penalty four times as stiff, and measured with it, a state on the ground
        held more energy than it had; the halves, each within its own start's, released it (the
        ground drops of tests/test_energy.py, f64, dt 0.5 s: every body +0.2 to 11 % of its
        largest energy in the split step)."""
        self.contact_stiffness[None] = CONTACT_STIFFNESS / (dt * dt)
        self.energy_stiffness[None] = CONTACT_STIFFNESS / (scene_dt * scene_dt)
        if self.has_contact:
            self.contact.set_dt(dt)

    @ti.func
    def filtered(self, i, a):
        """Zero the constrained rows: pinned vertices and sleeping bodies (filtered CG)."""
        if ti.static(self.pins):
            a *= self.model.free[i]
        return a * self.sleep.awake[self.model.vertex_body[i]]    # a sleeping body is held like a pinned one

    @ti.func
    def round_off(self, b):
        """What body b's |grad E|^2 cannot tell from 0 beyond its own floor: the contact pairs' round-off
        (Contact.body_noise), (N s)^2."""
        out = ti.cast(0.0, ti.f64)
        if ti.static(self.has_contact):
            out = self.contact.body_noise[b]
        return out

    @ti.func
    def gravity_vector(self):
        return self.gravity[None]

    # ------------------------------------------------------------ the ground: energy, gradient, Hessian

    @ti.func
    def penalty(self, i, x, plane, k):
        """k m_i / 2 min(0, y - plane)^2 of vertex i at position x, float64 (J)."""
        d = ti.cast(ti.min(0.0, x[1] - plane), ti.f64)
        return 0.5 * ti.cast(k * self.model.mass[i], ti.f64) * d * d

    @ti.func
    def contact_energy(self, i, x):
        """What the ground stores at vertex i: the penalty against the ground itself, with the
        scene dt's stiffness (`set_dt`) (J)."""
        return self.penalty(i, x, self.ground[None], self.energy_stiffness[None])

    @ti.func
    def pressed(self, x):
        """1 where a vertex at x is pressed into the ground (it has a normal force), else 0."""
        out = 0
        if ti.static(self.has_ground):
            out = int(x[1] < self.ground[None])
        return out

    @ti.func
    def step_contact_energy(self, i, x):
        """The step's contact term of vertex i: the penalty against its plane this step (J)."""
        return self.penalty(i, x, self.plane[i], self.contact_stiffness[None])

    @ti.func
    def friction_energy(self, i, v, h):
        """h mu lambda_i f0(|u|) of vertex i at velocity v, float64 (J)."""
        u = ti.cast(ti.Vector([v[0], v[2]]), ti.f64).norm()
        return ti.cast(h * self.friction[None] * self.normal_force[i], ti.f64) * friction_shape(u, self.stick_speed[None])[0]

    @ti.func
    def contact_force(self, i, x, v, h):
        """-grad of the contact and friction terms of vertex i at (x, v), N s; and their Hessian
        there (kg/s), kept in contact_hessian for the products H u. Friction's Hessian is
        h mu lambda_i (f1(s) / s (I - t t^T) + f1'(s) t t^T), s = |u|, t = u / s (`friction_shape`):
        2 / eps I at rest, falling smoothly to none along the slide at eps and beyond."""
        km = self.contact_stiffness[None] * self.model.mass[i]
        d = ti.min(0.0, x[1] - self.plane[i])
        s = ti.Vector([v[0], v[2]]).norm()
        _, across, along = self.friction_model(s)
        lam = h * self.friction[None] * self.normal_force[i]
        c, e = lam * across, lam * (along - across)
        tx, tz = v[0] / ti.max(s, 1e-30), v[2] / ti.max(s, 1e-30)
        self.contact_hessian[i] = ti.Vector([c + e * tx * tx, h * h * km * (d < 0.0), c + e * tz * tz, e * tx * tz])
        return ti.Vector([-c * v[0], -h * km * d, -c * v[2]])

    @ti.func
    def friction_model(self, s):
        """`friction_shape` at speed s as Newton's model takes it: while `majorize` is on, the
        curvature along the slide is the one across it (the ground's and the pairs' friction)."""
        f0, across, along = friction_shape(s, ti.cast(self.stick_speed[None], float))
        if self.majorize[None]:
            along = across
        return f0, across, along

    @ti.func
    def contact_product(self, i, u: ti.template()):
        """(the contact's Hessian) u at vertex i."""
        c, w = self.contact_hessian[i], u[i]
        return ti.Vector([c[0] * w[0] + c[3] * w[2], c[1] * w[1], c[3] * w[0] + c[2] * w[2]])

    @ti.func
    def contact_block(self, i):
        """The contact's Hessian at vertex i as a 3x3 matrix (the preconditioner's share)."""
        c = self.contact_hessian[i]
        return ti.Matrix([[c[0], 0.0, c[3]], [0.0, c[1], 0.0], [c[3], 0.0, c[2]]])

    @ti.kernel
    def start_contacts(self, xn: ti.template(), x: ti.template(), h: float, dt: float):
        """At the step's start: each vertex's plane; lambda_i <- k m_i max(0, plane - y_i) at x_n,
        the normal force that friction is lagged on; and the Hessian at the first iterate x
        (v = 0), which the preconditioner is built with."""
        ti.loop_config(serialize=self.serial_vertices)
        for i in range(self.model.vertex_count[None]):
            km = self.contact_stiffness[None] * self.model.mass[i]
            self.plane[i] = ti.min(self.ground[None], xn[i][1] + ti.static(RECOVERY_SPEED) * dt)
            self.normal_force[i] = km * ti.max(0.0, self.plane[i] - xn[i][1])
            drag = h * self.friction[None] * self.normal_force[i] * 2.0 / ti.cast(self.stick_speed[None], float)
            self.contact_hessian[i] = ti.Vector([drag, h * h * km * (x[i][1] < self.plane[i]), drag, 0.0])

    @ti.kernel
    def release_deep(self):
        """After `start_contacts`, for the acceleration at a step's start (a_n, which BDF2's and the
        trapezoidal rule's history start from): a vertex deeper than one step of RECOVERY_SPEED
        feels no ground. Its penalty, k m_i RECOVERY_SPEED dt, is an impulse the step's
        minimisation turns into a rise at RECOVERY_SPEED, but as an acceleration it is 1000
        RECOVERY_SPEED / dt (5e4 m/s^2 at dt 0.02 s), which a history taken from it would carry
        into every later step: a body placed 0.45 m into the ground left it at 323 m/s."""
        ti.loop_config(serialize=self.serial_vertices)
        for i in range(self.model.vertex_count[None]):
            if self.plane[i] < self.ground[None]:
                self.plane[i] = -ti.static(UNREACHABLE)
                self.normal_force[i] = 0.0

    @ti.kernel
    def body_grounded(self, x: ti.template(), grounded: ti.types.ndarray()):
        """grounded[b] <- 1 where some vertex of body b is below the ground plane (pressed into it:
        a body resting on the ground always is, by the penalty's sag), else 0."""
        ti.loop_config(serialize=True)
        for b in range(grounded.shape[0]):
            grounded[b] = 0
        ti.loop_config(serialize=self.serial_vertices)
        for i in range(self.model.vertex_count[None]):
            if self.pressed(x[i]):
                grounded[self.model.vertex_body[i]] = 1
