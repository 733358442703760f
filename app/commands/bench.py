"""`main.py bench`: what accuracy costs in time, per scene, against a converged reference.

The benchmark's parts and what it measures: app/bench/.
"""

import os
import sys
import time
from dataclasses import replace
from pathlib import Path

import fem
from app import device, outputs
from app.bench import contact, startup
from app.bench.conclusions import headline
from app.bench.measure import (STIFF, compare_preconditioners, contact_cost, kernel_profile, machine,
                               measure_scene, stiff_bar)
from app.bench.plan import QUICK, REFERENCES, full_plan, variants
from app.bench.report import DOCS, DOCS_FILES, RESULT_FILES, quick_scope, write
from app.files import check_output, refuse_overwrite
from app.progress import Progress
from fem.errors import FemError


def destination(args):
    """(folder, file names) the results go to: --out, or with --docs the pages in docs/, which
    it replaces (they are under version control) and which only the full plan may write."""
    if not args.docs:
        refuse_overwrite(args.out, args.overwrite)
        outputs.remove_stale_temporaries(args.out)     # what a killed run left
        return Path(args.out), RESULT_FILES
    if args.quick or args.scenes:
        raise FemError(f"--docs records the full benchmark; drop {'--quick' if args.quick else '--scenes'}")
    check_output(DOCS, "--docs", "folder")
    return DOCS, DOCS_FILES


def run(args, plan=None):
    """main.py bench; `plan` (for tests) replaces the quick or full plan."""
    folder, names = destination(args)
    backend = device.start(args)["backend"]
    plan = plan or (QUICK if args.quick else full_plan())
    if args.scenes:
        plan = replace(plan, scenes=args.scenes)
    info = machine(backend, args.precision)
    began = time.perf_counter()
    scenes = []
    runs = len(REFERENCES) + len(variants())
    with Progress(len(plan.scenes) * runs, "run", "bench") as progress:
        for ref in plan.scenes:
            scenes.append(measure_scene(ref, plan, args, progress))
    lines, numbers = headline(scenes, quick=plan.quick)
    info["bench_minutes"] = (time.perf_counter() - began) / 60
    results = {"machine": info, "plan": vars(plan), "headline": lines, "headline_numbers": numbers,
               "scenes": scenes}
    if plan.stiff:
        print(f"bench: preconditioners on the stiff {plan.stiff}", file=sys.stderr)
        stiff = compare_preconditioners(stiff_bar(plan.stiff), plan.preconditioner_steps)
        results["stiff"] = {"name": plan.stiff, **STIFF, "preconditioners": stiff}
    if plan.startup:
        print(f"bench: start-up and resting cost of {plan.startup}", file=sys.stderr)
        results["startup"] = startup.measure(plan.startup)
        results["startup"]["resting_ms"] = startup.resting_cost(plan.startup)
        results["startup"].update(startup.view_seconds(plan.startup))    # {} without a display
    if plan.startup_breakdown:
        print(f"bench: where a warm start goes, {len(plan.startup_breakdown)} starts", file=sys.stderr)
        results.setdefault("startup", {})["breakdown"] = [startup.breakdown(scene, options)
                                                          for scene, options in plan.startup_breakdown]
    if plan.profile:
        print(f"bench: kernel profile of {plan.profile}", file=sys.stderr)
        results["profile"] = kernel_profile(plan.profile, args, info)    # last: it restarts Taichi
    if plan.contact:
        print(f"bench: contact's cost on {Path(plan.contact).stem}", file=sys.stderr)
        results["contact"] = contact_cost(plan.contact, plan, args, info)      # with the profiler on too
    if plan.contact_sizes:
        print(f"bench: piles of {', '.join(map(str, plan.contact_sizes))} boxes, beside the peer", file=sys.stderr)
        fem.init(args.arch, args.precision, debug=args.debug)     # the profiler off: the times a user sees
        results["contact"]["scaling"] = contact.scaling(plan.contact_sizes, *plan.contact_steps,
                                                        os.environ.get("PEER_PYTHON"))
    write(results, folder, names)
    print("\n".join(([quick_scope(results)] if plan.quick else []) + lines))
    print(f"wrote {folder / names['md']}, {names['json']}, {names['plot']} ({info['bench_minutes']:.1f} min)")
    return 0
