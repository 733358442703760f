"""Per-tet elasticity: one formula serves the force, the matrix-free product and the stats.

Symbols (Sifakis & Barbic 2012):
    Ds  columns x0-x3, x1-x3, x2-x3 of a tet's current corners (3x3)
    Bm  inverse of the same matrix at rest (3x3), so F = Ds Bm
    W   rest volume (m^3);  mu, lam  Lame parameters (Pa)
    R   polar rotation of F (fem/rotation.py; identity for linear tets)
The solver uses these through Bm R^T (see fem/implicit/rotations.py), the stats through R.
"""

import taichi as ti


@ti.func
def edge_matrix(a, b, c, d):
    """Columns a-d, b-d, c-d: the Ds of a tet with corners a, b, c, d."""
    return ti.Matrix.cols([a - d, b - d, c - d])


@ti.func
def linear_stress(eps, mu, lam):
    """Small-strain stress sigma = 2 mu eps + lam tr(eps) I (Pa)."""
    return 2.0 * mu * eps + lam * eps.trace() * ti.Matrix.identity(float, 3)


@ti.func
def corner_forces(P, Bm, W):
    """Forces on the four corners of a tet with first Piola stress P (N).

    H = -W P Bm^T holds the forces on corners 0..2 in its columns; corner 3
    gets minus their sum, so the tet exerts no net force.
    """
    H = -W * P @ Bm.transpose()
    f0 = ti.Vector([H[0, 0], H[1, 0], H[2, 0]])
    f1 = ti.Vector([H[0, 1], H[1, 1], H[2, 1]])
    f2 = ti.Vector([H[0, 2], H[1, 2], H[2, 2]])
    return f0, f1, f2, -(f0 + f1 + f2)


@ti.func
def is_finite(s):
    """True unless s is NaN or +-inf (or beyond 1e30, which no sane state reaches)."""
    return ti.abs(s) < 1e30


@ti.func
def energy_density(F, mu, lam, one):
    """psi = mu eps:eps + lam/2 tr(eps)^2 with eps = sym(F) - one I (J/m^3), in F's float type.

    F in the tet's rotated frame (F R^T, or R^T F: the same invariants); one = 1 gives the
    elastic energy density, one = 0 the quadratic form 1/2 eps:sigma(eps) of a velocity gradient.
    """
    eps = 0.5 * (F + F.transpose())
    for i in ti.static(range(3)):
        eps[i, i] -= one
    return mu * (eps * eps).sum() + 0.5 * lam * eps.trace() ** 2


@ti.func
def stiffness_block(h, W, mu, lam):
    """Diagonal 3x3 block of R Ke R^T for a corner whose rotated shape gradient is h = R g.

    Ke's block is W (lam g g^T + mu (g.g I + g g^T)); rotating it only turns g into R g.
    """
    hh = h.outer_product(h)
    return W * (lam * hh + mu * (h.dot(h) * ti.Matrix.identity(float, 3) + hh))
