"""What the benchmark's rows say: errors against the reference, the error goal, the cheapest run
within it, the direct baseline, and the headline sentences."""

import math
import statistics
from collections import Counter

from app.bench import direct
from app.bench.plan import (BASELINE_TOLERANCE, DIRECT_TARGET, DIRECT_TOLERANCE, DT_FACTORS, ERROR_GOAL, INTEGRATORS,
                            MIN_REFERENCE_ORDER, PCG_TOLERANCES, REFERENCE_ORDER, REFERENCE_REFINEMENT,
                            REFERENCE_SETTINGS, SECOND_ORDER, TARGET_SCENE, integrator_of, sci)
from fem.implicit.integrators import chosen
from fem.scene import SolverSettings

ORDER_MARGIN = 10    # the observed order leaves out errors under this many times the reference's floor
TIME_RESOLUTION = 0.1   # the time axis's resolution: two full benchmark runs on one 2-core machine (AMD EPYC,
                        # 243 backward-Euler rows) put the same variant's time per simulated second a median
                        # 8 % apart (a tenth of them more than 21 %)

# ---------------------------------------------------------------- conclusions

def find(scene, **fields):
    """The first row whose fields have these values, or None."""
    return next((r for r in scene["variants"] if all(r[k] == v for k, v in fields.items())), None)


def final_error(row):
    return list(row["errors"].values())[-1]


def baseline(scene, method, step, solver="pcg", integrator="backward-euler"):
    """The row at the scene's dt with the default tolerance (PCG), or the solver alone (direct: the fastest)."""
    if solver != "pcg":
        return find(scene, method=method, solver=solver)
    return find(scene, method=method, solver="pcg", step=step, integrator=integrator, dt_factor=1,
                tolerance=BASELINE_TOLERANCE)


def dt_axis(scene, step, integrator, method="corotational"):
    """The rows of the dt axis (PCG at the default tolerance), largest dt first (none from results that
    predate the integrator)."""
    rows = [find(scene, method=method, solver="pcg", step=step, integrator=integrator, dt_factor=f,
                 tolerance=BASELINE_TOLERANCE) for f in DT_FACTORS]
    return [r for r in rows if r is not None]


def reference_order(difference, twins):
    """The reference's own observed order, from `difference`, its distance to the run at 2 dt_ref, and
    `twins`, that run's distance to the one at 4 dt_ref: with an error C dt^p they are C dt_ref^p (2^p - 1)
    and 2^p times that. (Two runs that agree exactly say nothing: the integrator's order.)"""
    return math.log2(twins / difference) if difference > 0 and twins > 0 else REFERENCE_ORDER


def reference_floor(difference, order):
    """The reference's own error, C dt_ref^p = difference / (2^p - 1), p its observed order, at most its
    integrator's REFERENCE_ORDER (higher would be luck) and at least MIN_REFERENCE_ORDER."""
    p = min(max(order, MIN_REFERENCE_ORDER), REFERENCE_ORDER)
    return difference / (2 ** p - 1)


def observed_order(scene, step, integrator):
    """The slope of log error against log dt over the corotational dt axis (least squares), leaving out
    errors under ORDER_MARGIN times the reference's floor, which they would mostly measure; None with
    fewer than two points."""
    points = [(r["dt"], final_error(r)) for r in dt_axis(scene, step, integrator)
              if final_error(r) is not None and final_error(r) > ORDER_MARGIN * scene["reference_floor"]]
    if len(points) < 2:
        return None
    return statistics.linear_regression([math.log(dt) for dt, _ in points], [math.log(e) for _, e in points]).slope


def observed_orders(scene):
    """{integrator: {step: observed order}} of the corotational steps."""
    return {integrator: {step: observed_order(scene, step, integrator) for step in ("newton", "single")}
            for integrator in INTEGRATORS}


def corotation_cost(scene, step, solver="pcg"):
    """Extra time per step of corotational over linear FEM, in %."""
    corot, linear = baseline(scene, "corotational", step, solver), baseline(scene, "linear", "newton", solver)
    return 100 * (corot["ms_median"] / linear["ms_median"] - 1)


def meets_goal(row, scene):
    """Error plus the reference's own error (so a bound on the true error) within the goal."""
    error = final_error(row)
    return error is not None and error + scene["reference_floor"] <= ERROR_GOAL


def goal_dt(scene, step, integrator="backward-euler"):
    """The largest dt of the corotational dt axis (PCG at the default tolerance) that meets the goal."""
    return next((r["dt"] for r in dt_axis(scene, step, integrator) if meets_goal(r, scene)), None)


