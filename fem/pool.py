"""Kernels compile once per process: a Simulation borrows its Taichi fields from here.

Taichi compiles a kernel once for every object whose fields it reads: a Simulation
with fields of its own would compile the whole step again, seconds before its first
step. So a Simulation borrows a set of `Parts` (Model, ImplicitSolver, Measure and two
States) sized to a `Capacity` and compiled for its `Switches`, and gives them back
when it is dropped; the next Simulation with the same effects and a mesh of about the
same size reuses them, kernels already compiled. The same sizes in a later process
also find Taichi's offline cache, so a warm start compiles nothing.

A Simulation's parts belong to it while it lives: keep the Simulation, not its model.
"""

import weakref
from collections import defaultdict
from dataclasses import dataclass

import taichi as ti

from fem.coarse import Patches
from fem.implicit.broad_phase import BroadPhase
from fem.implicit.contact import Contact
from fem.implicit.effects import Effects
from fem.implicit.elasticity import Elasticity
from fem.implicit.energy_momentum import EnergyMomentum
from fem.implicit.islands import Islands
from fem.implicit.linear import LinearSolver
from fem.implicit.newton import Newton
from fem.implicit.potential import IncrementalPotential
from fem.implicit.preconditioner import Preconditioner
from fem.implicit.rotations import Rotations
from fem.implicit.safeguards import Safeguards
from fem.implicit.sleep import Sleep
from fem.implicit.solver import ImplicitSolver, Switches
from fem.measure import Measure
from fem.model import Capacity, Model, State

_idle = defaultdict(list)          # (Capacity, Switches) -> Parts nobody uses
_runtime = [None]                  # the Taichi runtime their fields live in
made = {"parts": 0}                # how many Parts this process has made (tests count compilations with it)


@dataclass
class Parts:
    model: Model
    solver: ImplicitSolver
    measure: Measure
    states: tuple


def borrow(owner, arrays, effects, settings):
    """Parts for a scene's model arrays (fem.builder.model_arrays), Effects and
    SolverSettings, loaded with them; they go back to the pool when `owner` is
    garbage-collected."""
    bodies, X, T, mass, free = arrays
    if _runtime[0] is not ti.lang.impl.get_runtime():     # Taichi restarted: every idle field is gone
        clear()
    capacity = Capacity.fitting(len(X), len(T), len(bodies))
    key = (capacity, Switches.of(effects, len(X), len(T), bool((free == 0).any()), bodies, settings.dt))
    parts = _idle[key].pop() if _idle[key] else make(*key)
    parts.model.load(*arrays)
    parts.solver.load(effects, settings)
    parts.measure.load(effects.gravity)
    weakref.finalize(owner, give_back, key, parts, _runtime[0])
    return parts


def give_back(key, parts, runtime):
    if runtime is _runtime[0]:                 # fields made before a restart are not kept
        _idle[key].append(parts)


def make(capacity, switches):
    model = Model(capacity)
    solver = ImplicitSolver(model, switches)
    made["parts"] += 1
    return Parts(model, solver, Measure(model, solver.rotations.quaternions, switches, solver.effects),
                 (State(capacity.vertices), State(capacity.vertices)))


def compiled_kernels():
    """How many kernels Taichi has compiled (or loaded from its offline cache) in this
    process for the engine: one per kernel and per set of parts it ran on."""
    classes = (Model, ImplicitSolver, Sleep, Rotations, Elasticity, Effects, Contact, BroadPhase, Islands,
               IncrementalPotential, Preconditioner, LinearSolver, Newton, Safeguards, EnergyMomentum, Measure, Patches)
    kernels = [f for c in classes for f in vars(c).values() if hasattr(f, "_primal")]
    return sum(len(k._primal.compiled_kernels) for k in kernels)


def clear():
    """Forget every idle part: Taichi restarted (fem.init, ti.init), their fields are gone.
    `borrow` notices a restart by the runtime's identity; fem.runtime need not tell the pool."""
    _idle.clear()
    _runtime[0] = ti.lang.impl.get_runtime()
