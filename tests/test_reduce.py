"""fem/reduce.py: sums and maxima per segment in stages equal numpy's, on one segment, on many of
uneven sizes (empty ones among them) and on 1000, with contiguous and interleaved chunks, on one
thread and on many, in two stages (a CPU's) and in more (a GPU's)."""

import numpy as np
import pytest
import taichi as ti

import fem
from fem.reduce import CHUNK, SegmentSums, chunk_layout


@ti.data_oriented
class Summed:
    """values (n, 2) summed (or maximised) per segment into out (segments, 2), in float64;
    room: fields and sums for that many more items and segments than are in use."""

    def __init__(self, values, starts, room=0, **options):
        self.values = ti.Vector.field(2, ti.f64, len(values) + room)
        self.values.from_numpy(np.pad(values, ((0, room), (0, 0))))
        self.out = ti.Vector.field(2, ti.f64, len(starts) - 1 + room)
        self.out.fill(UNTOUCHED)
        self.sums = SegmentSums(len(values) + room, len(starts) - 1 + room, 2, ti.f64, **options)
        self.sums.load(starts)

    @ti.func
    def value(self, j, s, values: ti.template()):
        return values[j]

    @ti.func
    def store(self, s, total, values: ti.template()):
        self.out[s] = total

    @ti.kernel
    def run(self):
        self.sums.reduce(self.value, self.store, self.values)



UNTOUCHED = 7.0


def segments(sizes):
    return np.concatenate([[0], np.cumsum(sizes)]).astype(np.int32)


