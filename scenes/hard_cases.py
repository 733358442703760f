"""Hard cases: small scenes built in Python that must stay finite and lose energy under damping.

tests/test_hard_cases.py, tests/test_energy.py, `main.py figures` (hard_case_energy) and
tools/robustness_table.py all read these lists, so the table in docs/robustness.md
always describes what the tests check.

Every case runs twice, once with linear and once with corotational bodies, and the cases
that share a time step and a step count run as bodies of one scene (`build_scene`, `groups`):
bodies do not interact, and Taichi compiles its kernels once per Simulation (seconds), not
once per body.
"""

from dataclasses import dataclass, field
from itertools import groupby

import numpy as np

from fem.mesh import TetMesh, prepare_mesh
from fem.scene import Body, ContactEffect, Effects, Impulse, Initial, Material, Scene, Selection, SolverSettings

METHODS = ("linear", "corotational")
DAMPING = Effects(alpha=0.1, beta=0.1)       # the coursework's Rayleigh damping


# ---------------------------------------------------------------- meshes

def cube(cells=2, size=(1.0, 1.0, 1.0), keep=None):
    """A box of `size` m centred at the origin, cells^3 (or cells = (nx, ny, nz)) cubes of 6 tets
    each (Kuhn split); only the cubes (i, j, k) where keep(i, j, k) is true, if given."""
    n = np.broadcast_to(cells, 3)
    axes = [np.linspace(-s / 2, s / 2, c + 1) for s, c in zip(size, n)]
    X = np.array(np.meshgrid(*axes, indexing="ij")).reshape(3, -1).T
    index = np.arange(np.prod(n + 1)).reshape(tuple(n + 1))
    kuhn = [(0, 1, 3, 7), (0, 1, 5, 7), (0, 2, 3, 7), (0, 2, 6, 7), (0, 4, 5, 7), (0, 4, 6, 7)]
    tets = []
    for i, j, k in np.ndindex(*n):
        if keep is None or keep(i, j, k):
            corner = [index[i + a, j + b, k + c] for a in (0, 1) for b in (0, 1) for c in (0, 1)]
            tets += [[corner[t] for t in tet] for tet in kuhn]
    used, tets = np.unique(tets, return_inverse=True)        # drop the corners of no cube kept
    return prepare_mesh(X[used], tets.reshape(-1, 4), f"cube(cells={cells}, size={size})")


def sliver_tet(height=1e-3):
    """One sliver: four corners of a unit square lifted alternately by +-height (m), so all six
    edges are about 1.4 m long but the volume is only 2/3 * height and two dihedral angles are
    nearly 0 and two nearly 180 degrees."""
    X = np.array([[1.0, 0, height], [-1.0, 0, height], [0, 1.0, -height], [0, -1.0, -height]])
    return prepare_mesh(X, np.array([[0, 1, 2, 3]]), f"sliver_tet(height={height})")


# ---------------------------------------------------------------- hard cases

@dataclass
class Part:
    """One body of a hard case: its mesh, material and initial velocities.

    push: [(local vertex id, velocity (3,) m/s)], set at t = 0.
    """

    mesh: TetMesh
    E: float = 1e4            # Pa
    nu: float = 0.3
    density: float = 1000.0   # kg/m^3
    push: list = field(default_factory=list)


@dataclass
class HardCase:
    """A scene that must stay finite and lose energy under damping.

    inverted: start from the rest shape mirrored through the plane x = centre, so
    every tet is inverted (det F < 0) at t = 0.
    """

    name: str
    what: str
    parts: list
    dt: float = 0.02          # s
    steps: int = 100
    inverted: bool = False


def corner_push(speed):
    """Opposite pushes on two corners of a cube(cells=2): it spins and shears."""
    return [(0, np.array([0.0, 0.0, speed])), (2, np.array([0.0, 0.0, -speed]))]


