"""`main.py bench`: what accuracy costs in time.

Every scene first runs a reference: corotational BDF2 (second order) at a small time step
(dt_ref = the scene's dt / 8, 0.0025 s for the seed scenes), Newton iterated to 1e-10
(or until its velocity settles to 1e-8) with PCG at 1e-10, always in float64. Then every
variant runs from the same start for the same simulated time:

    corotational, Newton step and one-solve ("single") step, backward Euler, each with
        PCG 1e-4 at dt = 2, 1, 1/2, 1/4 x the scene's dt     (the dt axis)
        PCG 1e-2, 1e-3, 1e-6 at the scene's dt               (the tolerance axis)
    linear: the same, once (one Newton iteration solves a linear body exactly)
    both methods, one-solve step at the scene's dt:
        Jacobi iteration at 10, 30, 100 iterations           (matrix-free, fem.implicit)
        direct sparse solvers                                (assembled and factorised, app.bench.direct):
            the fastest installed (MKL PARDISO with the fast-direct extra), its analysis of the
            pattern made once and the matrix refactorised every step, and SuperLU, from
            scratch every step (the coursework's way)
    BDF2 (the integrator axis): corotational Newton and one-solve steps, and linear, over the
        dt axis at PCG 1e-4 (its tolerances and solvers would repeat backward Euler's)

A variant's error is its RMS position distance to the reference at checkpoint times
that every dt divides. The reference has an error of its own, C dt_ref^p with p = 2 for
BDF2 where dt_ref resolves the motion. Two more runs, at 2 and 4 dt_ref, measure p: they
differ from each other 2^p times as much as the first differs from the reference. The
reference's floor, its own error, is that first difference over 2^p - 1 (3 for p = 2),
p taken at most 2 and at least 1/2 (ground contact, an impulsive start or a torsional
wave slow it down on some scenes). The error axis bottoms out there: a measured error is
the true one give or take the floor, so a variant meets the error goal only when its
error plus the floor does. (The backward-Euler reference this replaced was first order:
its floor, as large as its distance to the run at 2 dt_ref, came close to the smallest
errors of the dt axis on the spinning bars.) Each integrator's observed order is the slope
of log error against log dt over its dt axis: about 1 for backward Euler, 2 for BDF2
where dt resolves the motion.

A variant's cost is the wall time of a step, measured after warm-up (Taichi compiles
its kernels on first use), and the wall time per simulated second (ms per step / dt),
which compares runs at different dt.
Outputs: results.md (tables), results.json (every number), accuracy_vs_time.png; with --docs,
the pages in docs/ instead: benchmark.md, benchmark.json (from which `main.py figures` redraws
the plot) and accuracy_vs_time.png with its numbers in accuracy_vs_time.json.

The parts, in the order a run goes through them:

    plan.py         what to run: the plans, the variants, the reference's settings, the scenes
    measure.py      running them: a variant, the reference, a scene, the preconditioners, the machine
    conclusions.py  what the rows say: errors against the reference, the goal, the headline
    report.py       the files: results.md (tables, targets), results.json, and the plot (plot.py)
    direct.py       the direct baseline, an assembled sparse solver outside the engine
    startup.py      what a user waits before the first step
    contact.py      the pile from 5 to 40 boxes beside a peer, Newton's VBD (peer.py, run in a Python
                    that has it); how close the bodies came (gaps.py); their rows (contact_report.py)

`main.py bench` itself is app/commands/bench.py.
"""