def cheapest_to_goal(scene, step):
    """The corotational backward-Euler PCG row of this step kind that meets the goal in the least time per
    simulated second."""
    rows = [r for r in scene["variants"] if r["method"] == "corotational" and r["solver"] == "pcg"
            and r["step"] == step and integrator_of(r) == "backward-euler" and meets_goal(r, scene)]
    return min(rows, key=lambda r: r["s_per_sim_s"], default=None)


def measured_rows(scene):
    """The variants with an error at the last checkpoint (the reference's rows aside)."""
    return [r for r in scene["variants"] if r["solver"] != "reference" and final_error(r) is not None]


def frontier_rows(scene):
    """Variants no other variant beats in both time per simulated second and accuracy (at the last checkpoint)."""
    rows = measured_rows(scene)
    return [r for r in sorted(rows, key=lambda r: r["s_per_sim_s"])
            if not any(o["s_per_sim_s"] < r["s_per_sim_s"] and final_error(o) <= final_error(r) for o in rows)]


def frontier(scene):
    """The labels of the frontier's rows, fastest first."""
    return [r["label"] for r in frontier_rows(scene)]


def beaten_beyond_the_floor(scene, row, time_margin=0.0):
    """Whether a variant faster than `row` (by more than time_margin, a fraction of its time) is more
    accurate by more than the reference floor, the error axis's resolution: the frontier with
    differences the reference cannot tell apart as ties."""
    return any(o["s_per_sim_s"] * (1 + time_margin) < row["s_per_sim_s"]
               and final_error(o) + scene["reference_floor"] < final_error(row) for o in measured_rows(scene))


def beaten_beyond_resolution(scene, row):
    """`beaten_beyond_the_floor` with the time axis's resolution too: neither axis's unresolved
    differences beat `row`."""
    return beaten_beyond_the_floor(scene, row, TIME_RESOLUTION)


def default_step(scene):
    """(integrator, step, tolerance) of the engine's default settings, fem.scene.SolverSettings(), on
    this scene ("auto" picks by whether it has a ground)."""
    settings = SolverSettings()
    return chosen(settings.integrator, scene.get("ground", False)), settings.step, settings.tolerance


def direct_comparison(scene):
    """The matrix-free corotational one-solve step at PCG 1e-3 (at the baseline tolerance when the tolerance
    axis lacks 1e-3) against the direct baseline: a sentence, and {solver: direct ms per step / matrix-free ms
    per step} with "factorisation" (the fastest's alone)."""
    tolerance = DIRECT_TOLERANCE if DIRECT_TOLERANCE in PCG_TOLERANCES else BASELINE_TOLERANCE
    matrix_free = find(scene, method="corotational", solver="pcg", step="single", integrator="backward-euler",
                       dt_factor=1, tolerance=tolerance)
    rows = [r for r in scene["variants"] if r["method"] == "corotational" and r["solver"] == "direct"]
    ms = matrix_free["ms_median"]
    ratios = {r["backend"]: r["ms_median"] / ms for r in rows}
    fastest = rows[0]
    ratios["factorisation"] = fastest["factorise_ms"] / ms
    role = "the fastest direct solver installed" if fastest["backend"] != "superlu" else "the direct solver"
    sentence = (f"On {scene['name']} ({scene['tets']} tets) the matrix-free corotational one-solve step at PCG "
                f"{sci(tolerance)} takes {ms:.3g} ms; {role}, {direct.BACKENDS[fastest['backend']].label} "
                f"refactorising every step, takes {ratios[fastest['backend']]:.2g} times as long "
                f"({fastest['ms_median']:.3g} ms; its factorisation alone {fastest['factorise_ms']:.3g} ms, "
                f"{ratios['factorisation']:.2g} times)")
    if len(rows) > 1:
        sentence += f", SuperLU {ratios['superlu']:.2g} times ({rows[1]['ms_median']:.3g} ms)"
    exact = fastest if final_error(fastest) is not None else find(     # a direct run stopped by the budget
        scene, method="corotational", solver="pcg", step="single", integrator="backward-euler", dt_factor=1,
        tolerance=min(PCG_TOLERANCES))
    sentence += (f"; the matrix-free step's position error {final_error(matrix_free):.2e}, the exact solve's "
                 f"{final_error(exact):.2e}" + ("" if exact is fastest else f" (at PCG {sci(exact['tolerance'])})"))
    if scene["name"] != TARGET_SCENE:
        return sentence + f". (The target, at least {DIRECT_TARGET} times, is set on {TARGET_SCENE}.)", ratios
    met = "met" if ratios[fastest["backend"]] >= DIRECT_TARGET else "not met"
    return sentence + f". Target: at least {DIRECT_TARGET} times, {met}.", ratios


