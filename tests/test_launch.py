"""fem/launch.py launches Taichi's kernels without Taichi's per-call derivation: each call still
reaches the instance its template arguments mean (never one whose object died at the same address),
sets its scalars and returns what Taichi's own launch returns; what it does not cover takes Taichi's path."""

import gc

import numpy as np
import pytest
import taichi as ti

import fem
from fem import launch


@pytest.fixture(scope="module", autouse=True)
def f32():
    fem.init("cpu", "f32")


@ti.data_oriented
class Counter:
    """A field, kernels of every kind of argument and return this covers, and one it does not."""

    def __init__(self, start):
        self.values = ti.Vector.field(3, float, 4)
        self.total = ti.field(ti.f64, ())
        self.values.fill(start)
        self.plain = start                     # a plain attribute and a plain method: `data_oriented`
        self.helper = lambda: start            # a function kept on the object: Taichi's own lookup

    def doubled(self):
        return 2 * self.plain

    @ti.kernel
    def add(self, field: ti.template(), h: float, times: ti.i32, flag: ti.template()) -> ti.f64:
        for i in range(4):
            field[i] += h * times
        out = ti.cast(field[0][0], ti.f64)
        if ti.static(flag):
            out = -out
        return out

    @ti.kernel
    def pair(self, n: ti.u32) -> ti.types.vector(2, ti.f64):
        return ti.Vector([ti.cast(n, ti.f64), self.values[1][2]], ti.f64)

    @ti.kernel
    def count(self) -> ti.i32:
        return 7

    @ti.kernel
    def from_array(self, a: ti.types.ndarray()):
        for i in range(4):
            self.values[i][0] = a[i]


def run(counter):
    """Every kernel's results with whichever launch is installed."""
    return [counter.add(counter.values, 0.5, 3, False), counter.add(counter.values, 0.25, -2, True),
            tuple(counter.pair(9)), counter.count(), counter.from_array(np.arange(4.0)),
            counter.values.to_numpy().tolist()]


def test_same_results_as_taichi():
    launch.uninstall()
    try:
        expected = run(Counter(1.0))
    finally:
        launch.install()
    assert run(Counter(1.0)) == expected
    assert isinstance(Counter(1.0).pair(3), ti.Vector)


def test_an_object_at_a_known_address_proves_who_it_is(monkeypatch):
    """Every call keyed alike, as if each object were born at the address of the one before: the weak
    references still tell them apart, and each sum is its own object's."""
    monkeypatch.setattr(launch, "_key", lambda args, templates: "one address")
    counters = [Counter(float(start)) for start in range(3)]
    for start, counter in enumerate(counters):
        assert counter.add(counter.values, 1.0, 1, False) == start + 1.0
    del counters[0]
    gc.collect()
    assert counters[0].add(counters[0].values, 1.0, 1, False) == 3.0


def test_template_arguments_choose_the_instance():
    counter = Counter(0.0)
    other = ti.Vector.field(3, float, 4)
    other.fill(10.0)
    assert counter.add(counter.values, 1.0, 1, False) == 1.0
    assert counter.add(other, 1.0, 1, False) == 11.0
    assert counter.add(other, 1.0, 1, True) == -12.0
    assert counter.values[0][0] == 1.0


def error_of(call):
    try:
        call()
    except Exception as e:               # noqa: BLE001 (whichever Taichi raises)
        return type(e), str(e)
    return None


def test_wrong_arguments_get_taichi_errors():
    counter = Counter(0.0)
    counter.add(counter.values, 1.0, 1, False)
    wrong = [lambda: counter.add(counter.values, "1.0", 1, False), lambda: counter.add(counter.values, 1.0, 1.5, False),
             lambda: counter.add(counter.values, 1.0)]
    quick = [error_of(call) for call in wrong]
    launch.uninstall()
    try:
        assert quick == [error_of(call) for call in wrong]
    finally:
        launch.install()
    assert all(error is not None for error in quick)


def test_attributes_as_taichi_gives_them():
    counter = Counter(4.0)
    assert counter.plain == 4.0 and counter.doubled() == 8.0 and counter.helper() == 4.0
    assert callable(counter.count) and counter.count() == 7

    class Later(Counter):                      # a subclass Taichi did not decorate: its own method
        def doubled(self):
            return 3 * self.plain

    assert Later(1.0).doubled() == 3.0
    counter.doubled = lambda: "a stand-in"     # an object's own attribute before its class's method
    assert counter.doubled() == "a stand-in"


def test_a_restart_compiles_again():
    counter = Counter(2.0)
    assert counter.count() == 7
    fem.init("cpu", "f32", restart=True)
    counter = Counter(5.0)
    assert counter.add(counter.values, 1.0, 1, False) == 6.0


def test_what_a_kernel_prints_is_printed(capfd):
    @ti.kernel
    def hello(n: ti.i32):
        print("hello", n)

    for _ in range(2):
        hello(3)
    ti.sync()
    assert capfd.readouterr().out.count("hello 3") == 2


def test_instances_of_dead_objects_are_forgotten(monkeypatch):
    """Each object is an instance of its own (Taichi compiles one for each, as its own launch does): once
    a kernel keeps PRUNE of them, those of objects that died are dropped."""
    monkeypatch.setattr(launch, "PRUNE", 4)
    for start in range(12):
        counter = Counter(float(start))
        assert counter.count() == 7
        del counter
        gc.collect()
    plan = Counter.count._primal._quick_plan
    assert len(plan.instances) <= 5
