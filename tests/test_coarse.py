"""The two-level preconditioner (fem/coarse.py): its coarse matrix against an assembled one,
rigid motions in its null space, a symmetric positive definite P that follows a spinning
body, and the same steps as block Jacobi in fewer iterations."""

import numpy as np
import pytest
import scipy.sparse as sp
from conftest import make_scene

import fem
import fem.reduce
from app.bench.direct import DirectSolver
from fem.coarse import Patches, coarse_matrices, patches, rigid_modes
from fem.scene import Effects, Initial, Selection, SolverSettings
from scenes.hard_cases import cube

pytestmark = pytest.mark.usefixtures("f64")


def bar(E=1e5, nu=0.3, pinned=None, method="corotational", **solver):
    """A 2 x 1 x 1 m bar of 6^3 stretched cells (6 tets each; 343 vertices, 4 patches), spinning
    about y and twisting about x."""
    mesh = cube(cells=6, size=(1.0, 1.0, 1.0))
    mesh = type(mesh)(mesh.vertices * [2.0, 1.0, 1.0], mesh.tets, mesh.source)
    settings = dict(dt=0.02, tolerance=1e-8, max_iterations=1000, step="single", preconditioner="two-level")
    scene = make_scene(mesh, method, E=E, nu=nu, density=1000.0, pinned=pinned,
                       solver=SolverSettings(**{**settings, **solver}))
    scene.initial = [Initial(Selection(None), "spin", (np.array([0.0, 1.0, 0.0]), 2.0)),
                     Initial(Selection(None), "twist", (np.array([1.0, 0.0, 0.0]), 3.0))]
    return scene


def rest_frame_matrix(sim):
    """Q0^T A Q0 from the baseline's assembled A = cM M + cK K at rest (app/bench/direct.py: its own code)."""
    direct = DirectSolver(sim, backend="superlu")
    A = direct.system_matrix(np.broadcast_to(np.eye(3), (sim.model.n_tets, 3, 3)))
    patch = sim.solver.patches.patch_np
    Phi, _ = rigid_modes(sim.model.rest_positions_np, patch, sim.model.mass_np, sim.model.free_np.astype(float))
    n = len(patch)
    rows = np.repeat(np.arange(3 * n), 6)
    cols = (6 * np.repeat(patch, 3)[:, None] + np.arange(6)).ravel()
    Q = sp.csr_matrix((Phi.reshape(3 * n, 6).ravel(), (rows, cols)), shape=(3 * n, 6 * (patch.max() + 1)))
    return (Q.T @ A @ Q).toarray()


def test_patches_split_each_body_evenly():
    X = np.random.default_rng(0).random((1000, 3)) * [4.0, 1.0, 1.0]
    body = type("Body", (), {"vertices": range(0, 1000)})
    patch = patches(X, [body], max_patches=128)
    sizes = np.bincount(patch)
    assert len(sizes) == 11 and sizes.max() - sizes.min() <= 1      # about 90 vertices each
    assert len(np.bincount(patches(X, [body], max_patches=4))) <= 4


def test_coarse_matrix_is_the_assembled_matrix_seen_by_the_patches():
    pinned = np.flatnonzero(cube(cells=6).vertices[:, 0] < -0.49)
    sim = fem.Simulation(bar(pinned=pinned), integrator="backward-euler")   # H for h = dt (sim.coefficients)
    sim.step()
    patches_ = sim.solver.patches
    assert patches_.count[None] == 4
    cM, cK = sim.coefficients
    reference = rest_frame_matrix(sim)
    np.testing.assert_allclose(patches_.coarse_matrix(cM, cK), reference, atol=1e-10 * np.abs(reference).max())
    sim.set_material(0, 3e5, 0.45)                            # a live edit: the same matrices, rescaled
    sim.step()
    reference = rest_frame_matrix(sim)
    np.testing.assert_allclose(patches_.coarse_matrix(cM, cK), reference, atol=1e-10 * np.abs(reference).max())
    used = 6 * patches_.count[None]
    np.testing.assert_allclose(patches_.coarse_inverse.to_numpy()[:used, :used] @ reference, np.eye(used),
                               atol=1e-8)


def test_rigid_motions_of_a_patch_have_no_stiffness():
    mesh = cube(cells=3)
    mu, lam = 3e4, 5e4
    one = np.zeros(len(mesh.vertices), np.int64)
    ones = np.ones(len(mesh.vertices))
    M, K_mu, K_lam = coarse_matrices(mesh.vertices, mesh.tets, ones, ones, one)
    assert np.abs(mu * K_mu + lam * K_lam).max() <= 1e-10 * mu   # translations and rotations strain nothing
    assert np.linalg.eigvalsh(M).min() > 0                    # but they carry mass
    two = (mesh.vertices[:, 0] > 0).astype(np.int64)
    _, K_mu, K_lam = coarse_matrices(mesh.vertices, mesh.tets, ones, ones, two)
    eigenvalues = np.linalg.eigvalsh(mu * K_mu + lam * K_lam)
    assert np.sum(eigenvalues > 1e-8 * eigenvalues.max()) == 6   # two patches: only their relative motion strains
    assert eigenvalues.min() > -1e-8 * eigenvalues.max()


