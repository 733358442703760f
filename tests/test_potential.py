"""The incremental potential: its energy pass leaves the gradient of the iterate it evaluates."""

import numpy as np
from test_newton import spinning_incompressible

import fem


def test_the_energy_pass_leaves_the_gradient_of_its_iterate(f64):
    """The line search's energy pass also stores the tet terms of grad E (a trial it accepts
    needs them next): the same numbers as the gradient's own pass, stiffness damping included."""
    sim = fem.Simulation(spinning_incompressible(), integrator="backward-euler")   # its h is dt
    for _ in range(2):
        sim.step()
    potential, corner, dt = sim.solver.potential, sim.solver.elasticity.corner, sim.settings.dt
    used = 4 * sim.model.n_tets          # the pool's field is larger: past this, another scene's numbers
    potential.energy(potential.v0, potential.x, potential.v, dt, 1)
    fused = corner.to_numpy()[:used]
    potential.gradient_corners(potential.x, potential.v, dt, 1)
    alone = corner.to_numpy()[:used]
    potential.gradient_corners(potential.x, potential.v, dt, 0)
    undamped = corner.to_numpy()[:used]
    assert np.abs(alone - undamped).max() > 1e-3 * np.abs(alone).max()     # the damping term counts
    # two kernels, compiled apart: their rounding differs (near-incompressible: lambda = 5000 mu)
    np.testing.assert_allclose(fused, alone, rtol=0, atol=1e-9 * np.abs(alone).max())
