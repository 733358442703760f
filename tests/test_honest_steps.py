"""What a step reports is what it did (issue 61), each checked against a reference of its own:

- a body at rest is no failed step: round-off's rises (1e-28 J) trim nothing;
- the integrator a step names is the one it took: the trapezoidal rule with a ground is the theta
  rule with rho_infinity 0.9, and a body in free flight above the ground falls as that rule's
  own formula says (analytic), or exactly 1/2 g t^2 when the scene asks for rho_infinity 1;
- `residual` is the relative residual at the answer, recomputed from the states with numpy's
  own forces (app/bench/direct.py), in float32 too;
- backward Euler's stiffness damping measures strain rates in the rotated frame: a spinning box
  keeps its spin as an undamped one does (angular momentum about the centre, from the states);
- a stiff spinning cube converges under every integrator, with or without a ground below (from
  its rigid turn, not its tangent), and keeps its spin but for the integrator's own loss;
- boxes falling freely in a contact scene converge and take no rigid step: their centres fall
  as 1/2 g t^2 (analytic).
"""

import numpy as np
import pytest

import fem
from app.bench.direct import DirectSolver
from conftest import make_scene
from fem.scene import Body, Effects, Material, Scene, SolverSettings
from scenes.hard_cases import cube
from test_energy_scheme import forces
from test_step_promises import angular_momentum

G = 9.81


def spun(sim, omega, vertices=slice(None)):
    """Sets the given vertices spinning rigidly at omega (rad/s) about their centre of mass, the rest still."""
    x, v = sim.positions(), np.zeros_like(sim.positions())
    m = sim.model.mass.to_numpy()[:sim.model.n_vertices].astype(np.float64)[vertices, None]
    centre = (m * x[vertices]).sum(0) / m.sum()
    v[vertices] = np.cross(np.asarray(omega, float), x[vertices] - centre)
    sim.set_state(x, v)


@pytest.mark.parametrize("precision", ["f32", "f64"])
def test_a_body_at_rest_beside_a_spinning_one_is_never_trimmed(request, precision):
    """No gravity: the still rod's energy terms are all 0, and its energy wanders by round-off
    (about 1e-28 J in float64), which trimmed it on 25 to 99 of 100 steps before."""
    request.getfixturevalue(precision)
    rod = cube((3, 1, 1), (1.0, 0.2, 0.2))
    box = cube(2, (0.4, 0.4, 0.4))
    bodies = [Body("rod", rod, Material(1e5, 0.3, 1000.0), "corotational"),
              Body("box", type(box)(box.vertices + [3.0, 0.0, 0.0], box.tets, box.source), Material(1e5, 0.3, 1000.0),
                   "corotational")]
    sim = fem.Simulation(Scene("rest", bodies, effects=Effects(), solver=SolverSettings(dt=0.02)))
    n_rod = len(rod.vertices)
    spun(sim, (0.0, 4.0, 0.0), slice(n_rod, None))
    start = sim.positions()[:n_rod]
    trims = sum(sim.step()["energy_limited"] for _ in range(100))
    assert trims == 0
    assert np.abs(sim.positions()[:n_rod] - start).max() < 1e-9 * (1 if precision == "f64" else 1e6)