def preconditioner_reference(sim, r):
    """D^-1 r + Q A_c^-1 Q^T r, filtered, in numpy from the solver's fields."""
    solver, p = sim.solver, sim.solver.patches
    n, count = sim.model.n_vertices, p.count[None]
    free = sim.model.free_np[:, None]
    r = r * free
    R = p.frame.to_numpy()[:count]
    patch = p.patch_np
    Y = sim.model.rest_positions_np - p.centre.to_numpy()[patch]
    f = np.einsum("nji,nj->ni", R[patch], r)                                   # R_a^T r_i
    g = np.zeros((count, 6))
    np.add.at(g, patch, np.hstack([f, np.cross(Y, f)]))
    y = (p.coarse_inverse.to_numpy()[:6 * count, :6 * count] @ g.ravel()).reshape(count, 6)
    coarse = np.einsum("nij,nj->ni", R[patch], y[patch, :3] + np.cross(y[patch, 3:], Y))
    jacobi = np.einsum("nij,nj->ni", solver.preconditioning.block_inverses(), r)
    return (jacobi + coarse) * free


@pytest.mark.parametrize("loops", ["serial", "parallel", "a GPU's"])
def test_preconditioner_is_symmetric_positive_definite_and_follows_the_body(loops, monkeypatch, request):
    """Also with parallel loops and chunks of 16 members, so that the restriction's sums in stages
    (fem/reduce.py) split every patch into several chunks, as on a large mesh; and laid out as on
    a GPU (interleaved chunks, stages between, the coarse product's rows in pieces)."""
    if loops != "serial":
        monkeypatch.setattr(fem.runtime, "PARALLEL_MIN", {"tets": 0, "vertices": 0})
        monkeypatch.setattr(fem.reduce, "CHUNK", 16)
    if loops == "a GPU's":
        monkeypatch.setattr(fem.runtime, "on_cpu", lambda: False)
        monkeypatch.setattr(fem.reduce, "GPU_CHUNK", 16)
        monkeypatch.setattr(fem.reduce, "FAN_IN", 2)
        fem.pool.clear()                          # parts made for a CPU's layout are not borrowed,
        request.addfinalizer(fem.pool.clear)      # nor these by later tests
    pinned = np.flatnonzero(cube(cells=6).vertices[:, 0] < -0.49)
    sim = fem.Simulation(bar(pinned=pinned))
    for _ in range(10):
        sim.step()
    frames = sim.solver.patches.frame.to_numpy()[:4]
    assert np.abs(frames - np.eye(3)).max() > 0.05            # the patches turned with the bar
    patches = sim.solver.patches
    if loops != "serial":
        assert not patches.serial and patches.sums.stages[0].chunks[None] > 2 * patches.count[None]
    assert (patches.parts > 1, len(patches.sums.stages) > 1) == (loops == "a GPU's",) * 2
    rng = np.random.default_rng(1)
    n = sim.model.n_vertices
    free = sim.model.free_np[:, None]
    u, w = rng.standard_normal((n, 3)) * free, rng.standard_normal((n, 3)) * free   # as CG's r: filtered
    Pu, Pw = (sim.solver.linear.apply_preconditioner(a, sim.solver.preconditioner) for a in (u, w))
    np.testing.assert_allclose(Pu, preconditioner_reference(sim, u), rtol=1e-10, atol=1e-14)
    assert np.isclose(np.vdot(w, Pu), np.vdot(u, Pw), rtol=1e-10)
    assert np.vdot(u, Pu) > 0
    assert np.abs(Pu[pinned]).max() == 0


def test_patch_frames_are_a_rigidly_turned_bodys_rotation():
    sim = fem.Simulation(bar(method="corotational"))
    angle, axis = 0.8, np.array([1.0, 2.0, 2.0]) / 3.0
    K = np.cross(np.eye(3), axis)
    R = np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K
    sim.set_state(sim.model.rest_positions_np @ R.T + [0.3, 0.0, 0.0], np.zeros((sim.model.n_vertices, 3)))
    sim.step()
    frames = sim.solver.patches.frame.to_numpy()[:sim.solver.patches.count[None]]
    np.testing.assert_allclose(frames, np.broadcast_to(R, frames.shape), atol=1e-9)


