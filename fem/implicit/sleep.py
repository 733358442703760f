"""Sleeping bodies: which bodies a step moves.

A body asleep is left exactly as it is: every pass of the step skips its tets and filters
its vertices like pinned ones, so it costs nothing and cannot drift. `Simulation` decides
when a body falls asleep (fem/simulation.py) and wakes it; this part holds the flag on the
device and the two kernels that read or hold a body's motion.

Fields (bodies of the capacity):
    awake (bodies,)   0: the body sleeps, the step leaves it be; 1: it moves
"""

import taichi as ti


@ti.data_oriented
class Sleep:
    def __init__(self, model, serial_vertices):
        self.model = model
        self.serial_vertices = serial_vertices
        self.awake = ti.field(ti.i32, model.capacity.bodies)

    @ti.func
    def tet_awake(self, e):
        return self.awake[self.model.tet_body[e]]

    @ti.kernel
    def body_speeds(self, v: ti.template(), speed: ti.types.ndarray()):
        """speed[b] <- the largest |v_i|^2 over body b's vertices, (m/s)^2 (speed: (bodies,) float64)."""
        ti.loop_config(serialize=True)
        for b in range(speed.shape[0]):
            speed[b] = 0.0
        ti.loop_config(serialize=self.serial_vertices)
        for i in range(self.model.vertex_count[None]):
            ti.atomic_max(speed[self.model.vertex_body[i]], ti.cast(v[i].norm_sqr(), ti.f64))

    @ti.kernel
    def hold(self, v: ti.template(), start: ti.i32, stop: ti.i32):
        """v <- 0 on vertices start..stop-1: a body put to sleep rests exactly."""
        for i in range(start, stop):
            v[i] = ti.Vector.zero(float, 3)