@pytest.mark.parametrize("rho, fall_ratio", [(None, 1.0 + (2.0 / 1.9 - 1.0) * 0.02 / 0.5), (1.0, 1.0)])
def test_the_trapezoidal_rule_with_a_ground_names_what_it_takes(f64, capfd, rho, fall_ratio):
    """The theta rule falls x_n - x_0 = 1/2 g t^2 + (theta - 1/2) g dt t under constant g, theta =
    1 / (1 + rho): with a ground, "trapezoidal" takes rho 0.9 unless the scene names rho, says so
    once on stderr, and each step's `integrator` says which rule it was."""
    scene = make_scene(cube(2, (0.5, 0.5, 0.5)), E=1e6, position=(0.0, 3.0, 0.0),
                       effects=Effects(gravity=(0.0, -G, 0.0), ground=0.0),
                       solver=SolverSettings(dt=0.02, integrator="trapezoidal", rho_infinity=rho, tolerance=1e-10))
    sim = fem.Simulation(scene)
    notes = [line for line in capfd.readouterr().err.splitlines() if "rho_infinity" in line]
    y0 = sim.positions()[:, 1].mean()
    names = {sim.step()["integrator"] for _ in range(25)}
    fallen = y0 - sim.positions()[:, 1].mean()
    assert fallen / (0.5 * G * sim.t ** 2) == pytest.approx(fall_ratio, abs=1e-6)
    if rho is None:
        assert names == {"trapezoidal (rho_infinity 0.9)"} and len(notes) == 1
        assert "set solver.rho_infinity = 1" in notes[0]
    else:
        assert names == {"trapezoidal"} and notes == []


@pytest.mark.parametrize("E, nu", [(1e8, 0.3), (1e5, 0.49)])
def test_a_float32_residual_is_the_one_recomputed_from_the_states(f32, E, nu):
    """Backward Euler steps of a spinning box: the reported residual against numpy's
    max_b |M (v - v_n) - dt f(x)|_b / sqrt(|M v_n|_b^2 + |dt f(x)|_b^2) at the answer; before,
    float32's was divided by its round-off floor, 5.5 (nu 0.49) to 376 (E 1e8) times too small."""
    dt = 0.02
    scene = make_scene(cube(3), E=E, nu=nu, solver=SolverSettings(dt=dt, integrator="backward-euler"))
    sim = fem.Simulation(scene)
    spun(sim, (0.0, 3.0, 1.0))
    reference = DirectSolver(sim)
    m = sim.model.mass.to_numpy()[:sim.model.n_vertices].astype(np.float64)[:, None]
    ratios = []
    for _ in range(16):
        v_n = sim.velocities()
        info = sim.step()
        if info["energy_limited"] or (sim.solver.safeguards.body_deformation.to_numpy()[:1] != 1.0).any():
            continue                                   # the energy projection moved the answer
        f = forces(sim, reference)
        residual = np.linalg.norm(m * (sim.velocities() - v_n) - dt * f)
        scale = np.sqrt(((m * v_n) ** 2).sum() + ((dt * f) ** 2).sum())
        ratios.append(info["residual"] / (residual / scale))
    assert len(ratios) >= 3
    assert 0.5 <= min(ratios) and max(ratios) <= 2.0, ratios


def test_backward_euler_damping_keeps_a_spin(f64):
    """One backward Euler step of a box spinning at 3 rad/s, beta 0.1: the spin it keeps is the
    undamped step's (which loses about 0.2 % to backward Euler's own error), at every stiffness.
    Before, the damping took the step's chord velocities for a strain rate: 0.58 kept at E 5e7."""
    kept = {}
    for E in (5e5, 5e6, 5e7):
        for beta in (0.0, 0.1):
            scene = make_scene(cube(2, (0.5, 0.5, 0.5)), E=E, effects=Effects(beta=beta),
                               solver=SolverSettings(dt=0.02, integrator="backward-euler"))
            sim = fem.Simulation(scene)
            spun(sim, (0.0, 3.0, 0.0))
            L0 = np.linalg.norm(angular_momentum(sim))
            info = sim.step()
            assert info["converged"], (E, beta, info)
            kept[E, beta] = np.linalg.norm(angular_momentum(sim)) / L0
        assert kept[E, 0.1] >= 0.99, kept
        assert kept[E, 0.1] == pytest.approx(kept[E, 0.0], abs=2e-3), kept


