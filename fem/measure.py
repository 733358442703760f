"""What a step did, in numbers: energies, volumes, inverted tets, per-tet colour data.

Measuring costs a pass over the tets, so it runs only when asked for (stats
files, the window's panel, colour modes), never inside the step itself.
"""

import numpy as np
import taichi as ti

from fem.elastic import edge_matrix, polar_rotation, strain_energy_density
from fem.runtime import serial_loops


@ti.data_oriented
class Measure:
    def __init__(self, model):
        self.model = model
        n_bodies = len(model.bodies)
        self.volume = ti.field(float, n_bodies)        # m^3
        self.elastic = ti.field(float, n_bodies)       # J
        self.kinetic = ti.field(float, n_bodies)       # J
        self.inverted = ti.field(ti.i32, n_bodies)
        self.tet_body = ti.field(ti.i32, model.n_tets)
        self.vertex_body = ti.field(ti.i32, model.n_vertices)
        self.tet_volume_ratio = ti.field(float, model.n_tets)
        self.tet_energy_density = ti.field(float, model.n_tets)   # J/m^3
        self.serial_tets = serial_loops(model.n_tets, "tets")
        self.serial_vertices = serial_loops(model.n_vertices, "vertices")
        self.tet_body.from_numpy(model.tet_body)
        self.vertex_body.from_numpy(model.vertex_body)

    @ti.kernel
    def measure(self, x: ti.template(), v: ti.template()):
        for b in self.volume:
            self.volume[b], self.elastic[b], self.kinetic[b], self.inverted[b] = 0.0, 0.0, 0.0, 0
        ti.loop_config(serialize=self.serial_tets)
        for e in self.tet_body:
            t = self.model.tets[e]
            F = edge_matrix(x[t[0]], x[t[1]], x[t[2]], x[t[3]]) @ self.model.Bm[e]
            R = ti.Matrix.identity(float, 3)
            if self.model.corotational[e]:
                R = polar_rotation(F)
            J = F.determinant()
            psi = strain_energy_density(F, R, self.model.mu[e], self.model.lam[e])
            b = self.tet_body[e]
            self.volume[b] += J * self.model.rest_volume[e]
            self.elastic[b] += psi * self.model.rest_volume[e]
            if J <= 0:
                self.inverted[b] += 1
            self.tet_volume_ratio[e] = J
            self.tet_energy_density[e] = psi
        ti.loop_config(serialize=self.serial_vertices)
        for i in self.vertex_body:
            self.kinetic[self.vertex_body[i]] += 0.5 * self.model.mass[i] * v[i].norm_sqr()

    def read(self, x, v):
        """Per-body numbers as plain Python: volume ratio, kinetic and elastic energy (J), inverted tets."""
        self.measure(x, v)
        rest = np.array([b.rest_volume for b in self.model.bodies])
        kinetic, elastic = self.kinetic.to_numpy(), self.elastic.to_numpy()
        return {
            "kinetic_energy": float(kinetic.sum()),
            "elastic_energy": float(elastic.sum()),
            "volume_ratio": (self.volume.to_numpy() / rest).tolist(),
            "inverted_tets": int(self.inverted.to_numpy().sum()),
            "body_kinetic_energy": kinetic.tolist(),
            "body_elastic_energy": elastic.tolist(),
            "body_inverted_tets": self.inverted.to_numpy().tolist(),
        }
