"""The piles' rows of docs/benchmark.md's "What contact costs": ours at 5 to 40 boxes, then beside the
peer's (app/bench/contact.py measures them)."""

import numpy as np


def markdown(scaling):
    """The piles' rows: ours at each size, then ours beside the peer's (or why it is not measured)."""
    rows, peer_runs = scaling["ours"], scaling["peer"]
    low, high = scaling["load_average"]
    lines = ["### The pile from 5 to 40 boxes, beside a peer", "",
             f"Piles of {', '.join(map(str, scaling['sizes']))} boxes (examples/pile.toml's first boxes; past its "
             f"20, its layers repeated upward), each {scaling['steps']} steps after {scaling['warmup']} from the "
             f"start, Taichi's profiler off, load average {low:.1f} at the start and {high:.1f} at the end "
             f"({scaling['date']}). Smallest gap: the least distance between two bodies' surfaces over the timed "
             f"steps (the contact distance is {1e3 * scaling['distance']:g} mm); sunk: the deepest vertex under "
             "the ground.", "",
             "| boxes | vertices | ms/step | Newton it./step | CG it./step | steps not converged | contact off, "
             "ms/step | contact on / off | smallest gap | sunk |", "|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        on, off = r["on"], r["off"]
        lines.append(f"| {r['bodies']} | {r['vertices']} | {on['ms_median']:.3g} | {on['newton']:.1f} | "
                     f"{on['cg']:.0f} | {on['unconverged']} of {scaling['steps']} | {off['ms_median']:.3g} | "
                     f"{on['ms_median'] / off['ms_median']:.0f} x | {gap(on, scaling['steps'])} | "
                     f"{1e3 * on['sunk']:.2f} mm |")
    lines += ["", growth("Ours", [(r["bodies"], r["on"]["ms_median"]) for r in rows]), ""]
    if isinstance(peer_runs, str):
        return lines + [f"The peer, Newton's VBD: {peer_runs}.", ""]
    lines += ["| boxes | ms/step, ours | ms/step, peer | smallest gap, ours | smallest gap, peer | sunk, ours | "
              "sunk, peer |", "|---:|---:|---:|---:|---:|---:|---:|"]
    for r, p in zip(rows, peer_runs["rows"]):
        lines.append(f"| {r['bodies']} | {r['on']['ms_median']:.3g} | {p['ms_median']:.3g} | "
                     f"{gap(r['on'], scaling['steps'])} | {gap(p, scaling['steps'])} | {1e3 * r['on']['sunk']:.2f} mm | "
                     f"{1e3 * p['sunk']:.2f} mm |")
    s = peer_runs["setup"]
    return lines + ["", growth("The peer's", [(p["bodies"], p["ms_median"]) for p in peer_runs["rows"]]), "",
                    f"The peer: Newton {s['newton']}'s VBD with self-contact (Warp {s['warp']}, on the {s['device']}), "
                    f"the same boxes, steps, gravity, ground and contact distance; each step {s['substeps']} sub-steps "
                    f"of {s['iterations']} iterations (its softbody_gift example's), contact a penalty of "
                    f"{s['contact_stiffness']:g} N/m closer than the distance (ours: a barrier), a vertex touching the "
                    f"ground {1e3 * s['particle_radius']:g} mm above it (ours: at it). Its elasticity is neo-Hookean "
                    "with our E and nu's Lame parameters (ours: corotational), its damping the stiffness part of ours "
                    "alone (the mass part has no counterpart), its friction ours (0.3 between boxes, 0.4 on the "
                    "ground). app/bench/peer.py runs it.", ""]


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