def test_at_the_default_tolerances_halving_dt_never_makes_the_answer_worse(f64):
    """The spinning, twisting bar of app/bench/order.py at the default tolerances, 0.4 s, against
    the same rule at dt 0.000625 s solved to 1e-10: its error falls with dt at the trapezoidal
    rule's order. With a tolerance that did not follow dt, it rose from 1.7e-4 m at dt 0.01 s to
    2.1e-3 m at 0.0025 s: the solve's error per step, added up over more steps."""
    from app.bench.order import twisting_state

    def positions(dt, tolerance=None):
        scene, x, v = twisting_state(dt, "trapezoidal")
        defaults = SolverSettings()
        scene.solver = SolverSettings(dt=dt, integrator="trapezoidal", sleep=False,
                                      tolerance=tolerance or defaults.tolerance,
                                      newton_tolerance=1e-12 if tolerance else defaults.newton_tolerance)
        sim = fem.Simulation(scene)
        sim.set_state(x, v)
        for _ in range(round(0.4 / dt)):
            sim.step()
        return sim.positions()

    reference = positions(0.000625, tolerance=1e-10)
    errors = [np.abs(positions(dt) - reference).max() for dt in (0.02, 0.01, 0.005, 0.0025)]
    orders = np.log2(np.array(errors[:-1]) / errors[1:])
    assert (orders >= 1.8).all(), (errors, orders)


@pytest.mark.parametrize("precision, E, nu, spin", [("f64", 1e9, 0.49995, 3.0), ("f32", 1e7, 0.45, 10.0)])
@pytest.mark.parametrize("integrator, ground", [("backward-euler", None), ("backward-euler", -10.0), ("bdf2", None),
                                                ("trapezoidal", None), ("trapezoidal", -10.0)])
def test_a_stiff_spinning_cube_converges_from_its_rigid_turn(request, precision, E, nu, spin, integrator, ground):
    """A 0.5 m cube falling at 2 m/s and spinning at dt 0.02 s, with every integrator, in free
    flight (a ground far below, or none): Newton's first iterate, backward Euler's at x_n or a
    multistep rule's guess extrapolated from v_n, moved it along its turn's tangent, and at E 1e9,
    nu 0.49995 (f64) it stalled at a relative residual of 1 for 20 iterations a step (backward
    Euler with a ground, where it lost 87 % of its spin in 10 steps), or took 3 to 5 (BDF2, the
    trapezoidal rule: residuals up to 1.3e-3, a trimmed step); at E 1e7, nu 0.45, f32: 8 and 3. From its
    rigid turn (fem/implicit/fallback.py, arc_first_iterate) it takes at most 2 (one step in ten may take
    3: in f32 at the round-off floor, in f64 under backward Euler to converge), its residual
    within a few times the tolerance; its spin (angular momentum about the centre, summed in numpy
    from the states) loses no more than backward Euler's own (omega dt)^2 a step (the centripetal
    forces at x_(n+1) have a torque about x_n; BDF2 and the theta rule a ground gives the
    trapezoidal rule lose less), and none under the conserving scheme (the trapezoidal rule off
    the ground); its centre falls at g, and it stays a cube (no edge longer by 1e-3). (In float32
    a cube at E 1e9, nu 0.49995 cannot be resolved: the round-off of its positions alone strains
    it by 6e-8, lam times that is 2e5 Pa, and its residual stays 1.)"""
    request.getfixturevalue(precision)          # f32 gives the module its f64 back after
    box = cube(2, (0.5, 0.5, 0.5))
    scene = Scene("stiff", [Body("box", box, Material(E, nu, 1000.0), "corotational")],
                  effects=Effects(gravity=(0.0, -G, 0.0), ground=ground),
                  solver=SolverSettings(dt=0.02, integrator=integrator))
    sim = fem.Simulation(scene)
    spun(sim, (0.0, 0.0, spin))
    sim.set_state(sim.positions(), sim.velocities() + [0.0, -2.0, 0.0])
    L0 = angular_momentum(sim)
    # the conserving scheme's energy-momentum step minimises again from each answer with its
    # inertia target set there, and at a smaller tolerance where the answer would leave the energy
    # projection more than a share of the deformation's energy (fem/implicit/energy_momentum.py)
    most = 12 if (integrator, ground) == ("trapezoidal", None) else 2
    # in float32 a step may end its second iteration just above the round-off floor and take a third
    # (the cube at 10.5 rad/s under backward Euler: step 5 of 10; at 10 rad/s step 4 where PCG's sums
    # round otherwise); in float64 backward Euler's may take a third where its gradient still falls
    # (newton.py, FALLING: step 3 of 10, which with two ended settled at 2.2 times the tolerance, and
    # 8 of the other 9 at 1.4 to 4 times): one such step in ten
    slack, iterations = 1, []
    for _ in range(10):
        info = sim.step()
        iterations.append(info["newton_iters"])
        assert info["newton_iters"] <= most + slack and info["residual"] <= 1e-2 and not info["energy_limited"], info
    assert sum(iterations) <= 10 * most + slack, iterations
    # backward Euler's own loss on a stiff rotor: dL = h sum x_n x f(x_(n+1)) = -(omega h)^2 L a step
    loss = 1e-6 if (integrator, ground) == ("trapezoidal", None) else (spin * 0.02) ** 2
    assert np.linalg.norm(angular_momentum(sim)) >= 0.99 * (1.0 - loss) ** 10 * np.linalg.norm(L0)
    m = sim.model.mass.to_numpy()[:sim.model.n_vertices].astype(np.float64)
    assert (m * sim.velocities()[:, 1]).sum() / m.sum() == pytest.approx(-2.0 - G * 0.2, rel=1e-3)
    edges = np.linalg.norm(sim.positions()[box.tets[:, 0]] - sim.positions()[box.tets[:, 1]], axis=1)
    rest = np.linalg.norm(box.vertices[box.tets[:, 0]] - box.vertices[box.tets[:, 1]], axis=1)
    assert np.abs(edges / rest - 1.0).max() <= 1e-3


