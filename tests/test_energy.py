"""The promise of the step: total energy never rises, on every hard case (scenes/hard_cases.py),
at every time step of ENERGY_DTS, with linear and corotational bodies, in f32 and f64."""

import numpy as np
import pytest

import fem
from cases import energy_history
from scenes.hard_cases import ENERGY_DTS, ENERGY_TOLERANCE

PRECISIONS = ("f32", "f64")


@pytest.fixture(scope="module", params=PRECISIONS)
def precision(request):
    """Every test of one precision, then every test of the other: Taichi restarts once for each."""
    fem.init("cpu", request.param)
    return request.param


@pytest.mark.parametrize("dt", ENERGY_DTS)
def test_total_energy_never_rises_from_one_step_to_the_next(precision, dt):
    """The promise: kinetic + elastic + gravitational energy never rises, for every hard case and
    both methods, at every time step; per step at most ENERGY_TOLERANCE of the starting energy."""
    fem.init("cpu", precision)
    layout, energies = energy_history(dt)
    rise = np.diff(energies, axis=0).max(axis=0) / np.abs(energies[0])
    worst = {f"{case.name} ({method})": float(r) for (case, method, _), r in zip(layout, rise)
             if not r <= ENERGY_TOLERANCE[precision]}
    assert np.isfinite(energies).all()
    assert not worst, worst