def uneven(count, seed=1):
    """`count` segment sizes from 0 to a few chunks, a few of them long."""
    rng = np.random.default_rng(seed)
    sizes = rng.integers(0, 3 * CHUNK, count)
    sizes[rng.integers(0, count, max(1, count // 10))] = rng.integers(5 * CHUNK, 40 * CHUNK)
    sizes[0] = 0
    return sizes


CASES = {"one body": np.array([50_000]), "uneven bodies": uneven(37), "1000 bodies": uneven(1000)}


@pytest.mark.parametrize("chunk, fan_in", [(CHUNK, 0), (16, 0), (CHUNK, 4), (16, 32)])
@pytest.mark.parametrize("serial", [False, True])
@pytest.mark.parametrize("interleave", [False, True])
@pytest.mark.parametrize("case", CASES)
def test_sums_and_maxima_per_segment_equal_numpy(f32, case, interleave, serial, chunk, fan_in):
    starts = segments(CASES[case])
    values = np.random.default_rng(2).standard_normal((starts[-1], 2))
    expected_sum = np.array([values[a:b].sum(0) if b > a else [0, 0] for a, b in zip(starts, starts[1:])])
    expected_max = np.array([values[a:b].max(0) if b > a else [0, 0]      # the largest, negative or not
                             for a, b in zip(starts, starts[1:])])
    for combine, expected in (("sum", expected_sum), ("max", expected_max)):
        summed = Summed(values, starts, combine=combine, interleave=interleave, serial=serial, chunk=chunk,
                        fan_in=fan_in)
        assert (len(summed.sums.stages) > 1) == (fan_in > 0 and not serial)      # the stages between ran
        summed.run()
        magnitude = np.array([np.abs(values[a:b]).sum(0) for a, b in zip(starts, starts[1:])])
        assert np.all(np.abs(summed.out.to_numpy() - expected) <= 1e-14 * magnitude)


@pytest.mark.parametrize("fan_in", [0, 4])
def test_loops_over_the_capacity_skip_what_is_not_in_use(f32, fan_in):
    """fem/runtime.GPU_CAPACITY_LOOPS: each stage loops over its fields' capacity (a constant, so
    that a GPU's grid fits the mesh) and skips the chunks and segments not in use. On a model
    smaller than its capacity the sums are those of loops over what is in use, bit for bit, and
    the segments past it are not written."""
    starts = segments(CASES["uneven bodies"])
    values = np.random.default_rng(3).standard_normal((starts[-1], 2))
    outs = []
    for capacity_loops in (False, True):
        summed = Summed(values, starts, room=500, interleave=True, chunk=16, fan_in=fan_in,
                        capacity_loops=capacity_loops)
        summed.run()
        outs.append(summed.out.to_numpy())
    used = len(starts) - 1
    expected = np.array([values[a:b].sum(0) if b > a else [0, 0] for a, b in zip(starts, starts[1:])])
    np.testing.assert_allclose(outs[1][:used], expected, rtol=1e-12, atol=1e-12)
    assert np.array_equal(outs[1], outs[0])
    assert np.all(outs[1][used:] == UNTOUCHED)


def test_a_long_segment_takes_a_stage_per_fan_in_until_a_thread_can_add_the_rest(f32):
    # a GPU's default: a 973k-tet one-body sum in chunks of 128 tets: 7,605 partials, then 238, then 8
    sums = SegmentSums(973_360, 1, 1, ti.f64, chunk=128, fan_in=32, serial=False)
    sums.load(np.array([0, 973_360]))
    assert [stage.chunks[None] for stage in sums.stages] == [7605, 238, 8]


def test_chunks_cover_each_segment_once_and_hold_at_most_chunk_items():
    starts = segments([0, 1, CHUNK, CHUNK + 1, 10 * CHUNK - 3])
    chunk_segment, first_chunk = chunk_layout(starts, CHUNK, single=False)
    assert first_chunk.tolist() == [0, 1, 2, 3, 5, 15]
    assert chunk_segment.tolist() == [0, 1, 2, 3, 3] + [4] * 10
    _, one_each = chunk_layout(starts, CHUNK, single=True)
    assert one_each.tolist() == [0, 1, 2, 3, 4, 5]


def test_a_gpus_layout_run_on_the_cpu_steps_as_the_cpus_does(f32, monkeypatch, request):
    """Every sum of the step laid out as on a GPU (interleaved chunks of GPU_CHUNK, stages of
    FAN_IN between, the coarse product's rows in pieces), run on the CPU: the same motion as the
    CPU's own layout, to f32 round-off, on a box large enough for the two-level preconditioner;
    also with the PCG iteration's loops over the fields' capacity (fem/runtime.GPU_CAPACITY_LOOPS)."""
    import dataclasses

    import fem.pool
    from tools.gpu_measure import box_simulation

    def run():
        fem.pool.clear()
        sim = box_simulation(10)
        sim.settings = dataclasses.replace(sim.settings, step="newton", integrator="auto")
        for _ in range(5):
            sim.step()
        return sim, sim.positions(), sim.stats()["total_energy"]

    request.addfinalizer(fem.pool.clear)           # no later test borrows a solver laid out as on a GPU
    cpu, x_cpu, energy_cpu = run()
    assert cpu.solver.preconditioner == "two-level" and len(cpu.solver.sleep.tet_sums.stages) == 1
    monkeypatch.setattr(fem.runtime, "on_cpu", lambda: False)
    monkeypatch.setattr(fem.runtime, "PARALLEL_MIN", {"tets": 0, "vertices": 0})
    monkeypatch.setattr(fem.reduce, "FAN_IN", 4)
    gpu, x_gpu, energy_gpu = run()
    assert len(gpu.solver.sleep.tet_sums.stages) > 2 and gpu.solver.patches.parts > 1   # laid out as on a GPU
    moved = np.abs(x_cpu - cpu.model.rest_positions_np).max()
    assert moved > 0.01
    assert np.abs(x_gpu - x_cpu).max() <= 1e-4 * moved
    assert energy_gpu == pytest.approx(energy_cpu, rel=1e-5)
    monkeypatch.setattr(fem.runtime, "GPU_CAPACITY_LOOPS", 1)     # and the PCG loops over the capacity
    fitted, x_fitted, energy_fitted = run()
    model = fitted.model
    assert fitted.solver.linear.capacity_loops and fitted.solver.patches.sums.capacity_loops
    assert model.capacity.vertices > model.n_vertices and model.capacity.tets > model.n_tets   # loops skip some
    assert np.abs(x_fitted - x_cpu).max() <= 1e-4 * moved
    assert energy_fitted == pytest.approx(energy_cpu, rel=1e-5)
