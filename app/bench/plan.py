"""What the benchmark runs: the plans, the variants of a scene, the reference's settings, the scenes."""

from dataclasses import dataclass
from pathlib import Path

import numpy as np

import scenes
from app.bench import direct
from app.bench.order import INTEGRATORS   # {"backward-euler": "backward Euler", "bdf2": "BDF2", ...}: the tables' names
SECOND_ORDER = ("bdf2", "trapezoidal")    # each compared with backward Euler
from assets.generators import box
from fem.scene import Body, Effects, Initial, Material, Scene, Selection, SolverSettings, place_mesh

STEPS = {"corotational": ("newton", "single"), "linear": ("newton",)}   # a linear body's step is exact either way
DT_FACTORS = (2, 1, 0.5, 0.25)   # the dt axis, times the scene's dt (0.04 to 0.005 s for the seed scenes)
PCG_TOLERANCES = (1e-2, 1e-3, 1e-4, 1e-6)
BDF2_TOLERANCES = (1e-3,)       # BDF2's corotational steps at the scene's dt: what a looser tolerance buys
JACOBI_ITERATIONS = (10, 30, 100)
BASELINE_TOLERANCE = 1e-4        # the scenes' default PCG tolerance: the dt axis and the comparisons use it
DIRECT_TOLERANCE = 1e-3          # the matrix-free step set against the direct baseline: as accurate as an
                                 # exact solve of the same step (the 1e-3 and 1e-6 rows' errors agree)
DIRECT_TARGET = 30               # issue 12: the matrix-free step at least 30 times faster than the fastest direct one
TARGET_SCENE = "box50k"          # the scene of the speed targets (issue 12), the direct one's among them
MAX_ITERATIONS = 1000            # PCG: the tolerance, not the cap, ends a solve
REFERENCE_REFINEMENT = 8         # dt_ref = the scene's dt / 8
# The reference: BDF2, Newton to a gradient of 1e-10 of the step's terms. Where the line search finds no
# more decrease (up to half the steps of a turning scene stall near 1e-7, each iteration trying 13 step
# lengths), it stops once an iteration changes the velocity by under 1e-8 of its size, or after 15
# iterations; its rotations are the engine's own, certified to 1e-12 rad in f64 (SVD where they cannot be).
# Against 1e-10, 50 iterations and SVD rotations throughout, the positions at 2 s move by 3e-7 of the scene
# size on torsion and 1e-7 on cube86, far under each floor (cube86's reference: 7 s instead of 42).
REFERENCE_SETTINGS = dict(step="newton", integrator="bdf2", method="pcg", tolerance=1e-10, newton_tolerance=1e-8,
                          max_newton=15, rotations="iterative")
REFERENCE_RUNS = (1, 2, 4)       # the reference at dt_ref, and its twins at 2 and 4 dt_ref: its own order
REFERENCE_ORDER = 2              # BDF2's: the reference's own observed order counts for at most this (more is luck)
MIN_REFERENCE_ORDER = 0.5        # and at least this (a floor 2.4 times its distance to the run at 2 dt_ref):
                                 # slower, its runs say little about its error (the bunny on the ground: 0.3)
ERROR_GOAL = 1e-2                # accurate enough: RMS position error under 1 % of the bounding-box diagonal
MIN_TIMED_STEPS = 3              # a variant stopped by the time budget still times this many steps
BOXES = {"box80": 2, "box1k": 5, "box10k": 10, "box50k": 17}   # 2 x 1 x 1 m bar, 2k x k x k cells


