"""Sums without contention: a sum per segment in two stages.

A segment is a contiguous range of items: a body's vertices or tets, a coarse patch's
members. Adding every item into its segment's one entry (`out[body[i]] += value`) makes every
thread of a body wait on one address, and one thread per segment leaves most of a GPU idle
when segments are few and long (a body, 128 patches of a million-tet mesh). So:

    stage 1: each chunk of at most CHUNK items of one segment adds them up, in order,
             into its own partial[c];
    stage 2: each segment adds its chunks' partials, in order, into its result.

A long segment has many chunks (a one-body mesh of 973k tets: 7,600), too many for stage 2's
one thread a segment on a GPU. There the partials are added in more stages first, FAN_IN at a
time in chunks like stage 1's, until each segment has FAN_IN or fewer (7,600 -> 238 -> 8).
A CPU runs as many threads as it has cores, and adds a few thousand numbers in microseconds:
it keeps two stages.

No two threads write one place, and the order of the adds is fixed by the layout, so a sum
is the same on every run. On the CPU a chunk is a contiguous run of items; on a GPU the
chunks of a segment interleave (chunk k of C takes items k, k + C, k + 2C, ...), so that
neighbouring threads read neighbouring items (coalesced loads). Where loops run on one
thread (small meshes on the CPU, fem/runtime.serial_loops) a segment is one chunk: the adds
of a plain loop, in its order.

A sum into one number (PCG's dot products r.z, p.Ap, a weighted |r|^2: `s += ...` on a kernel's
local in a parallel loop) needs none of this: Taichi's thread-local pass already gives every
thread its own partial and adds the partials once per thread at the loop's end (seen in its
IR: "tls prologue" / "tls epilogue"). On a GPU that is once per thread of the loop's grid,
however short the loop, so fem/runtime.GPU_GRID_BLOCKS keeps the grid small. What it cannot
do is a sum whose target moves with the item, `out[body[i]] += ...`: that is what this module
is for.

Use: make a `SegmentSums` beside the fields it sums, `load` the segments' starts (a new
scene), and call `reduce(value, store, data)` inside a kernel, with two ti.funcs of the
caller: `value(j, s, data)`, item j's contribution to segment s (a ti.Vector of `width`;
data: whatever the caller passed, e.g. the field being summed), and `store(s, total, data)`,
what to do with segment s's total.
"""

import numpy as np
import taichi as ti

from fem import runtime

