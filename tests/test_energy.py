"""The promise of the step: total energy never rises, on every hard case (scenes/hard_cases.py),
at every time step of ENERGY_DTS, with linear and corotational bodies, in f32 and f64; and on
bodies dropped and spun onto the ground, where the contact's energy counts too."""

import numpy as np
import pytest

import fem
from cases import energy_history, ground_history
from fem.scene import INTEGRATORS
from scenes.hard_cases import ENERGY_DTS, ENERGY_TOLERANCE

PRECISIONS = ("f32", "f64")


@pytest.fixture(scope="module", params=PRECISIONS)
def precision(request):
    """Every test of one precision, then every test of the other: Taichi restarts once for each."""
    fem.init("cpu", request.param)
    return request.param


@pytest.mark.parametrize("integrator", INTEGRATORS)
@pytest.mark.parametrize("dt", ENERGY_DTS)
def test_total_energy_never_rises_from_one_step_to_the_next(precision, dt, integrator):
    """The promise: kinetic + elastic + gravitational energy never rises, for every hard case and
    both methods, at every time step; per step at most ENERGY_TOLERANCE of the starting energy."""
    fem.init("cpu", precision)
    layout, energies, _ = energy_history(dt, integrator=integrator)
    rise = np.diff(energies, axis=0).max(axis=0) / np.abs(energies[0])
    worst = {f"{case.name} ({method})": float(r) for (case, method, _), r in zip(layout, rise)
             if not r <= ENERGY_TOLERANCE[precision]}
    assert np.isfinite(energies).all()
    assert not worst, worst


@pytest.mark.parametrize("integrator", INTEGRATORS)
@pytest.mark.parametrize("dt", ENERGY_DTS)
def test_bodies_dropped_and_spun_onto_the_ground_never_gain_energy(precision, dt, integrator):
    """Issue 23's promise with the ground on: cubes of E 1e3 to 1e9 Pa and nu 0.3 to 0.49995,
    linear and corotational, falling at 2 m/s and spinning at 3 rad/s onto the plane, without
    damping: kinetic + elastic + gravitational + contact energy never rises by more than
    ENERGY_TOLERANCE of the run's largest energy in one step, with either integrator."""
    fem.init("cpu", precision)
    layout, energies, _ = ground_history(dt, integrator)
    rise = np.diff(energies, axis=0).max(axis=0) / np.abs(energies).max(axis=0)
    worst = {f"{name} ({method})": float(r) for (name, method, _), r in zip(layout, rise)
             if not r <= ENERGY_TOLERANCE[precision]}
    assert np.isfinite(energies).all()
    assert not worst, worst
