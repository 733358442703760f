"""Sleeping bodies: which bodies a step moves.

A body asleep is left exactly as it is: every pass of the step skips its tets and filters
its vertices like pinned ones, so it costs nothing and cannot drift. `Simulation` decides
when a body falls asleep (fem/simulation.py) and wakes it; this part holds the flag on the
device and the two kernels that read or hold a body's motion. It also holds the bodies' vertex
and tet ranges, as the segments of `sums` and `tet_sums`: the step's parts sum over each body's
vertices or tets with them (`reduce`, fem/reduce.py), one sum at a time.

Fields (bodies of the capacity):
    awake (bodies,)     0: the body sleeps, the step leaves it be; 1: it moves
    largest (bodies,)   the largest |v|^2 of each body's vertices, (m/s)^2
"""

import numpy as np
import taichi as ti

from fem import runtime
from fem.reduce import SegmentSums

TET_CHUNK = 16  # tets per chunk of the per-body tet sums on a CPU
SUMS = 10      # the widest per-body sum: a body's spin (3), inertia (6) and kinetic energy (1)


@ti.data_oriented
class Sleep:
    def __init__(self, model, serial_vertices, serial_tets):
        self.model = model
        self.serial_vertices = serial_vertices
        self.awake = ti.field(ti.i32, model.capacity.bodies)
        self.largest = ti.field(ti.f64, model.capacity.bodies)       # (m/s)^2, of body_speeds
        # a max per body of up to two numbers in two stages: no thread waits on its body's one
        # entry (its fastest vertex here; its contact with the ground in fem/implicit/safeguards.py)
        self.fastest = SegmentSums(model.capacity.vertices, model.capacity.bodies, 2, ti.f64, "max",
                                   serial=serial_vertices)
        # per-body sums over vertices (a sum of up to SUMS numbers at a time), for every part of
        # the step: no thread waits on its body's one entry, as every vertex of a one-body mesh did
        self.sums = SegmentSums(model.capacity.vertices, model.capacity.bodies, SUMS, ti.f64,
                                serial=serial_vertices)
        # a tet's terms are heavy (its rotation, energy and gradient): chunks of TET_CHUNK keep both
        # CPU threads busy to the end (128 made box50k's energy passes 1.5 times as long)
        self.tet_sums = SegmentSums(model.capacity.tets, model.capacity.bodies, 1, ti.f64, serial=serial_tets,
                                    chunk=TET_CHUNK if runtime.on_cpu() else None)
        # two numbers a tet: E_b with the damping in the line search's frame and in the iterate's own
        # (IncrementalPotential.holds_frame)
        self.tet_pairs = SegmentSums(model.capacity.tets, model.capacity.bodies, 2, ti.f64, serial=serial_tets,
                                     chunk=TET_CHUNK if runtime.on_cpu() else None)

    def load(self):
        """A new scene: its bodies' vertex and tet ranges."""
        starts = np.array([b.vertices.start for b in self.model.bodies] + [self.model.n_vertices])
        self.fastest.load(starts)
        self.sums.load(starts)
        tets = np.array([b.tets.start for b in self.model.bodies] + [self.model.n_tets])
        self.tet_sums.load(tets)
        self.tet_pairs.load(tets)

    @ti.func
    def tet_awake(self, e):
        return self.awake[self.model.tet_body[e]]

    def body_speeds(self, v, speed):
        """speed[b] <- the largest |v_i|^2 over body b's vertices, (m/s)^2 (speed: (bodies,) float64)."""
        self.largest_speeds(v, speed)

    @ti.kernel
    def largest_speeds(self, v: ti.template(), speed: ti.types.ndarray()):
        self.fastest.reduce(self.speed_squared, self.store_speed, v)
        ti.loop_config(serialize=True)
        for b in range(speed.shape[0]):
            speed[b] = self.largest[b]

    @ti.func
    def speed_squared(self, i, b, v: ti.template()):
        return ti.Vector([ti.cast(v[i].norm_sqr(), ti.f64), 0.0])

    @ti.func
    def store_speed(self, b, largest, v: ti.template()):
        self.largest[b] = largest[0]

    @ti.kernel
    def hold(self, v: ti.template(), start: ti.i32, stop: ti.i32):
        """v <- 0 on vertices start..stop-1: a body put to sleep rests exactly."""
        for i in range(start, stop):
            v[i] = ti.Vector.zero(float, 3)