# Items per chunk on a CPU: a patch of the 973k box (1,330 vertices) in 11 chunks, a one-body sum
# of its 170k vertices in 1,330 partials.
CHUNK = 128
# On a GPU, smaller chunks: 128 left 1,400 threads for a one-body sum of the 973k box, each adding
# 128 heavy items (a vertex's gradient, gathered from its corners) in turn. Measured on an H100
# (docs/gpu.md, tools/gpu_tune.py): the 973k box's one-solve step 17.4 ms at 128, 14.7 at 32, 17.3 at 8.
GPU_CHUNK = 32
FAN_IN = 32            # partials per chunk in the stages between the first and the last, on a GPU
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
    """Sums (or maxima) in stages of up to `segments` segments over up to `items` items.

    Fields:
        start (segments + 1,)          the segments' item ranges
        stages[k].first_chunk (segments + 1,)    each segment's chunks of stage k + 1
        stages[k].chunk_segment (chunks,)        the segment of each chunk
        stages[k].partial (chunks, width)        the chunks' sums, in `dtype`
    chunk: items per chunk (CHUNK on a CPU, GPU_CHUNK on a GPU). combine: "sum", or "max" (the
    largest value; 0 for an empty segment). serial: the loops run on one thread, a chunk per
    segment. interleave: chunks interleave (default: on a GPU). fan_in: partials per chunk of the
    stages between the first and the last (default: FAN_IN on a GPU; 0, none, on a CPU).
    capacity_loops: loops over the fields' capacity, a constant, skipping what is not in use
    (default: fem/runtime.capacity_loops()).
    """

    def __init__(self, items, segments, width, dtype=float, combine="sum", serial=False, interleave=None,
                 chunk=None, fan_in=None, capacity_loops=None):
        self.chunk = chunk or (CHUNK if runtime.on_cpu() else GPU_CHUNK)
        self.fan_in = (0 if serial or runtime.on_cpu() else FAN_IN) if fan_in is None else fan_in
        self.width, self.dtype, self.combine = width, dtype, combine
        self.serial = serial
        self.interleave = not runtime.on_cpu() if interleave is None else interleave
        self.capacity_loops = runtime.capacity_loops() if capacity_loops is None else capacity_loops
        self.start = ti.field(ti.i32, segments + 1)
        self.segments = ti.field(ti.i32, ())
        self.stages = []
        units, longest, per = items, items, self.chunk       # all units, one segment's most, units per chunk
        while True:
            capacity = -(-units // per) + segments
            self.stages.append(Stage(capacity, segments, width, dtype))
            units, longest, per = capacity, -(-longest // per), self.fan_in
            if serial or not self.fan_in or longest <= self.fan_in:
                break
        # what `load` writes: the segments' starts, then each stage's first chunks and chunks' segments
        self.layout_fields = [self.start] + [field for stage in self.stages
                                             for field in (stage.first_chunk, stage.chunk_segment)]

    def load(self, starts):
        """The segments [starts[s], starts[s+1]) (numpy, segments + 1 offsets)."""
        layout, units, per = [np.asarray(starts)], starts, self.chunk
        for stage in self.stages:
            chunk_segment, first_chunk = chunk_layout(units, per, self.serial)
            layout += [first_chunk, chunk_segment]
            units, per = first_chunk, self.fan_in
        lengths = np.array([len(rows) for rows in layout], np.int32)
        assert all(n <= field.shape[0] for n, field in zip(lengths, self.layout_fields))
        self._load(np.concatenate(layout).astype(np.int32), lengths)

    @ti.kernel
    def _load(self, packed: ti.types.ndarray(), lengths: ti.types.ndarray()):
        """Every layout field in one launch (one kernel to compile, not one per field): field k
        <- packed's next lengths[k] numbers, its rows beyond them 0; each stage's chunk count."""
        self.segments[None] = lengths[0] - 1
        begin = 0
        for k in ti.static(range(len(self.layout_fields))):
            field = ti.static(self.layout_fields[k])
            n = lengths[k]
            for i in range(field.shape[0]):
                field[i] = 0
                if i < n:
                    field[i] = packed[begin + i]
            begin += n
        for k in ti.static(range(len(self.stages))):
            self.stages[k].chunks[None] = lengths[2 + 2 * k]

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
    def units(self, c, stage: ti.template(), unit_start: ti.template()):
        """Chunk c of `stage`: its segment s and units (items, or the stage before's partials):
        n of them, from `first` on, `stride` apart; unit_start: the segments' unit ranges."""
        s = stage.chunk_segment[c]
        k, count = c - stage.first_chunk[s], stage.first_chunk[s + 1] - stage.first_chunk[s]
        begin, length = unit_start[s], unit_start[s + 1] - unit_start[s]
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
        first = self.stages[0]
        chunks = first.chunks[None] * on
        ti.loop_config(serialize=self.serial)
        for c in range(first.capacity if ti.static(self.capacity_loops) else chunks):
            if c >= chunks:
                continue
            s, begin, n, stride = self.units(c, first, self.start)
            total = self._nothing()
            for t in range(n):
                total = self._join(total, value(begin + t * stride, s, data))
            first.partial[c] = total
        for k in ti.static(range(1, len(self.stages))):      # a GPU's stages between: FAN_IN partials a chunk
            stage, before = self.stages[k], self.stages[k - 1]
            chunks_k = stage.chunks[None] * on
            for c in range(stage.capacity if ti.static(self.capacity_loops) else chunks_k):
                if c >= chunks_k:
                    continue
                s, begin, n, stride = self.units(c, stage, before.first_chunk)
                total = self._nothing()
                for t in range(n):
                    total = self._join(total, before.partial[begin + t * stride])
                stage.partial[c] = total
        last = self.stages[ti.static(len(self.stages) - 1)]
        segments = self.segments[None] * on
        ti.loop_config(serialize=self.serial)
        for s in range(self.start.shape[0] - 1 if ti.static(self.capacity_loops) else segments):
            if s >= segments:
                continue
            total = last.partial[last.first_chunk[s]]       # not 0 + partial: a serial sum stays bit for bit
            for c in range(last.first_chunk[s] + 1, last.first_chunk[s + 1]):
                total = self._join(total, last.partial[c])
            if self.start[s + 1] == self.start[s]:
                total = ti.Vector.zero(self.dtype, self.width)
            store(s, total, data)


@ti.data_oriented
class Stage:
    """One stage's chunks: which segment each belongs to, each segment's first, and their partials."""

    def __init__(self, capacity, segments, width, dtype):
        self.capacity = capacity
        self.chunk_segment = ti.field(ti.i32, capacity)
        self.first_chunk = ti.field(ti.i32, segments + 1)
        self.partial = ti.Vector.field(width, dtype, capacity)
        self.chunks = ti.field(ti.i32, ())
