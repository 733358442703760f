"""The piles' rows of docs/benchmark.md's "What contact costs": ours at 5 to 40 boxes, then beside the
peer's (app/bench/contact.py measures them)."""

import numpy as np


def piles(results):
    """The piles' rows of a benchmark's results ([] when it did not measure them)."""
    scaling = results.get("contact", {}).get("scaling")
    return markdown(scaling) if scaling else []


def markdown(scaling):
    """The piles' rows: ours at each size, then ours beside the peer's (or why it is not measured), then
    what friction's stick speed costs (where measured)."""
    return piles_and_peer(scaling) + stick_speeds(scaling)


def stick_speeds(scaling):
    """The pile's rows at each stick speed measured ([] where a benchmark did not measure them)."""
    measured = scaling.get("stick_speeds")
    if not measured:
        return []
    lines = ["### What friction's stick speed costs", "",
             "Friction holds a body below its stick speed (`[effects] stick_speed`, IPC's eps_v, 1 mm/s unless a "
             "scene sets it): a body it holds creeps, at most that fast, and while a pair sticks its friction curves "
             "by 2 mu lambda / eps, so a smaller one holds more tightly and conditions the step worse. The pile of "
             f"{measured['bodies']} boxes, the same steps as above, at each:", "",
             "| stick speed | ms/step | Newton it./step | CG it./step | steps not converged |", "|---:" * 5 + "|"]
    lines += [f"| {1e3 * r['stick_speed']:g} mm/s | {ms(r['ms_median'])} | {r['newton']:.1f} | {r['cg']:.0f} | "
              f"{r['unconverged']} of {scaling['steps']} |" for r in measured["rows"]]
    return lines + [""]


def piles_and_peer(scaling):
    """Ours at each size, then ours beside the peer's (or why it is not measured)."""
    rows, peer_runs = scaling["ours"], scaling["peer"]
    low, high = scaling["load_average"]
    sizes = scaling["sizes"]
    lines = [f"### The pile from {sizes[0]} to {sizes[-1]} boxes, beside a peer", "",
             f"Piles of {', '.join(map(str, sizes[:-1]))} and {sizes[-1]} boxes (examples/pile.toml's first boxes; "
             f"past its 20, its layers repeated upward), each {scaling['steps']} steps after {scaling['warmup']} "
             f"from the start, on the machine above, Taichi's profiler off, load average {low:.1f} at the start "
             f"and {high:.1f} at the end ({scaling['date']}). Smallest gap: the least distance between two "
             "bodies' surfaces over the timed steps (the contact distance is "
             f"{1e3 * scaling['distance']:g} mm); sunk: the deepest vertex under the ground.", "",
             "| boxes | vertices | ms/step | Newton it./step | CG it./step | steps not converged | contact off, "
             "ms/step | contact on / off | smallest gap | sunk |", "|---:" * 10 + "|"]
    for r in rows:
        on, off = r["on"], r["off"]
        lines.append(f"| {r['bodies']} | {r['vertices']} | {ms(on['ms_median'])} | {on['newton']:.1f} | "
                     f"{on['cg']:.0f} | {on['unconverged']} of {scaling['steps']} | {ms(off['ms_median'])} | "
                     f"{on['ms_median'] / off['ms_median']:.0f} x | {gap(on, scaling['steps'])} | "
                     f"{1e3 * on['sunk']:.2f} mm |")
    lines += ["", growth("Our", [(r["bodies"], r["on"]["ms_median"]) for r in rows]), ""]
    if isinstance(peer_runs, str):
        return lines + [f"The peer, Newton's VBD: {peer_runs}.", ""]
    lines += ["| boxes | solver | ms/step | smallest gap | sunk |", "|---:|---|---:|---:|---:|"]
    for r in rows:
        lines.append(f"| {r['bodies']} | ours | {ms(r['on']['ms_median'])} | {gap(r['on'], scaling['steps'])} | "
                     f"{1e3 * r['on']['sunk']:.2f} mm |")
        lines += [f"| {p['bodies']} | peer, {stiffness(p['contact_stiffness'])} N/m | {ms(p['ms_median'])} | "
                  f"{gap(p, scaling['steps'])} | {1e3 * p['sunk']:.2f} mm |"
                  for p in peer_runs["rows"] if p["bodies"] == r["bodies"]]
    stiffnesses = dict.fromkeys(p["contact_stiffness"] for p in peer_runs["rows"])
    for k in stiffnesses:
        costs = [(p["bodies"], p["ms_median"]) for p in peer_runs["rows"] if p["contact_stiffness"] == k]
        lines += ["", growth(f"The peer's (at {stiffness(k)} N/m)", costs)]
    s = peer_runs["setup"]
    return lines + ["", f"The peer: Newton {s['newton']}'s VBD with self-contact (Warp {s['warp']}, device "
                    f"{s['device']}), the same boxes, dt, steps, gravity, ground, friction (0.3 between boxes, 0.4 on "
                    f"the ground) and contact distance; each step {s['substeps']} sub-steps of {s['iterations']} "
                    "iterations (its softbody_gift example's)"
                    f"{'; Warp runs a CPU kernel on one thread (VBD is made for GPUs)' if s['device'] == 'cpu' else ''}"
                    ". Its contact is a penalty, between boxes closer than "
                    "the contact distance (ours: a barrier) and with the ground from "
                    f"{1e3 * s['particle_radius']:g} mm above it (ours: a penalty from the ground itself), of "
                    f"{' or '.join(map(stiffness, stiffnesses))} N/m (its example's, and stiffer). Its "
                    "elasticity is neo-Hookean with our E and nu's Lame parameters (ours: corotational), its damping "
                    "the stiffness part of ours alone (the mass part has no counterpart). app/bench/peer.py runs it.",
                    ""]


def ms(value):
    """A time in ms: three digits, and no exponent past 1000."""
    return f"{value:.3g}" if value < 1000 else f"{value:.0f}"


def stiffness(value):
    """N/m as 5e4, 1e6."""
    return f"{value:.0e}".replace("e+0", "e")


def gap(row, steps):
    """A smallest gap in mm, or how many steps a vertex was inside another body."""
    if row["crossed_steps"]:
        return f"crossed in {row['crossed_steps']} of {steps} steps"
    return "–" if row["gap"] is None else f"{1e3 * row['gap']:.2f} mm"


def growth(who, points):
    """A sentence: how the ms/step of `points` [(bodies, ms)] grows from the fewest bodies to the most, and
    the power of the bodies that fits it (least squares in logs; 1 is linear). "" for one size."""
    if len(points) < 2:
        return ""
    (n0, ms0), (n1, ms1) = points[0], points[-1]
    power = np.polyfit(np.log([n for n, _ in points]), np.log([ms for _, ms in points]), 1)[0]
    return (f"{who} step costs {ms1 / ms0:.1f} times as much at {n1} boxes as at {n0} ({n1 / n0:g} times the "
            f"bodies): about bodies^{power:.2f} over the sizes measured (1 would be linear).")