def spread(values, spec=".2f"):
    """'lo to hi' of several values ('' for one)."""
    return f"{min(values):{spec}} to {max(values):{spec}}" if len(values) > 1 else ""


def median_ratio(pairs):
    """(median of a / b, every a / b) over the pairs where both are known and non-zero."""
    ratios = [a / b for a, b in pairs if a and b]
    return (statistics.median(ratios), ratios) if ratios else (None, [])


def where_met(dts):
    """'reaches it at dt 0.04 s in 2 of 4 scenes, 0.01 s in 1, never in 1', from the largest dt meeting
    the goal in each scene (None: none does)."""
    counts = Counter(dts)
    found = sorted((d for d in counts if d is not None), reverse=True)
    if not found:
        return "never reaches it" if len(dts) == 1 else f"reaches it in none of the {len(dts)} scenes"
    if len(dts) == 1:
        return f"reaches it at dt {found[0]:g} s"
    parts = [f"{d:g} s in {counts[d]}" for d in found] + ([f"never in {counts[None]}"] if None in counts else [])
    return f"reaches it at dt {parts[0]} of {len(dts)} scenes" + "".join(f", {p}" for p in parts[1:])


def cost_text(costs):
    """A cost in % over the scenes: '+2 %', with its range over several scenes, marked where the
    median is within TIME_RESOLUTION, the spread of timings from run to run."""
    median = statistics.median(costs)
    text = f"{median:+.0f} %"
    notes = [f"{min(costs):+.0f} to {max(costs):+.0f} %"] if len(costs) > 1 else []
    if abs(median) < 100 * TIME_RESOLUTION:
        notes.append("within noise")
    return text + (f" ({'; '.join(notes)})" if notes else "")