@pytest.mark.parametrize("E, nu, share", [(1e5, 0.3, 0.95), (1e6, 0.45, 0.75)])
def test_two_level_takes_the_same_steps_in_fewer_iterations(E, nu, share):
    runs = {}
    for preconditioner in ("jacobi", "two-level"):    # backward Euler, h = dt: the trapezoidal rule's
        # h = dt/2 leaves more mass in H = M + h^2 K, which block Jacobi handles well alone
        sim = fem.Simulation(bar(E=E, nu=nu, preconditioner=preconditioner, integrator="backward-euler"))
        iterations = sum(sim.step()["solver_iters"] for _ in range(5))
        runs[preconditioner] = sim.positions(), iterations
    (x_jacobi, jacobi), (x_two, two) = runs["jacobi"], runs["two-level"]
    np.testing.assert_allclose(x_two, x_jacobi, atol=1e-7)
    print(f"E {E:g}: {jacobi} iterations with block Jacobi, {two} two-level")
    assert two < share * jacobi


@pytest.mark.parametrize("step", ["single", "newton"])
def test_pins_ground_and_gravity_give_the_same_steps_as_block_jacobi(step):
    """A bar pinned at one end sags under gravity onto the ground, with damping: the filtered
    rows (pins), the ground's blocks and the coarse level agree, so both preconditioners take
    the same steps. Newton does not meet 1e-9 on every step (it did not before the ground became
    an energy either), and friction's sticking turns what is left into millimetres, so Newton's
    case runs without friction."""
    pinned = np.flatnonzero(cube(cells=6).vertices[:, 0] < -0.49)
    runs = {}
    for preconditioner in ("jacobi", "two-level"):
        scene = bar(E=3e4, pinned=pinned, step=step, preconditioner=preconditioner, tolerance=1e-9,
                    newton_tolerance=1e-9)
        scene.initial = []
        scene.effects = Effects(gravity=(0.0, -9.81, 0.0), ground=-0.7, alpha=0.1, beta=0.002,
                                friction=0.5 if step == "single" else 0.0)
        sim = fem.Simulation(scene)
        energies = [sim.stats()["total_energy"]]
        for _ in range(20):
            sim.step()
            energies.append(sim.stats()["total_energy"])
        runs[preconditioner] = sim.positions(), np.array(energies)
    (x_jacobi, e_jacobi), (x_two, e_two) = runs["jacobi"], runs["two-level"]
    assert x_two[:, 1].min() < -0.69                          # the free end reached the ground
    np.testing.assert_allclose(x_two, x_jacobi, atol=1e-6 if step == "single" else 1e-5)
    if step == "newton":
        assert np.diff(e_two).max() <= 1e-9 * abs(e_two[0])
    np.testing.assert_allclose(e_two, e_jacobi, rtol=1e-5 if step == "single" else 1e-4)


def test_linear_bodies_keep_unrotated_patches():
    sim = fem.Simulation(bar(method="linear", tolerance=1e-6))
    for _ in range(5):
        sim.step()
    frames = sim.solver.patches.frame.to_numpy()[:sim.solver.patches.count[None]]
    np.testing.assert_array_equal(frames, np.broadcast_to(np.eye(3), frames.shape))
    sim.set_method("corotational")
    sim.step()
    assert np.abs(sim.solver.patches.frame.to_numpy()[0] - np.eye(3)).max() > 1e-3


def test_preconditioner_setting_is_checked_and_auto_picks_by_size():
    with pytest.raises(fem.FemError, match="preconditioner must be one of"):
        SolverSettings(preconditioner="multigrid").check("scene")
    small, large = bar(preconditioner="auto"), bar(preconditioner="auto")
    mesh = cube(cells=12)                                     # 2197 vertices: from 2000 up, two-level
    large.bodies[0].mesh = type(mesh)(mesh.vertices * [2.0, 1.0, 1.0], mesh.tets, mesh.source)
    assert fem.Simulation(small).step()["preconditioner"] == "jacobi"
    assert fem.Simulation(large).solver.preconditioner == "two-level"
    jacobi_iteration = bar(preconditioner="two-level", method="corotational")
    jacobi_iteration.solver.method = "jacobi"                 # the preconditioner is PCG's alone
    assert fem.Simulation(jacobi_iteration).step()["preconditioner"] is None


@pytest.mark.parametrize("precision", ["f64", "f32"])    # f32 last: the module's other tests run in f64
def test_energy_never_rises_with_the_two_level_newton_step(precision):
    """The step's promise holds whatever the preconditioner: a spinning, twisting near-incompressible
    bar, Newton step, two-level PCG at the scenes' default tolerance."""
    from scenes.hard_cases import ENERGY_TOLERANCE
    fem.init("cpu", precision)
    sim = fem.Simulation(bar(E=1e6, nu=0.45, step="newton", tolerance=1e-4))
    energies = [sim.stats()["total_energy"]]
    for _ in range(40):
        assert sim.step()["preconditioner"] == "two-level"
        energies.append(sim.stats()["total_energy"])
    rise = np.diff(energies).max() / abs(energies[0])
    assert np.isfinite(energies).all() and rise <= ENERGY_TOLERANCE[precision]
    # the conserving scheme: it ends where it began, to round-off (either way)
    assert abs(energies[-1] - energies[0]) <= ENERGY_TOLERANCE[precision] * abs(energies[0])
