"""Sleeping bodies: which bodies a step moves.

A body asleep is left exactly as it is: every pass of the step skips its tets and filters
its vertices like pinned ones, so it costs nothing and cannot drift. `Simulation` decides
when a body falls asleep (fem/simulation.py) and wakes it; this part holds the flag on the
device and the two kernels that read or hold a body's motion.

Fields (bodies of the capacity):
    awake (bodies,)     0: the body sleeps, the step leaves it be; 1: it moves
    largest (bodies,)   the largest |v|^2 of each body's vertices, (m/s)^2
"""

import numpy as np
import taichi as ti

from fem.reduce import SegmentSums


@ti.data_oriented
class Sleep:
    def __init__(self, model, serial_vertices):
        self.model = model
        self.serial_vertices = serial_vertices
        self.awake = ti.field(ti.i32, model.capacity.bodies)
        self.largest = ti.field(ti.f64, model.capacity.bodies)       # (m/s)^2, of body_speeds
        # a max per body in two stages: no thread waits on its body's one entry
        self.fastest = SegmentSums(model.capacity.vertices, model.capacity.bodies, 1, ti.f64, "max",
                                   serial=serial_vertices)
        self.starts = None

    @ti.func
    def tet_awake(self, e):
        return self.awake[self.model.tet_body[e]]

    def body_speeds(self, v, speed):
        """speed[b] <- the largest |v_i|^2 over body b's vertices, (m/s)^2 (speed: (bodies,) float64)."""
        starts = [b.vertices.start for b in self.model.bodies] + [self.model.n_vertices]
        if starts != self.starts:                 # a new scene: its bodies' vertex ranges
            self.fastest.load(np.array(starts))
            self.starts = starts
        self.largest_speeds(v, speed)

    @ti.kernel
    def largest_speeds(self, v: ti.template(), speed: ti.types.ndarray()):
        self.fastest.reduce(self.speed_squared, self.store_speed, v)
        ti.loop_config(serialize=True)
        for b in range(speed.shape[0]):
            speed[b] = self.largest[b]

    @ti.func
    def speed_squared(self, i, b, v: ti.template()):
        return ti.Vector([ti.cast(v[i].norm_sqr(), ti.f64)])

    @ti.func
    def store_speed(self, b, largest):
        self.largest[b] = largest[0]

    @ti.kernel
    def hold(self, v: ti.template(), start: ti.i32, stop: ti.i32):
        """v <- 0 on vertices start..stop-1: a body put to sleep rests exactly."""
        for i in range(start, stop):
            v[i] = ti.Vector.zero(float, 3)