def centre_and_momentum(sim):
    """(centre of mass (3,), its velocity (3,)), summed in numpy from the states."""
    m = sim.model.mass.to_numpy()[:sim.model.n_vertices].astype(np.float64)[:, None]
    return (m * sim.positions()).sum(0) / m.sum(), (m * sim.velocities()).sum(0) / m.sum()


@pytest.mark.parametrize("E, spin, wobble", [(1e5, (1.0, 2.0, 0.5), 3.0), (1e7, (1.0, 2.0, 0.5), 3.0),
                                             (1e3, (0.0, 0.0, 0.0), 0.0), (1e7, (0.0, 0.0, 0.0), 0.0)])
def test_the_centre_of_mass_falls_on_the_parabola(f64, E, spin, wobble):
    """A 1.2 m rod thrown spinning and twisting (or released at rest) under gravity, the
    conserving scheme at the default tolerances, 1 s: its centre of mass is where the parabola
    c_0 + v_0 t + g t^2 / 2 puts it, to 1e-9 of the fall, and moves at v_0 + g t (analytic).
    The energy projection corrects the internal motion only; its shift along g took the spinning
    rod 4.4e-5 m off the parabola in 1 s (E 1e5) and the released one 1e-12 m. The rod released at
    rest is the case where the solve's residual leaves its deformation more energy than its
    velocities hold: its positions pay (fem/implicit/projection.py), and nothing is trimmed."""
    rod = cube(3, (1.2, 0.2, 0.2))
    scene = make_scene(rod, E=E, position=(0.0, 3.0, 0.0), effects=Effects(gravity=(0.0, -G, 0.0)),
                       solver=SolverSettings(dt=0.02, integrator="trapezoidal", sleep=False))
    sim = fem.Simulation(scene)
    x = sim.positions()
    c0, _ = centre_and_momentum(sim)
    r = x - c0
    v = np.cross(spin, r) + np.cross([wobble, 0.0, 0.0], r) * r[:, :1] + [0.3, 1.0, 0.0]
    sim.set_state(x, v)
    c0, v0 = centre_and_momentum(sim)
    E0 = sim.stats()["total_energy"]
    g = np.array([0.0, -G, 0.0])
    worst, trims = 0.0, 0
    for k in range(1, 51):
        trims += sim.step()["energy_limited"]
        t = 0.02 * k
        c, vc = centre_and_momentum(sim)
        worst = max(worst, np.abs(c - (c0 + v0 * t + 0.5 * g * t * t)).max())
        assert np.abs(vc - (v0 + g * t)).max() <= 1e-12 * G * t
    assert worst <= 1e-9 * 0.5 * G, worst
    assert trims == 0
    assert abs(sim.stats()["total_energy"] - E0) <= 1e-9 * abs(E0)


