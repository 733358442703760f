"""The effects a scene switches on: gravity, Rayleigh damping, pins and ground contact.

Each is a `ti.static` branch fixed when the solver is made (`Switches`): an effect a scene
leaves off compiles to nothing. Gravity and damping enter the incremental potential
(fem/implicit/potential.py reads their fields); pins, ground contact and sleeping bodies
are constraints, applied by zeroing rows (`filtered`, filtered CG, Baraff & Witkin 1998).

The ground is an active set chosen at the step's start (`start_iterate`, fem/implicit/newton.py):
a vertex below the plane, or one the ground pushed up last step (`pressed`), has its normal
velocity prescribed so that it lands on the plane; after the solve `mark_pressed` keeps those
the plane still pushes, and `ground_contact` applies friction and lifts any vertex left below.

Fields (n vertices of the capacity; one entry when the scene has no ground):
    mass_damping ()       alpha, 1/s
    stiffness_damping ()  beta, s
    gravity ()            g, m/s^2
    ground ()             plane height y, m
    friction ()           share of tangential velocity lost on contact
    contact (n,)          1: on the ground this step
    pressed (n,)          1: the ground pushed it last step
"""

import taichi as ti


@ti.data_oriented
class Effects:
    """The effects' values on the device for one model; `load` takes a scene's (fem.scene.Effects)."""

    def __init__(self, model, elasticity, sleep, switches):
        n = model.capacity.vertices
        self.model, self.elasticity, self.sleep = model, elasticity, sleep
        self.has_gravity, self.has_ground = switches.gravity, switches.ground     # compile-time switches
        self.has_stiffness_damping = switches.stiffness_damping                   # D includes beta K_n
        self.pins = switches.pins
        self.serial_vertices = switches.serial_vertices
        self.mass_damping = ti.field(float, ())
        self.stiffness_damping = ti.field(float, ())
        self.gravity = ti.Vector.field(3, float, ())
        self.ground = ti.field(float, ())
        self.friction = ti.field(float, ())
        self.contact = ti.field(ti.i32, n if self.has_ground else 1)
        self.pressed = ti.field(ti.i32, n if self.has_ground else 1)

    def load(self, effects):
        """A scene's effects (fem.scene.Effects); alpha and beta are also kept for the host."""
        self.alpha, self.beta = effects.alpha, effects.beta
        self.mass_damping[None], self.stiffness_damping[None] = effects.alpha, effects.beta
        self.gravity[None] = effects.gravity or (0.0, 0.0, 0.0)
        self.ground[None] = effects.ground or 0.0
        self.friction[None] = effects.friction

    @ti.func
    def filtered(self, i, a):
        """Zero the constrained rows: pinned vertices, and the normal of those on the ground
        (filtered CG, Baraff & Witkin 1998)."""
        if ti.static(self.pins):
            a *= self.model.free[i]
        if ti.static(self.has_ground):
            if self.contact[i]:
                a[1] = 0.0
        return a * self.sleep.awake[self.model.vertex_body[i]]    # a sleeping body is held like a pinned one

    @ti.func
    def gravity_vector(self):
        return self.gravity[None]

    def ground_reaction(self, rhs, d, cM, cK, newton):
        """pressed <- vertices in contact that the plane pushes up: the normal component of
        grad E is positive there (E would fall if they went down). After a Newton step rhs
        is -grad E at the result; after a single solve the linear model's gradient is
        -rhs + H d, so K d is formed first."""
        if not newton:
            self.elasticity.stiffness_product(d)
        self.mark_pressed(rhs, d, cM, cK, newton)

    @ti.kernel
    def mark_pressed(self, rhs: ti.template(), d: ti.template(), cM: float, cK: float, newton: ti.template()):
        ti.loop_config(serialize=self.serial_vertices)
        for i in range(self.model.vertex_count[None]):
            if not self.sleep.awake[self.model.vertex_body[i]]:     # asleep: keeps its contacts for waking
                continue
            self.pressed[i] = 0
            if self.contact[i]:
                g = -rhs[i]
                if ti.static(not newton):
                    g += cM * self.model.mass[i] * d[i] + cK * self.elasticity.gather(i)
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
