"""What a step did, in numbers: energies, volumes, inverted tets, per-tet colour data.

Measuring costs a pass over the tets, so it runs only when asked for (stats
files, the window's panel, colour modes), never inside the step itself.
"""

import numpy as np
import taichi as ti

from fem.elastic import edge_matrix, energy_density
from fem.rotation import newton_rotation, polar_rotation, quaternion_matrix


@ti.data_oriented
class Measure:
    """Per-body volume, energies and inverted tets of a state; energies summed in float64.

    start: a quaternion field (m,) to start each tet's rotation from (the solver's last
    rotations: near the answer, so Newton steps certify it and the SVD is rarely needed).
    switches: the solver's `Switches` (whether loops run serially, whether there is a ground).
    effects: the solver's effects (fem/implicit/effects.py): the ground's contact energy.
    Like the solver, made once per Model and reused (fem/pool.py); `load` sets the gravity.
    """

    def __init__(self, model, start, switches, effects):
        self.model, self.effects = model, effects
        self.has_ground = switches.ground
        self.start = start              # quaternions (x, y, z, w) per tet: where rotations are sought from
        n_bodies, n_tets = model.capacity.bodies, model.capacity.tets
        self.gravity = ti.Vector.field(3, ti.f64, ())   # m/s^2; the potential is -sum m g.x, zero at the origin
        self.volume = ti.field(ti.f64, n_bodies)        # m^3
        self.elastic = ti.field(ti.f64, n_bodies)       # J
        self.kinetic = ti.field(ti.f64, n_bodies)       # J
        self.potential = ti.field(ti.f64, n_bodies)     # J, gravitational
        self.contact = ti.field(ti.f64, n_bodies)       # J, stored in the ground's penalty
        self.inverted = ti.field(ti.i32, n_bodies)
        self.tet_volume_ratio = ti.field(float, n_tets)
        self.tet_energy_density = ti.field(float, n_tets)   # J/m^3
        self.needs_svd = ti.field(ti.i8, n_tets)              # 1: R from the SVD
        self.serial_tets, self.serial_vertices = switches.serial_tets, switches.serial_vertices

    def load(self, gravity):
        """gravity: (gx, gy, gz) m/s^2 or None."""
        self.gravity[None] = gravity or (0.0, 0.0, 0.0)

    @ti.kernel
    def measure_tets(self, x: ti.template(), v: ti.template()) -> ti.i32:
        """Volumes, inverted tets, kinetic and potential energy, and the elastic energy of
        every tet whose rotation Newton steps certify from the solver's last rotation;
        returns how many tets are left for `measure_svd_tets`."""
        for b in range(self.model.body_count[None]):
            self.volume[b], self.elastic[b], self.kinetic[b], self.potential[b] = 0.0, 0.0, 0.0, 0.0
            self.contact[b] = 0.0
            self.inverted[b] = 0
        left = 0
        ti.loop_config(serialize=self.serial_tets)
        for e in range(self.model.tet_count[None]):
            F = self.deformation(x, e)
            J = F.determinant()
            b = self.model.tet_body[e]
            self.volume[b] += ti.cast(J, ti.f64) * ti.cast(self.model.rest_volume[e], ti.f64)
            if J <= 0:
                self.inverted[b] += 1
            self.tet_volume_ratio[e] = J
            self.needs_svd[e] = 0
            R = ti.Matrix.identity(float, 3)
            if self.model.method(e):
                q, converged = newton_rotation(F, self.start[e])
                R = quaternion_matrix(q)
                if not converged:
                    self.needs_svd[e] = 1
                    left += 1
            if not self.needs_svd[e]:
                self.add_energy(e, F, R)
        g = self.gravity[None]
        if ti.static(self.effects.has_contact):
            self.effects.contact.share_energy(x)
        ti.loop_config(serialize=self.serial_vertices)
        for i in range(self.model.vertex_count[None]):
            m = ti.cast(self.model.mass[i], ti.f64)
            b = self.model.vertex_body[i]
            self.kinetic[b] += 0.5 * m * ti.cast(v[i], ti.f64).norm_sqr()
            self.potential[b] -= m * g.dot(ti.cast(x[i], ti.f64))
            if ti.static(self.has_ground):
                self.contact[b] += self.effects.contact_energy(i, x[i])
            if ti.static(self.effects.has_contact):
                self.contact[b] += self.effects.contact.energy[i]     # its share of the pairs' penalty
        return left

    @ti.kernel
    def measure_svd_tets(self, x: ti.template()):
        """The elastic energy of the tets left by measure_tets, R from the SVD (`polar_rotation`)."""
        ti.loop_config(serialize=self.serial_tets)
        for e in range(self.model.tet_count[None]):
            if self.needs_svd[e]:
                F = self.deformation(x, e)
                self.add_energy(e, F, polar_rotation(F))

    @ti.kernel
    def body_table(self, table: ti.types.ndarray()):
        """Per body: kinetic, elastic and potential energy, volume, inverted tets, contact energy
        (one read, not six)."""
        for b in range(table.shape[0]):
            table[b, 0], table[b, 1], table[b, 2] = self.kinetic[b], self.elastic[b], self.potential[b]
            table[b, 3], table[b, 4], table[b, 5] = self.volume[b], self.inverted[b], self.contact[b]

    @ti.func
    def deformation(self, x: ti.template(), e):
        t = self.model.tets[e]
        return edge_matrix(x[t[0]], x[t[1]], x[t[2]], x[t[3]]) @ self.model.Bm[e]

    @ti.func
    def add_energy(self, e, F, R):
        psi = energy_density(ti.cast(R.transpose() @ F, ti.f64), ti.cast(self.model.mu(e), ti.f64),
                             ti.cast(self.model.lam(e), ti.f64), 1.0)
        self.elastic[self.model.tet_body[e]] += psi * ti.cast(self.model.rest_volume[e], ti.f64)
        self.tet_energy_density[e] = ti.cast(psi, float)

    def measure(self, x, v):
        """Fill the per-body and per-tet numbers for positions x and velocities v (fields)."""
        if self.measure_tets(x, v) > 0:
            self.measure_svd_tets(x)

    def read(self, x, v):
        """Per-body numbers as plain Python: volume ratio, energies (J), inverted tets.

        total_energy = kinetic + elastic + gravitational potential + contact (the ground's
        penalty, 0 without a ground): the energy the step never raises.
        """
        self.measure(x, v)
        rest = np.array([b.rest_volume for b in self.model.bodies])
        table = np.zeros((len(rest), 6))
        self.body_table(table)
        kinetic, elastic, potential, volume, inverted, contact = table.T
        potential = potential + contact
        inverted = inverted.astype(int)
        return {
            "kinetic_energy": float(kinetic.sum()),
            "elastic_energy": float(elastic.sum()),
            "gravity_energy": float((potential - contact).sum()),
            "contact_energy": float(contact.sum()),
            "total_energy": float((kinetic + elastic + potential).sum()),
            "volume_ratio": (volume / rest).tolist(),
            "inverted_tets": int(inverted.sum()),
            "body_kinetic_energy": kinetic.tolist(),
            "body_elastic_energy": elastic.tolist(),
            "body_total_energy": (kinetic + elastic + potential).tolist(),
            "body_inverted_tets": inverted.tolist(),
        }