@dataclass
class Plan:
    """How much to measure."""

    scenes: list          # built-in names, scene files or BOXES names
    checkpoints: tuple    # s: positions are compared with the reference at these times (rounded to a
                          # multiple of the largest dt); the last ends a run
    warmup_steps: int     # first steps of every run left out of the timings
    budget_s: float       # a variant whose run would take longer stops early (the reference never does)
    startup: str = ""     # a scene whose start-up and resting cost are measured too ("": none)
    stiff: str = ""       # a BOXES bar also compared, made STIFF, on preconditioners alone ("": none)
    preconditioner_steps: int = 30   # steps of each preconditioner in their comparison
    profile: str = ""     # a BOXES bar whose one-solve and default steps get a kernel profile ("": none)
    contact: str = ""     # a scene with contact whose cost is measured, with contact and without ("": none)
    contact_steps: tuple = (40, 20)  # its steps before the timed ones (the bodies land), and the timed ones
    contact_sizes: tuple = ()        # piles of these many boxes measured the same steps, beside the peer's
                                     # (app/bench/contact.py)
    quick: bool = False   # too little for the full run's conclusions (frontier, targets, costs under the
                          # timing noise): its report says what it measured and leaves those out
    startup_breakdown: tuple = ()    # (scene, (simulate's options, ...)) whose warm start is broken down


FULL_CHECKPOINTS = (0.4, 1.0, 2.0)   # s: the full plan's; a run to 2 s turns the bars by 4 rad
FULL_BUDGET_S = 120.0


def full_plan():
    """Every built-in scene without contact, and the three larger bars. A scene with contact (two_boxes) is
    left out: its steps are dominated by the contact pairs' Newton iterations, not by what the dt, integrator
    and solver axes compare, and it alone would take longer than all the others together."""
    elastic = [name for name in scenes.builtin_scenes() if scenes.load_scene(name).effects.contact is None]
    return Plan([*elastic, "box1k", "box10k", "box50k"], FULL_CHECKPOINTS, 2, FULL_BUDGET_S, "epcot",
                "box50k", profile="box50k", contact=PILE, contact_sizes=(5, 10, 20, 40),
                startup_breakdown=startup_breakdown())


def startup_breakdown():
    """Every built-in scene and the pile as `simulate` starts them, and epcot with each switch that
    compiles kernels of its own (contact, float64, the kernel profiler)."""
    starts = [(name, ()) for name in scenes.builtin_scenes()] + [(PILE, ())]
    return tuple(starts + [("epcot", ("--contact",)), ("epcot", ("--precision", "f64")), ("epcot", ("--profile",))])


PILE = str(Path(__file__).resolve().parents[2] / "examples" / "pile.toml")   # 20 boxes falling onto each other
QUICK = Plan(["cube86", "box1k"], (0.4, 1.0), 2, 20.0, quick=True)
# measured: 5.9 minutes, the machine's 2 cores shared with other work (load average 4.1 at the start)
QUICK_DURATION = "about 6 minutes on 2 cores shared with other work (load average 4), more on a busier machine"
TEST = Plan(["box80"], (0.08, 0.2), 2, 10.0, stiff="box80", preconditioner_steps=3,   # tests: seconds
            profile="box80", contact="two_boxes", contact_steps=(20, 5))


@dataclass(frozen=True)
class Variant:
    method: str               # "linear" | "corotational"
    solver: str               # "reference" | "pcg" | "jacobi" | "direct"
    step: str = "single"      # "newton" | "single"; a linear body takes the same step either way
    dt_factor: float = 1      # its dt: this times the scene's dt
    tolerance: float = 0.0    # pcg, reference
    iterations: int = 0       # jacobi
    backend: str = ""         # direct: a name in app.bench.direct.BACKENDS
    integrator: str = "backward-euler"   # a name in fem.scene.INTEGRATORS

    @property
    def name(self):
        """What it integrates and solves with, e.g. "corotational BDF2 PCG 1e-4"."""
        if self.solver == "reference":
            k = round(self.dt_factor * REFERENCE_REFINEMENT)
            return f"{INTEGRATORS[self.integrator]} reference" + (f" at {k} dt_ref" if k > 1 else "")
        if self.solver == "direct":
            return f"{self.method} {INTEGRATORS[self.integrator]} direct ({direct_role(self.backend)})"
        setting = {"pcg": f"PCG {sci(self.tolerance)}", "jacobi": f"Jacobi x{self.iterations}"}[self.solver]
        return f"{self.method} {INTEGRATORS[self.integrator]} {setting}"

    def dt(self, scene_dt):
        return self.dt_factor * scene_dt

    @property
    def step_name(self):
        return "exact" if self.method == "linear" else {"newton": "Newton", "single": "single"}[self.step]