@pytest.mark.parametrize("precision", ["f32", "f64"])
def test_boxes_falling_freely_in_a_contact_scene_take_no_rigid_step(request, precision):
    """two_boxes before the boxes touch anything: a converged solve leaves the energy a rise within
    its tolerance's band (4e-10 to 9e-8 J in float64), which a body that may not move its positions
    (contact) took for a failed solve, a rigid step on 3 of its first 3 steps. Every one of those
    steps converges now, and each box's centre falls as 1/2 g t^2 (BDF2 is exact on a parabola)."""
    import scenes
    request.getfixturevalue(precision)
    sim = fem.Simulation(scenes.load_scene("two_boxes"))
    m = sim.model.mass.to_numpy()[:sim.model.n_vertices].astype(np.float64)
    body = sim.model.vertex_body.to_numpy()[:sim.model.n_vertices]

    def centres():
        x = sim.positions().astype(np.float64)
        return np.array([(m[body == b, None] * x[body == b]).sum(0)[1] / m[body == b].sum() for b in (0, 1)])

    start = centres()
    infos = [sim.step() for _ in range(3)]
    assert [(info["converged"], info["energy_limited"]) for info in infos] == [(True, 0)] * 3
    t = 3 * sim.scene.solver.dt
    assert np.allclose(start - centres(), 0.5 * G * t * t, rtol=1e-4 if precision == "f64" else 1e-3)


@pytest.mark.parametrize("precision, integrator", [("f64", "trapezoidal"), ("f64", "bdf2"), ("f32", "trapezoidal")])
def test_a_stiff_box_landing_on_the_ground_is_not_frozen_by_its_rigid_steps(request, precision, integrator):
    """A 0.5 m cube at E 1e9 Pa dropped 1 cm onto the ground: the step after it lands rises in
    energy under a second-order rule (the ground's penalty rings at 50 times 1/dt), and the body
    takes its rigid step, which on the ground keeps it where it was, at rest in the penalty. The
    next step then started from the same state and failed the same way: the box stayed frozen
    1.96e-4 m deep with every later step a rigid one. A body whose failed step leaves it as it
    was is now `strained`: the next step is backward Euler's, and the box settles at the
    penalty's sag with converged steps and an energy that never rises (f64: 2 rigid steps, then
    none; f32: 4)."""
    request.getfixturevalue(precision)
    size, gap = 0.5, 0.01
    mesh = cube(cells=2, size=(size, size, size))
    box = Body("stiff box", type(mesh)(mesh.vertices + np.array([0.0, size / 2 + gap, 0.0]), mesh.tets, mesh.source),
               Material(1e9, 0.3, 1000.0), "corotational")
    scene = Scene("stiff landing", [box], effects=Effects(gravity=(0.0, -G, 0.0), ground=0.0, friction=0.5),
                  solver=SolverSettings(dt=0.02, integrator=integrator))
    sim = fem.Simulation(scene)
    energies, infos = [sim.stats()["total_energy"]], []
    for _ in range(20):
        infos.append(sim.step())
        energies.append(sim.stats()["total_energy"])
    trimmed = [k for k, info in enumerate(infos) if info["energy_limited"]]
    assert len(trimmed) <= 4 and all(k < 10 for k in trimmed), trimmed         # the landing's, not every step's
    assert all(info["converged"] for info in infos[10:]), [info["converged"] for info in infos]
    assert np.diff(energies).max() <= (1e-6 if precision == "f64" else 1e-4) * energies[0]
    lowest = sim.positions()[:, 1].min()
    assert -1e-4 < lowest < 0.0        # at the penalty's sag (2.7e-5 m in f64), not 1.96e-4 m deep
