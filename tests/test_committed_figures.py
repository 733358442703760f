"""Every committed figure still says what the engine does: each docs/NAME.json (the numbers drawn
in docs/NAME.png) against a fresh `figures` run, within a tolerance. (tests/test_figures.py checks
the torsion figures and how every figure is made; frame25_coursework needs the coursework's files.)
When the engine changes a figure, regenerate it: `.venv/bin/python main.py figures --out docs --overwrite`.
"""

import json
import math

import pytest

from test_cli import run
from test_figures import DOCS

FIGURES = ["accuracy_vs_time", "volume_bunny", "volume_cube", "volume_cube86", "volume_epcot", "volume_fertility",
           "frame25_builtin", "epcot_compare", "epcot_compare_volume", "hard_case_energy", "integrator_order",
           "energy_drift"]
# Numbers agree to 5 % or 0.01 (f32 round-off in long runs, a few solver iterations more or less).
RELATIVE, ABSOLUTE = 0.05, 1e-2
# A run that blows up amplifies round-off, and round-off differs between processors (the same kernels
# compiled for AVX-512 or AVX2 add in another order) and between runs on one machine (166,632 J here,
# 97,646 J there at the third point): the one-solve step at dt 0.5 s on the hard case agrees for its
# first FIRST_STEPS energies only. Of the rest, what is stable is compared (unstable_features): the
# step at which it rises past RISE times its start, and that every energy is positive. How large the
# blown-up energies get is not: 5.6e13 J at most in the committed run, 2.6e15 J with the tests' build
# of the same kernels (tests/conftest.py), 1e9 times the start either way.
UNSTABLE = {"hard_case_energy.total_energy.single"}
FIRST_STEPS = 2
RISE = 10.0
# The Newton step on the hard case takes 98 % of the energy away in its first step (f32); what is left
# carries the round-off of what was taken (4 to 5 % of it between an AVX-512 and an AVX2 processor), so
# its energies agree to 5 % or to START_SHARE of the run's start energy. From its third step on (LATER),
# each step stops where float32 no longer resolves the nearly incompressible cube's volume term (residual
# 0.13 to 0.18 of its scale, at its round-off floor), and whether a step stops there or an iteration
# later is round-off's choice: the app's build and the tests' kept 11.6 and 7.6 J at step 10, 2.7 and
# 2.1 J at the end. There the energies agree within a factor CHAOS, and the figure's word, that the
# energy never rises, is its largest_rise_over_start, compared as every number is.
DISSIPATED = {"hard_case_energy.total_energy.newton"}
START_SHARE = 2e-3
LATER, CHAOS = 3, 2.0


def differences(made, committed, where=""):
    """Where two JSON values differ beyond the tolerance: [(path, made, committed)]."""
    if isinstance(made, dict) and isinstance(committed, dict):
        if set(made) != set(committed):
            return [(where, sorted(made), sorted(committed))]
        return [d for key in made for d in differences(made[key], committed[key], f"{where}.{key}")]
    if isinstance(made, list) and isinstance(committed, list):
        if where in UNSTABLE:
            if not same_blow_up(made, committed):
                return [(where, unstable_features(made), unstable_features(committed))]
            made, committed = made[:FIRST_STEPS], committed[:FIRST_STEPS]
        if len(made) != len(committed):
            return [(where, f"{len(made)} values", f"{len(committed)} values")]
        if where in DISSIPATED and made:
            floor = START_SHARE * max(abs(made[0]), abs(committed[0]))
            return [(f"{where}[{i}]", a, b) for i, (a, b) in enumerate(zip(made, committed))
                    if not (math.isclose(a, b, rel_tol=RELATIVE, abs_tol=floor)
                            or i >= LATER and b / CHAOS <= a <= b * CHAOS)]
        return [d for i, (a, b) in enumerate(zip(made, committed)) for d in differences(a, b, f"{where}[{i}]")]
    numbers = all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in (made, committed))
    if numbers and where.replace(".largest_rise_over_start", ".total_energy") in UNSTABLE:
        # The figure says "rises to ... times its start": at least doubling in one step, both times.
        return [] if min(made, committed) > 1 else [(where, made, committed)]
    if numbers:
        return [] if math.isclose(made, committed, rel_tol=RELATIVE, abs_tol=ABSOLUTE) else [(where, made, committed)]
    return [] if made == committed or where.endswith("source") else [(where, made, committed)]