def headline(scenes, quick=False):
    """The measured answers, as sentences and as numbers. `quick`: a quick run's, which leaves out what
    its few scenes and short runs cannot support: the frontier and whether Newton pays."""
    n, last = len(scenes), scenes[0]["checkpoints"][-1]
    dts = sorted({s["dt"] for s in scenes})
    at_dt = f"dt {dts[0]:g} s" if len(dts) == 1 else "each scene's dt"
    newton = [baseline(s, "corotational", "newton") for s in scenes]
    single = [baseline(s, "corotational", "single") for s in scenes]
    time_ratio, times = median_ratio((a["s_per_sim_s"], b["s_per_sim_s"]) for a, b in zip(newton, single))
    error_ratio, errors = median_ratio((final_error(a), final_error(b)) for a, b in zip(newton, single))
    goal = {integrator: {step: [goal_dt(s, step, integrator) for s in scenes] for step in ("newton", "single")}
            for integrator in INTEGRATORS}
    cheapest = [(cheapest_to_goal(s, "newton"), cheapest_to_goal(s, "single")) for s in scenes]
    pays, pay_ratios = median_ratio((a["s_per_sim_s"], b["s_per_sim_s"]) for a, b in cheapest if a and b)
    floors = [s["reference_floor"] for s in scenes]
    numbers = {
        "newton_over_single_time": time_ratio, "newton_over_single_error": error_ratio,
        "goal_dt": goal,     # {integrator: {step: per scene, in order: the largest dt meeting the goal (None: none)}}
        "cheapest_to_goal_newton_over_single": pays,
        "corotation_cost_single_pct": statistics.median(corotation_cost(s, "single") for s in scenes),
        "corotation_cost_newton_pct": statistics.median(corotation_cost(s, "newton") for s in scenes),
        "corotation_cost_direct_pct": statistics.median(corotation_cost(s, "single", "direct") for s in scenes),
        "reference_floor": statistics.median(floors),
    }
    over = f"; medians over {n} scenes, {spread(times)} and {spread(errors)} times" if n > 1 else ""
    lines = [f"A correct step costs: Newton takes {fmt(time_ratio, '.2f')} times the wall time per simulated "
             f"second of the one-solve step and leaves {fmt(error_ratio, '.2f')} times its error (corotational "
             f"backward Euler, PCG {sci(BASELINE_TOLERANCE)}, {at_dt}{over})."]
    sentence, numbers["integrators"] = second_order(scenes, at_dt, frontier_claims=not quick)
    lines.append(sentence)
    sentence, numbers["default_step"] = default_step_numbers(scenes, at_dt, frontier_claims=not quick)
    lines.append(sentence)
    reach = {integrator: f"{INTEGRATORS[integrator]}'s Newton step {where_met(goal[integrator]['newton'])}, its "
                         f"one-solve step {where_met(goal[integrator]['single'])}" for integrator in INTEGRATORS}
    sentence = (f"Within the error goal ({100 * ERROR_GOAL:g} % of the scene size at t = {last:g} s, the "
                f"reference's own error counted in), at PCG {sci(BASELINE_TOLERANCE)}: "
                + "; ".join(reach.values()) + ".")
    if pays is not None and not quick:
        both = ("" if n == 1 else f" (median over the {len(pay_ratios)} scenes where both meet it)"
                if len(pay_ratios) > 1 else " (in the one scene where both meet it)")
        sentence += (f" The cheapest corotational backward-Euler run within it takes {pays:.2f} times the wall time "
                     f"per simulated second with Newton as with the one-solve step{both}: "
                     + ("Newton pays." if pays < 1 else "Newton does not pay at this goal."))
    lines.append(sentence)
    largest = max(scenes, key=lambda s: s["tets"])
    sentence, numbers["direct_over_matrix_free"] = direct_comparison(largest)
    lines.append(sentence)
    pct = {"single": cost_text([corotation_cost(s, "single") for s in scenes]),
           "newton": cost_text([corotation_cost(s, "newton") for s in scenes]),
           "direct": cost_text([corotation_cost(s, "single", "direct") for s in scenes])}
    lines.append(f"Corotation costs, per step against a linear body's (one exact solve, inside the line search "
                 f"and the energy safeguard): {pct['single']} with the matrix-free one-solve step (PCG "
                 f"{sci(BASELINE_TOLERANCE)}; it skips both, so it can cost less), {pct['newton']} with Newton and "
                 f"{pct['direct']} with the fastest direct solver" + (" (medians, and ranges over the scenes)"
                                                                     if n > 1 else "")
                 + f". Timings of one variant differ by about {100 * TIME_RESOLUTION:g} % from run to run: a cost "
                 "within that is noise.")
    dt_ref = f" = {scenes[0]['reference_dt']:g} s" if len(dts) == 1 else ""
    orders = [s["reference_order"] for s in scenes]
    numbers["reference_order"] = statistics.median(orders)
    ranges = f" (medians; {spread(floors, '.1e')} and {spread(orders)})" if n > 1 else ""
    lines.append(f"The reference ({INTEGRATORS[REFERENCE_SETTINGS['integrator']]}, Newton to 1e-10 in f64 at "
                 f"dt_ref = dt / {REFERENCE_REFINEMENT}{dt_ref}) has an error of its own of about "
                 f"{numbers['reference_floor']:.1e}: its distance to a run at 2 dt_ref over 2^p - 1, p its own "
                 f"order, {numbers['reference_order']:.2f}, from a third run at 4 dt_ref{ranges}. The error axis "
                 "bottoms out there: an error measured near it is the true one give or take that much.")
    return lines, numbers