HARD_CASES = [
    HardCase("inverted start", "1 m cube mirrored through a plane: all 48 tets inverted at t = 0",
             [Part(cube())], inverted=True),
    HardCase("near-incompressible", "nu = 0.4999 (lambda = 1666 E), corners pushed at 5 m/s",
             [Part(cube(), nu=0.4999, push=corner_push(5.0))]),
    HardCase("very soft", "E = 10 Pa, density 1000, corners pushed at 5 m/s",
             [Part(cube(), E=10.0, push=corner_push(5.0))]),
    HardCase("very stiff", "E = 1e9 Pa, corners pushed at 5 m/s",
             [Part(cube(), E=1e9, push=corner_push(5.0))]),
    HardCase("sliver tets", "a 1 x 1 x 0.001 m slab (48 flat tets) and a lone sliver tet "
             "(volume 7e-4 m^3, edges 1.4 m), pushed at 2 m/s",
             [Part(cube(size=(1.0, 1.0, 1e-3)), push=corner_push(2.0)),
              Part(sliver_tet(), push=[(0, np.array([0.0, 0.0, 2.0]))])]),
    HardCase("stiffness contrast 1e6", "two cubes, E = 1e3 and 1e9 Pa, in one solve, both pushed",
             [Part(cube(), E=1e3, push=corner_push(5.0)), Part(cube(), E=1e9, push=corner_push(5.0))]),
    # convergence is tested per body, so a 1e11 J body does not set the scale for 1 J ones
    HardCase("huge impulse", "one corner of a 1 m cube set to 1e5 m/s",
             [Part(cube(), push=[(0, np.array([1e5, 0.0, 0.0]))])], dt=0.1, steps=40),
    HardCase("large dt 0.5 s", "a cube pushed at 5 m/s from an inverted start",
             [Part(cube(), push=corner_push(5.0))], dt=0.5, steps=20, inverted=True),
    HardCase("large dt 0.5 s, extremes", "nu = 0.4999 and E = 1e9 cubes pushed at 5 m/s",
             [Part(cube(), nu=0.4999, push=corner_push(5.0)), Part(cube(), E=1e9, push=corner_push(5.0))],
             dt=0.5, steps=20),
    HardCase("1000 steps", "a 6-tet cube pushed at 3 m/s (10 s of motion)",
             [Part(cube(cells=1), push=[(0, np.array([3.0, 0.0, 0.0]))])], dt=0.01, steps=1000),
]


# Time steps at which every hard case must show total energy that never rises from one step
# to the next (tests/test_energy.py, docs/robustness.md), and the rise allowed per step,
# relative to the case's starting energy, in each precision.
ENERGY_DTS = (0.001, 0.02, 0.1, 0.5)
ENERGY_STEPS = 15
ENERGY_TOLERANCE = {"f32": 1e-3, "f64": 1e-6}


# Bodies dropped and spun onto the ground (issue 23): total energy, now with the ground's
# contact energy, must never rise either, at every dt of ENERGY_DTS, with either integrator.
# Each is a 0.5 m cube (cells=2) whose bottom starts GROUND_GAP above the plane, falling at
# 2 m/s and spinning at 3 rad/s about z, without damping (the hardest case for the promise).
GROUND_MATERIALS = [(1e3, 0.3), (1e3, 0.49995), (5e4, 0.49995), (1e9, 0.3), (1e9, 0.49995)]   # (E Pa, nu)
GROUND_GAP = 0.02            # m
GROUND_STEPS = {0.001: 60, 0.02: 40, 0.1: 30, 0.5: 20}      # enough to land and bounce or settle


def ground_scene(dt, integrator="backward-euler", methods=METHODS, damping=None, steps=None):
    """Every GROUND_MATERIALS cube once per method, laid out 3 m apart along x, dropped and spun
    onto the plane y = 0 under gravity. Returns (scene, layout) with layout [(name, method, [body])]."""
    bodies, initial, layout = [], [], []
    for E, nu in GROUND_MATERIALS:
        for method in methods:
            b = len(bodies)
            mesh = cube(size=(0.5, 0.5, 0.5))
            shift = np.array([3.0 * b, 0.25 + GROUND_GAP, 0.0])
            name = f"E {E:g} Pa, nu {nu:g}"
            bodies.append(Body(f"{name} {method}", TetMesh(mesh.vertices + shift, mesh.tets, mesh.source),
                               Material(E, nu, 1000.0), method))
            initial += [Initial(Selection(b), "velocity", (np.array([0.0, -2.0, 0.0]),)),
                        Initial(Selection(b), "spin", (np.array([0.0, 0.0, 1.0]), 3.0))]
            layout.append((name, method, [b]))
    damping = damping or Effects()
    effects = Effects(alpha=damping.alpha, beta=damping.beta, gravity=(0.0, -9.81, 0.0), ground=0.0, friction=0.5)
    scene = Scene(f"ground drops dt {dt:g} s", bodies, effects=effects,
                  solver=SolverSettings(dt=dt, tolerance=1e-4, max_iterations=400, integrator=integrator),
                  initial=initial)
    return scene, layout


def build_scene(cases, methods=METHODS):
    """One scene holding every case's bodies once per method, laid out 3 m apart along x.

    Returns (scene, layout) with layout [(case, method, [body indices])].
    """
    bodies, initial, layout = [], [], []
    for case in cases:
        for method in methods:
            ids = []
            for part in case.parts:
                shift = np.array([3.0 * len(bodies), 0.0, 0.0])
                mesh = TetMesh(part.mesh.vertices + shift, part.mesh.tets, part.mesh.source)
                ids.append(len(bodies))
                bodies.append(Body(f"{case.name} {method} {len(ids)}", mesh,
                                   Material(part.E, part.nu, part.density), method))
                for vertex, velocity in part.push:
                    initial.append(Initial(Selection(ids[-1], vertices=np.array([vertex])),
                                           "velocity", (velocity,)))
            layout.append((case, method, ids))
    dt, steps = cases[0].dt, cases[0].steps
    scene = Scene(f"hard cases dt {dt:g} s x {steps}", bodies, effects=DAMPING,
                  solver=SolverSettings(dt=dt, tolerance=1e-4, max_iterations=400),
                  initial=initial)
    return scene, layout