def unstable_features(energies):
    """What a blown-up run repeats on any machine: (the first index where the energy passes RISE
    times its start, whether every energy is positive, the largest energy)."""
    rise = next((i for i, e in enumerate(energies) if e > RISE * energies[0]), None)
    return rise, all(e > 0 for e in energies), max(energies)


def same_blow_up(made, committed):
    """Two blown-up runs agree: they rise past RISE times their start at the same step, and stay positive."""
    (rise, positive, _), (rise_c, positive_c, _) = map(unstable_features, (made, committed))
    return rise is not None and (rise, positive) == (rise_c, positive_c) and positive


@pytest.fixture(scope="module")
def fresh(tmp_path_factory):
    out = tmp_path_factory.mktemp("fresh-figures")
    code, _, err = run("figures", "--out", str(out), "--only", *FIGURES)
    assert code == 0, err
    return out


@pytest.mark.parametrize("name", FIGURES)
def test_the_committed_figure_says_what_the_engine_does_now(fresh, name):
    made = json.loads((fresh / f"{name}.json").read_text())
    committed = json.loads((DOCS / f"{name}.json").read_text())
    found = differences(made, committed, name)
    assert found == [], f"{len(found)} numbers differ, e.g. {found[:3]}: regenerate docs/{name}.png"


def test_the_comparison_finds_a_figure_that_no_longer_matches():
    committed = {"total_energy": {"single": [1.0, 9.25]}}
    assert differences({"total_energy": {"single": [1.0, 5.33]}}, committed) == [
        (".total_energy.single[1]", 5.33, 9.25)]
    assert differences({"total_energy": {"single": [1.0, 9.26]}}, committed) == []


def test_a_dissipated_energy_is_compared_against_the_run_s_start():
    where = "hard_case_energy.total_energy.newton"
    assert differences([520.8, 9.29, 7.93], [520.8, 8.93, 7.52], where) == []   # AVX2 against AVX-512
    assert differences([520.8, 9.29, 9.1], [520.8, 8.93, 7.52], where) == [(f"{where}[2]", 9.1, 7.52)]
    committed = [520.8, 14.9, 14.9, 14.2, 11.6, 2.7]                 # the app's build; the tests' below
    assert differences([520.8, 14.9, 14.9, 14.2, 7.6, 2.1], committed, where) == []
    assert differences([520.8, 14.9, 14.9, 14.2, 5.6, 2.1], committed, where) == [(f"{where}[4]", 5.6, 11.6)]


def test_a_run_that_blows_up_is_compared_by_its_first_steps_and_its_rise():
    committed = {"total_energy": {"single": [1.0, 9.25, 30.0, 90.0, 3e4]}, "largest_rise_over_start": {"single": 1e4}}
    other_processor = {"total_energy": {"single": [1.0, 9.26, 17.1, 60.2, 2.2e4]}, "largest_rise_over_start": {"single": 1e3}}
    assert differences(other_processor, committed, "hard_case_energy") == []
    later = {"total_energy": {"single": [1.0, 9.26, 9.9, 90.2, 3e4]}, "largest_rise_over_start": {"single": 1e4}}
    assert differences(later, committed, "hard_case_energy") == [
        ("hard_case_energy.total_energy.single", (3, True, 3e4), (2, True, 3e4))]
    smaller = {"total_energy": {"single": [1.0, 9.26, 30.0, 90.0, 3e2]}, "largest_rise_over_start": {"single": 1e2}}
    assert differences(smaller, committed, "hard_case_energy") == []          # how large: round-off's
    bounded = {"total_energy": {"single": [1.0, 9.26, 9.5, 9.0, 8.0]}, "largest_rise_over_start": {"single": 8.3}}
    assert differences(bounded, committed, "hard_case_energy") == [
        ("hard_case_energy.total_energy.single", (None, True, 9.5), (2, True, 3e4))]
    early = {"total_energy": {"single": [1.0, 5.33, 30.0, 90.0, 3e4]}, "largest_rise_over_start": {"single": 1e4}}
    assert differences(early, committed, "hard_case_energy") == [("hard_case_energy.total_energy.single[1]", 5.33, 9.25)]
    tamed = {"total_energy": {"single": [1.0, 9.25, 30.0, 90.0, 3e4]}, "largest_rise_over_start": {"single": 0.0}}
    assert differences(tamed, committed, "hard_case_energy") == [
        ("hard_case_energy.largest_rise_over_start.single", 0.0, 1e4)]
