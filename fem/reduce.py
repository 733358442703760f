"""Sums without contention: a sum per segment in two stages.

A segment is a contiguous range of items: a body's vertices or tets, a coarse patch's
members. Adding every item into its segment's one entry (`out[body[i]] += value`) makes every
thread of a body wait on one address, and one thread per segment leaves most of a GPU idle
when segments are few and long (a body, 128 patches of a million-tet mesh). So:

    stage 1: each chunk of at most CHUNK items of one segment adds them up, in order,
             into its own partial[c];
    stage 2: each segment adds its chunks' partials, in order, into its result.

No two threads write one place, and the order of the adds is fixed by the layout, so a sum
is the same on every run. On the CPU a chunk is a contiguous run of items; on a GPU the
chunks of a segment interleave (chunk k of C takes items k, k + C, k + 2C, ...), so that
neighbouring threads read neighbouring items (coalesced loads). Where loops run on one
thread (small meshes on the CPU, fem/runtime.serial_loops) a segment is one chunk: the adds
of a plain loop, in its order.

A sum into one number (PCG's dot products r.z, p.Ap, a weighted |r|^2: `s += ...` on a kernel's
local in a parallel loop) needs none of this: Taichi's thread-local pass already gives every
thread its own partial and adds the partials once per thread at the loop's end (seen in its
IR: "tls prologue" / "tls epilogue"). What it cannot do is a sum whose target moves with the
item, `out[body[i]] += ...`: that is what this module is for.

Use: make a `SegmentSums` beside the fields it sums, `load` the segments' starts (a new
scene), and call `reduce(value, store, data)` inside a kernel, with two ti.funcs of the
caller: `value(j, s, data)`, item j's contribution to segment s (a ti.Vector of `width`;
data: whatever the caller passed, e.g. the field being summed), and `store(s, total, data)`,
what to do with segment s's total.
"""

import numpy as np
import taichi as ti

from fem import runtime

# Items per chunk: a patch of the 973k box (1,330 vertices) in 11 chunks, a one-body sum of its
# 170k vertices in 1,330 partials for stage 2. Not measured on a GPU yet: tune it there.
CHUNK = 128
LOWEST = -3.4e38       # where a max starts: about float32's lowest number


def chunk_layout(starts, chunk, single):
    """(chunk_segment (chunks,), first_chunk (segments + 1,)) for segments [starts[s], starts[s+1]):
    each segment in max(1, ceil(length / chunk)) chunks, one when `single`."""
    lengths = np.diff(np.asarray(starts, np.int64))
    counts = np.ones_like(lengths) if single else np.maximum(1, -(-lengths // chunk))
    first_chunk = np.concatenate([[0], np.cumsum(counts)])
    return np.repeat(np.arange(len(lengths)), counts), first_chunk


@ti.data_oriented
class SegmentSums:
    """Two-stage sums of up to `segments` segments over up to `items` items.

    Fields:
        start (segments + 1,)          the segments' item ranges
        first_chunk (segments + 1,)    each segment's chunks: first_chunk[s] .. first_chunk[s+1]-1
        chunk_segment (chunks,)        the segment of each chunk
        partial (chunks, width)        stage 1's sums, in `dtype`
    chunk: items per chunk (CHUNK). combine: "sum", or "max" (the largest value; 0 for an empty segment). serial: the loops run
    on one thread, a chunk per segment. interleave: chunks interleave (default: on a GPU).
    """

    def __init__(self, items, segments, width, dtype=float, combine="sum", serial=False, interleave=None,
                 chunk=None):
        self.chunk = chunk or CHUNK
        capacity = -(-items // self.chunk) + segments
        self.width, self.dtype, self.combine = width, dtype, combine
        self.serial = serial
        self.interleave = not runtime.on_cpu() if interleave is None else interleave
        self.start = ti.field(ti.i32, segments + 1)
        self.first_chunk = ti.field(ti.i32, segments + 1)
        self.chunk_segment = ti.field(ti.i32, capacity)
        self.partial = ti.Vector.field(width, dtype, capacity)
        self.segments = ti.field(ti.i32, ())
        self.chunks = ti.field(ti.i32, ())

    def load(self, starts):
        """The segments [starts[s], starts[s+1]) (numpy, segments + 1 offsets)."""
        chunk_segment, first_chunk = chunk_layout(starts, self.chunk, self.serial)
        self.segments[None], self.chunks[None] = len(starts) - 1, len(chunk_segment)
        for field, values in ((self.start, starts), (self.first_chunk, first_chunk),
                              (self.chunk_segment, chunk_segment)):
            padded = np.zeros(field.shape[0], np.int32)
            padded[:len(values)] = values
            field.from_numpy(padded)

    @ti.func
    def _nothing(self):
        """What a sum (0) or a max (the lowest number) starts from."""
        start = ti.Vector.zero(self.dtype, self.width)
        if ti.static(self.combine == "max"):
            start = ti.Vector([LOWEST] * self.width, self.dtype)
        return start

    @ti.func
    def _join(self, a, b):
        result = a + b
        if ti.static(self.combine == "max"):
            result = ti.max(a, b)
        return result

    @ti.func
    def items(self, c):
        """Chunk c's segment s and items: n of them, from `first` on, `stride` apart."""
        s = self.chunk_segment[c]
        k, count = c - self.first_chunk[s], self.first_chunk[s + 1] - self.first_chunk[s]
        begin, length = self.start[s], self.start[s + 1] - self.start[s]
        first, n, stride = 0, 0, 1
        if ti.static(self.interleave):
            first, n, stride = begin + k, (length - k + count - 1) // count, count
        else:
            size = (length + count - 1) // count
            first, n = begin + k * size, ti.max(0, ti.min(size, length - k * size))
        return s, first, n, stride

    @ti.func
    def reduce(self, value: ti.template(), store: ti.template(), data: ti.template(), on=1):
        """For every segment s: store(s, the sum (or max) of value(j, s, data) over its items j, data).
        on = 0: nothing (a PCG iteration that has converged)."""
        ti.loop_config(serialize=self.serial)
        for c in range(self.chunks[None] * on):
            s, first, n, stride = self.items(c)
            total = self._nothing()
            for t in range(n):
                total = self._join(total, value(first + t * stride, s, data))
            self.partial[c] = total
        ti.loop_config(serialize=self.serial)
        for s in range(self.segments[None] * on):
            total = self.partial[self.first_chunk[s]]       # not 0 + partial: a serial sum stays bit for bit
            for c in range(self.first_chunk[s] + 1, self.first_chunk[s + 1]):
                total = self._join(total, self.partial[c])
            if self.start[s + 1] == self.start[s]:
                total = ti.Vector.zero(self.dtype, self.width)
            store(s, total, data)