REFERENCES = [Variant("corotational", "reference", "newton", k / REFERENCE_REFINEMENT, REFERENCE_SETTINGS["tolerance"],
                      integrator=REFERENCE_SETTINGS["integrator"]) for k in REFERENCE_RUNS]


def direct_backends():
    """The direct baseline: the fastest solver installed, and SuperLU, the coursework's (once if they are one)."""
    return list(dict.fromkeys([direct.fastest_available(), "superlu"]))


def direct_role(backend):
    """'fastest: MKL PARDISO' or 'SuperLU, coursework-like'."""
    return "SuperLU, coursework-like" if backend == "superlu" else f"fastest: {direct.BACKENDS[backend].label}"


def variants():
    """Every variant but the references, in the order of the tables: backward Euler over every axis,
    then BDF2 over the dt axis and BDF2_TOLERANCES (its other solvers would repeat backward Euler's), then
    the trapezoidal rule's corotational steps over the dt axis."""
    out = []
    for method, steps in STEPS.items():
        for step in steps:
            out += [Variant(method, "pcg", step, f, BASELINE_TOLERANCE) for f in DT_FACTORS]
            out += [Variant(method, "pcg", step, 1, tol) for tol in PCG_TOLERANCES if tol != BASELINE_TOLERANCE]
        out += [Variant(method, "jacobi", iterations=k) for k in JACOBI_ITERATIONS]
        out += [Variant(method, "direct", backend=name) for name in direct_backends()]
    for method, steps in STEPS.items():
        out += [Variant(method, "pcg", step, f, BASELINE_TOLERANCE, integrator="bdf2") for step in steps
                for f in DT_FACTORS]
        if method == "corotational":
            out += [Variant(method, "pcg", step, 1, tol, integrator="bdf2") for step in steps for tol in BDF2_TOLERANCES]
    out += [Variant("corotational", "pcg", step, f, BASELINE_TOLERANCE, integrator="trapezoidal")
            for step in STEPS["corotational"] for f in DT_FACTORS]
    return out


def sci(x):
    """1e-04 -> 1e-4."""
    return f"{x:.0e}".replace("e-0", "e-").replace("e+0", "e")


def step_name(row):
    return Variant(row["method"], row["solver"], row["step"]).step_name


def integrator_of(row):
    """A row's integrator (rows from before the integrator axis are backward Euler's)."""
    return row.get("integrator", "backward-euler")


# ---------------------------------------------------------------- scenes

def box_scene(name, k):
    """A 2 x 1 x 1 m rubber bar of 2k x k x k cells (10 k^3 tets), spinning about y at 2 rad/s and
    twisting about its long axis: it turns by 4 rad in 2 s, so linear FEM visibly fails."""
    mesh = place_mesh(box((2.0, 1.0, 1.0), (2 * k, k, k)))
    scene = Scene(name, [Body("bar", mesh, Material(E=1e5, nu=0.3, density=1000.0))],
                  description="A 2 x 1 x 1 m rubber bar spinning about y and twisting about its long axis.",
                  effects=Effects(beta=0.002), solver=SolverSettings(dt=0.02))
    scene.initial = [Initial(Selection(None), "spin", (np.array([0.0, 1.0, 0.0]), 2.0)),
                     Initial(Selection(None), "twist", (np.array([1.0, 0.0, 0.0]), 6.0))]
    return scene


def make_scene(ref):
    return box_scene(ref, BOXES[ref]) if ref in BOXES else scenes.load_scene(ref)


def checkpoint_times(plan, dt):
    """The plan's checkpoints rounded to multiples of the largest dt, so that every dt divides them."""
    period = max(DT_FACTORS) * dt
    return [period * max(1, round(t / period)) for t in plan.checkpoints]
