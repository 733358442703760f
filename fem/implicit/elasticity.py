"""The elastic terms tet by tet, and their sum per vertex.

Every pass over tets writes one value per tet corner into `corner`; a pass over vertices
then sums the corners around each vertex (`gather`) over the model's adjacency, so no two
threads ever add into the same vertex (no atomics: every run is the same bit for bit).
Elastic forces f(x), the stiffness product K(R) d and the energy Psi(x) share the stress
function of fem/elastic.py and the rotated matrix Bm R^T of fem/implicit/rotations.py.

Fields (m tets of the capacity):
    corner (4m, 3)   per-corner values before the gather (N, or N/m times m/s)
"""

import taichi as ti

from fem.elastic import corner_forces, edge_matrix, energy_density, linear_stress
from fem.rotation import quaternion_matrix

NAIVE = 2                # Model.method(e) of a tet of the naive variant (fem.scene.METHODS)


@ti.data_oriented
class Elasticity:
    """Per-tet elastic passes for one model, with the rotations of `rotations`; the tets of a
    sleeping body (`sleep`) are skipped by the stiffness product."""

    def __init__(self, model, rotations, sleep, switches):
        self.model, self.rotations, self.sleep = model, rotations, sleep
        self.serial_tets, self.serial_vertices = switches.serial_tets, switches.serial_vertices
        self.corner = ti.Vector.field(3, float, 4 * model.capacity.tets)

    @ti.func
    def store_corners(self, e, f: ti.template()):
        for k in ti.static(range(4)):
            self.corner[4 * e + k] = f[k]

    @ti.func
    def gather(self, i):
        """Sum of the corner values of every tet around vertex i."""
        s = ti.Vector.zero(float, 3)
        for j in range(self.model.adjacency_start[i], self.model.adjacency_start[i + 1]):
            s += self.corner[self.model.adjacency[j]]
        return s

    @ti.func
    def elastic_stress(self, x: ti.template(), e):
        """sigma(sym(F R^T) - I) of tet e at positions x: the stress in the tet's rotated frame (Pa).

        The naive variant f = -R Ke R^T (x - X) rotates the rest shape too: its strain is
        sym(R^T (F - I)), in this frame sym(F R^T) - sym(R^T), not zero under a pure rotation."""
        F = self.model.edges(x, e) @ self.rotations.rotated_Bm[e]               # F R^T
        unstrained = ti.Matrix.identity(float, 3)
        if self.model.method(e) == NAIVE:
            Rt = quaternion_matrix(self.rotations.quaternions[e]).transpose()
            unstrained = 0.5 * (Rt + Rt.transpose())
        eps = 0.5 * (F + F.transpose()) - unstrained
        return linear_stress(eps, self.model.mu(e), self.model.lam(e))

    @ti.func
    def elastic_energy(self, x: ti.template(), e):
        """Psi_e(x) = W psi(F R^T) of tet e at positions x, in float64 (J), R as extracted."""
        F = ti.cast(self.model.edges(x, e), ti.f64) @ ti.cast(self.rotations.rotated_Bm[e], ti.f64)
        return ti.cast(self.model.rest_volume[e], ti.f64) * energy_density(
            F, ti.cast(self.model.mu(e), ti.f64), ti.cast(self.model.lam(e), ti.f64), 1.0)

    @ti.func
    def tet_stiffness(self, e, u: ti.template(), w: ti.template(), beta):
        """corner <- one tet's share of K(R) d for the direction d = u + beta w (N/m times m/s).
        Taking d = z + beta p here fuses the CG direction update into this pass."""
        t = self.model.tets[e]
        d0, d1 = u[t[0]] + beta * w[t[0]], u[t[1]] + beta * w[t[1]]
        d2, d3 = u[t[2]] + beta * w[t[2]], u[t[3]] + beta * w[t[3]]
        B = self.rotations.rotated_Bm[e]
        dF = edge_matrix(d0, d1, d2, d3) @ B
        eps = 0.5 * (dF + dF.transpose())
        P = linear_stress(eps, self.model.mu(e), self.model.lam(e)) + self.rotations.twist[e] * (dF - eps)
        self.store_corners(e, corner_forces(-P, B, self.model.rest_volume[e]))

    @ti.kernel
    def stiffness_product(self, u: ti.template()):
        """corner <- (K(R) u)_e per tet."""
        self.stiffness_pass(u)

    @ti.func
    def stiffness_pass(self, u: ti.template()):
        """`stiffness_product`, inside another kernel."""
        ti.loop_config(serialize=self.serial_tets)
        for e in range(self.model.tet_count[None]):
            if self.sleep.tet_awake(e):
                self.tet_stiffness(e, u, u, 0.0)

    @ti.kernel
    def elastic_forces(self, x: ti.template(), out: ti.template()):
        """out <- f(x), the elastic force on every vertex (N), with the current rotations."""
        ti.loop_config(serialize=self.serial_tets)
        for e in range(self.model.tet_count[None]):
            self.store_corners(e, corner_forces(self.elastic_stress(x, e), self.rotations.rotated_Bm[e],
                                                self.model.rest_volume[e]))
        ti.loop_config(serialize=self.serial_vertices)
        for i in range(self.model.vertex_count[None]):
            out[i] = self.gather(i)
