"""The implicit step: backward Euler as a minimisation, solved matrix-free (method.md, section 6).

With x = x_n + dt v, one step finds the velocity v that minimises the incremental potential

    E(v) = 1/2 |v - v_n|_M^2 + dt/2 v^T D v - dt v^T M g + Psi(x_n + dt v)        (J)

(D = alpha M + beta K_n: Rayleigh damping with the stiffness frozen at the step's start;
Psi: the elastic energy, corotated linear or linear per body). Its stationarity condition
M (v - v_n) + dt D v - dt M g - dt f(x) = 0 is exactly backward Euler with damping.

Newton iterations minimise E: each solves H d = -grad E with the positive definite
H = (1 + dt alpha) M + (dt beta + dt^2) K(R), R: rotations at the current iterate, by
preconditioned CG or weighted Jacobi iteration, never assembling H, and a line search per
body accepts only iterates that lower that body's E_b. The first Newton iteration from v = 0
is the classical one-solve (stiffness-warping) step.

One module per part, each owning its fields and kernels; `ImplicitSolver` composes them:

    solver.py          ImplicitSolver.step: the step, top to bottom; StepInfo, Switches
    potential.py       E(v), grad E, H u: the inertia target and coefficients an integrator defines
    elasticity.py      the elastic terms tet by tet (corner values) and their gather per vertex
    rotations.py       the tets' rotations R (Bm R^T), warm-started, and the twist stiffness
    newton.py          Newton iterations, the per-body line search and stopping test, the one-solve step
    bend.py            a stiff body's trials: the turn of Newton's direction taken on its arc
    linear.py          PCG and Jacobi iteration on H d = -grad E
    preconditioner.py  block Jacobi and the coarse level (fem/coarse.py)
    effects.py         gravity, damping, pins and ground contact
    contact.py         contact between bodies and within one: the pairs' barrier, step bound
    friction.py        Coulomb friction between contact pairs, lagged
    broad_phase.py     contact's candidate pairs (a spatial hash) and islands
    islands.py         the line search of bodies that contact couples
    pair_geometry.py   one contact pair: its distance, normal and weights, and IPC's barrier
    sleep.py           which bodies the step moves
    energy_momentum.py the conserving scheme's energy-momentum step for stiff bodies (the algorithmic force)
    safeguards.py      finite results, momentum, no energy gain: the energy projection
    projection.py      the projection's move of positions, where scaled velocities cannot pay
    fallback.py        the rigid step of a body whose rise nothing pays for, and each body's rigid motion

Effects a scene leaves off are not compiled: gravity, pins, ground contact, contact between
bodies and stiffness damping are `ti.static` branches fixed when the solver is made (`Switches`), and rotations
are only extracted while some body is corotational. Per-vertex sums gather over the model's
adjacency (no atomics), so every run is the same bit for bit; contact's pair sums use atomics,
serial on the small meshes whose other loops are (the same bit for bit there too).
"""