def mirror_inverted(sim, layout):
    """Write the inverted start state: each inverted case's bodies mirrored through x = their centre."""
    x = sim.positions()
    for case, _, ids in layout:
        if case.inverted:
            for b in ids:
                s = sim.model.bodies[b].vertices
                centre = x[s, 0].mean()
                x[s, 0] = 2 * centre - x[s, 0]
    sim.set_state(x, sim.velocities())


def groups(cases=HARD_CASES):
    """Cases that can share one Simulation: same dt and number of steps."""
    key = lambda case: (case.dt, case.steps)  # noqa: E731
    return [list(group) for _, group in groupby(sorted(cases, key=key), key=key)]


# ---------------------------------------------------------------- bodies that meet (contact, issue 35)

# Each must end every step with no surface vertex inside another body's surface and no surface
# edge through another body's triangle (tests/test_contact_hard.py checks with numpy, apart
# from the contact code), its total energy never rising (but at an impulse), and finite.
# Corotational bodies of E 1e5 Pa (the plate 1e6), contact distance 0.01 m.
CONTACT_DTS = (0.1, 0.01, 0.001)
CONTACT_SECONDS = {"plate": 0.05, "stack": 1.0, "thrown": 0.6, "fold": 0.5}
FOLD_SPEED = 3.0                               # m/s: the hairpin's arm tips thrown towards each other
THROW_TIME, THROW_SPEED = 0.3, 10.0          # s, m/s: the ball's impulse towards the resting pile


def contact_box(name, size, cells, position, E=1e5):
    """A corotational box body (density 1000 kg/m^3, nu 0.3) of `size` m centred at `position`."""
    mesh = cube(cells=cells, size=size)
    return Body(name, TetMesh(mesh.vertices + np.asarray(position, float), mesh.tets, mesh.source),
                Material(E, 0.3, 1000.0), "corotational")


def contact_case(name, dt):
    """A contact hard case at dt: "plate10" and "plate100" (a 4 cm plate hitting a free block at
    10 or 100 m/s, no gravity), "stack" (5 boxes of 0.4 m stacked on the ground) or "thrown"
    (a 0.3 m box thrown at 10 m/s into a stack of 3 at THROW_TIME) or "fold" (one U-shaped bar
    whose arms are thrown together: it folds onto itself, self-contact)."""
    contact = ContactEffect(distance=0.01, friction=0.3)
    initial, impulses = [], []
    if name == "fold":
        bodies, initial = hairpin()
        effects = Effects(contact=contact)
    elif name.startswith("plate"):
        speed = float(name[len("plate"):])
        bodies = [contact_box("block", (1.0, 0.5, 1.0), (4, 2, 4), (0.0, 0.0, 0.0)),
                  contact_box("plate", (0.8, 0.04, 0.8), (4, 1, 4), (0.05, 0.5, 0.0), E=1e6)]
        initial.append(Initial(Selection(1), "velocity", (np.array([0.0, -speed, 0.0]),)))
        effects = Effects(contact=ContactEffect(distance=0.01))
    else:
        count = 5 if name == "stack" else 3
        bodies = [contact_box(f"box {k}", (0.4, 0.4, 0.4), (2, 2, 2), (0.005 * k, 0.21 + 0.43 * k, 0.0))
                  for k in range(count)]
        if name == "thrown":
            bodies.append(contact_box("ball", (0.3, 0.3, 0.3), (2, 2, 2), (-1.5, 0.6, 0.0)))
            impulses.append(Impulse(THROW_TIME, Selection(count), np.array([THROW_SPEED, 0.0, 0.0])))
        effects = Effects(gravity=(0.0, -9.81, 0.0), ground=0.0, friction=0.4, contact=contact)
    scene = Scene(f"{name} dt {dt:g} s", bodies, effects=effects, solver=SolverSettings(dt=dt),
                  initial=initial, impulses=impulses)
    return scene, max(1, round(CONTACT_SECONDS[name.rstrip("0123456789")] / dt))


def hairpin():
    """A U of 0.6 x 0.8 x 0.2 m (cells of 0.2 m, E 1e5 Pa): a base and two arms 0.2 m apart, the
    arms bent towards each other, their tips at FOLD_SPEED. Returns ([body], [Initial])."""
    mesh = cube(cells=(3, 4, 1), size=(0.6, 0.8, 0.2), keep=lambda i, j, k: i != 1 or j == 0)
    body = Body("hairpin", mesh, Material(1e5, 0.3, 1000.0), "corotational")
    x, initial = mesh.vertices, []
    for height in np.unique(x[:, 1]):
        for side in (-1.0, 1.0):                 # the left arm moves right, the right one left
            ids = np.flatnonzero((x[:, 1] == height) & (side * x[:, 0] > 0))
            speed = FOLD_SPEED * max(height + 0.2, 0.0) / 0.6
            initial.append(Initial(Selection(0, vertices=ids), "velocity", (np.array([-side * speed, 0.0, 0.0]),)))
    return [body], initial