def second_order(scenes, at_dt, frontier_claims=True):
    """What each second-order integrator buys and costs against backward Euler: a sentence, and its numbers
    (on the frontier of how many scenes unless not `frontier_claims`)."""
    n = len(scenes)
    ratios = {}
    for integrator in SECOND_ORDER:
        for step in ("newton", "single"):
            pairs = [(baseline(s, "corotational", step, integrator=integrator), baseline(s, "corotational", step))
                     for s in scenes]
            pairs = [(a, b) for a, b in pairs if a is not None]
            error, _ = median_ratio((final_error(a), final_error(b)) for a, b in pairs)
            time, _ = median_ratio((a["s_per_sim_s"], b["s_per_sim_s"]) for a, b in pairs)
            ratios.setdefault(integrator, {})[step] = {"error": error, "time": time}
    orders = {integrator: {step: median_or_none(observed_order(s, step, integrator) for s in scenes)
                           for step in ("newton", "single")} for integrator in INTEGRATORS}
    frontiers = [[integrator_of(r) for r in frontier_rows(s)] for s in scenes]
    on_frontier = {integrator: sum(integrator in f for f in frontiers) for integrator in INTEGRATORS}
    points = {integrator: sum(f.count(integrator) for f in frontiers) for integrator in INTEGRATORS}
    medians = " (medians)" if n > 1 else ""
    against = "; ".join(
        f"{INTEGRATORS[i]} with Newton steps leaves {fmt(r['newton']['error'], '.2g')} times the error in "
        f"{fmt(r['newton']['time'], '.2f')} times the wall time per simulated second, with one-solve steps "
        f"{fmt(r['single']['error'], '.2g')} times in {fmt(r['single']['time'], '.2f')} times"
        for i, r in ratios.items())
    sentence = (f"Second order against backward Euler (corotational, PCG {sci(BASELINE_TOLERANCE)}, {at_dt}): "
                f"{against}{medians}. Observed order, the slope of log error against log dt over the dt axis, "
                "Newton and one-solve steps: "
                + ", ".join(f"{INTEGRATORS[i]} {fmt(o['newton'], '.2f')} and {fmt(o['single'], '.2f')}"
                            for i, o in orders.items())
                + f"{medians}.")
    if frontier_claims:
        sentence += " On the accuracy/time frontier: " + ", ".join(
            f"{INTEGRATORS[i]} on {k} of {n} scenes ({points[i]} of the {sum(points.values())} points)"
            for i, k in on_frontier.items()) + "."
    numbers = {f"{i}_over_backward_euler": r for i, r in ratios.items()}
    return sentence, {**numbers, "observed_order": orders, "frontier_scenes": on_frontier, "frontier_points": points}


def default_step_numbers(scenes, at_dt, frontier_claims=True):
    """The engine's default step (corotational, PCG at the default tolerance, the scene's dt): on how many
    scenes it is on the frontier (said unless not `frontier_claims`) and meets the goal, and its time
    against backward Euler's one-solve step."""
    steps = [default_step(s) for s in scenes]
    rows = [find(s, method="corotational", solver="pcg", step=step, integrator=integrator, dt_factor=1,
                 tolerance=tolerance) for s, (integrator, step, tolerance) in zip(scenes, steps)]
    single = [baseline(s, "corotational", "single") for s in scenes]
    time, times = median_ratio((a["s_per_sim_s"], b["s_per_sim_s"]) for a, b in zip(rows, single))
    setting, step, tolerance = SolverSettings().integrator, steps[0][1], steps[0][2]
    numbers = {"integrator": setting, "integrators": [integrator for integrator, _, _ in steps], "step": step,
               "scenes": len(scenes), "on_frontier": sum(r["label"] in frontier(s) for r, s in zip(rows, scenes)),
               "on_frontier_beyond_floor": sum(not beaten_beyond_the_floor(s, r) for r, s in zip(rows, scenes)),
               "on_frontier_beyond_resolution": sum(not beaten_beyond_resolution(s, r) for r, s in zip(rows, scenes)),
               "meets_goal": sum(meets_goal(r, s) for r, s in zip(rows, scenes)), "time_over_single": time}
    n = len(scenes)
    over = f" (median; {spread(times)})" if n > 1 else ""
    kind = {"newton": "Newton", "single": "one-solve"}[step]
    used = dict.fromkeys(numbers["integrators"])
    which = " and ".join(f"{INTEGRATORS[i]} on {numbers['integrators'].count(i)}" for i in used) if n > 1 else \
        INTEGRATORS[steps[0][0]]
    name = f"{setting}: {which}" if setting == "auto" else INTEGRATORS[setting]
    frontier_clause = (f"is on the frontier on {numbers['on_frontier']} of {n} scenes "
                       f"({numbers['on_frontier_beyond_floor']} of {n} where beating it takes an error smaller by "
                       f"more than the reference floor, {numbers['on_frontier_beyond_resolution']} of {n} where it "
                       f"also takes a time shorter by more than {100 * TIME_RESOLUTION:g} %, the spread of timings "
                       "from run to run), " if frontier_claims else "")
    sentence = (f"The default step (fem.scene.SolverSettings(): {name}, {kind}; corotational, "
                f"PCG {sci(tolerance)}, {at_dt}) {frontier_clause}meets the {100 * ERROR_GOAL:g} % goal at "
                f"t = {scenes[0]['checkpoints'][-1]:g} s on {numbers['meets_goal']} of {n}, and takes "
                f"{fmt(time, '.2f')} times the wall time per simulated second of backward Euler's one-solve "
                f"step{over}.")
    return sentence, numbers


def median_or_none(values):
    known = [v for v in values if v is not None]
    return statistics.median(known) if known else None


def fmt(value, spec=".3g", missing="–"):
    return missing if value is None else format(value, spec)
