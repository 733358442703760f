"""Hard cases (scenes/hard_cases.py) stay finite, lose energy under damping, and report what went wrong.
(test_energy.py: their energy never rises from one step to the next.)

Every case runs with linear and corotational bodies, in f32 and f64. Cases that share a time
step run as bodies of one Simulation, so Taichi compiles a handful of times, not once per case.
"""

import math

import numpy as np
import pytest

import fem
from cases import CLI_HARD_CASES, forced_failures, run_cli_case, run_hard_cases
from scenes.hard_cases import HARD_CASES, METHODS, groups

PRECISIONS = ("f32", "f64")
CASES = [pytest.param(case.name, method, id=f"{case.name}-{method}")
         for case in HARD_CASES for method in METHODS]


@pytest.fixture(scope="module", params=PRECISIONS)
def precision(request):
    """Every test of one precision, then every test of the other: Taichi restarts once for each."""
    fem.init("cpu", request.param)
    return request.param


@pytest.fixture(scope="module")
def outcomes(precision):
    """{(case name, method): Outcome} of every hard case in one precision."""
    fem.init("cpu", precision)
    return {(o.case.name, o.method): o for group in groups() for o in run_hard_cases(group)}


@pytest.mark.parametrize("name, method", CASES)
def test_positions_stay_finite_and_no_step_is_rejected(outcomes, name, method):
    outcome = outcomes[name, method]
    assert outcome.finite
    assert outcome.rejected_steps == 0


@pytest.mark.parametrize("name, method", CASES)
def test_energy_ends_below_its_start_with_damping(outcomes, name, method):
    outcome = outcomes[name, method]
    assert math.isfinite(outcome.energy_end)
    assert outcome.energy_end <= outcome.energy_start * (1 + 1e-3)
    assert outcome.energy_max <= outcome.energy_start * (1 + 1e-3)


@pytest.mark.parametrize("name", [case.name for case in HARD_CASES if case.inverted])
def test_corotational_bodies_recover_from_an_inverted_start(outcomes, name):
    outcome = outcomes[name, "corotational"]
    assert outcome.inverted_start > 0
    assert outcome.inverted_end == 0
    assert all(abs(ratio - 1) < 0.05 for ratio in outcome.volume_ratio_end)


def test_capped_solves_and_non_finite_steps_are_reported(precision, capsys):
    fem.init("cpu", precision)
    result = forced_failures(lambda: capsys.readouterr().err)

    for info in result["capped"]:        # the cap is reported, never hidden
        assert info["solver_iters"] == 2 and info["solver_capped"] == 1
        assert info["converged"] is False
        assert info["residual"] is not None and info["residual"] > 1e-12
        assert info["finite"]

    assert [info["finite"] for info in result["nan"]] == [False, False, False]
    np.testing.assert_array_equal(result["after"], result["before"])   # the state is kept
    assert np.isfinite(result["after"]).all()
    warnings = [line for line in result["stderr"].splitlines() if line.startswith("warning:")]
    assert len(warnings) == 1, result["stderr"]
    assert "non-finite" in warnings[0] and "kept the previous state" in warnings[0]


@pytest.mark.parametrize("method, precision", CLI_HARD_CASES)
def test_simulate_command_survives_extremes(method, precision, tmp_path):
    """nu = 0.4999, E = 1e9 and E = 10 bodies, 1e5 m/s impulses, dt = 0.5 s, through main.py."""
    run = run_cli_case(method, precision, tmp_path)
    assert run.returncode == 0, run.stderr
    assert "0 steps rejected" in run.stdout
    assert "nan" not in run.stdout.lower() and "inf " not in run.stdout.lower()
    assert "Traceback" not in run.stderr
