"""Newton's line search where contact couples bodies (fem/implicit/newton.py, contact.py).

Without contact E is a sum of independent E_b and every body searches alone. Contact pairs
couple the bodies they join, so the bodies of one island (joined through candidate pairs,
BroadPhase.find_islands) share one step and one Armijo test on their summed E; bodies of
different islands still search alone.

Fields (bodies of the capacity):
    island_sums (bodies, 4)   float64 sums over an island's bodies (indexed by its lowest id)
    island_limit (bodies,)    the largest step of an island's line search: the least of its bodies'
                              (Contact.body_limit), indexed by its lowest id
"""

import taichi as ti

from fem.implicit.newton import ARMIJO


@ti.data_oriented
class Islands:
    """The island-wise start and Armijo test of `newton`'s line search, islands from `contact`."""

    def __init__(self, model, newton, contact):
        self.model, self.newton, self.contact = model, newton, contact
        self.island_sums = ti.Vector.field(4, ti.f64, model.capacity.bodies)
        self.island_limit = ti.field(float, model.capacity.bodies)

    @ti.func
    def search_together(self, tolerance):
        """Newton.start_search where contact couples the bodies: the bodies of one island
        (BroadPhase.find_islands) search together, from the island's own step bound, where their summed slope
        descends by more than the round-off of their summed E or one of them has not converged.
        Returns how many bodies search."""
        island, gradient = ti.static(self.contact.island, self.newton.potential.body_gradient)
        scale, floor = ti.static(self.newton.potential.body_scale, self.newton.potential.body_floor)
        ti.loop_config(serialize=True)
        for b in range(self.model.body_count[None]):
            self.island_sums[b] = ti.Vector.zero(ti.f64, 4)
            self.island_limit[b] = 1.0
        ti.loop_config(serialize=True)
        for b in range(self.model.body_count[None]):  # slope, resolution, unconverged bodies
            unconverged = gradient[b] > tolerance * tolerance * scale[b] + floor[b] + self.newton.effects.round_off(b)
            self.island_sums[island[b]] += ti.Vector([self.newton.body_slope[b], self.newton.body_resolution[b],
                                                      ti.cast(unconverged, ti.f64), 0.0])
            ti.atomic_min(self.island_limit[island[b]], self.contact.body_limit[b])
        count = 0
        ti.loop_config(serialize=True)
        for b in range(self.model.body_count[None]):
            s = self.island_sums[island[b]]
            self.newton.searching[b] = int(s[0] < 0 and (-s[0] > s[1] or s[2] > 0))
            self.newton.body_step[b] = self.newton.searching[b] * self.island_limit[island[b]]
            count += self.newton.searching[b]
        return count

    @ti.func
    def armijo(self):
        """Newton.armijo where contact couples the bodies: E is no longer a sum of independent E_b, so
        the bodies of one island (joined by contact pairs, Contact.find_islands) share one step
        and one test on their summed E (those that do not search keep their iterate, and a pair's
        terms count once). Returns how many bodies still search."""
        E, island = ti.static(self.newton.potential.body_E, self.contact.island)
        ti.loop_config(serialize=True)
        for b in range(self.model.body_count[None]):
            self.island_sums[b] = ti.Vector.zero(ti.f64, 4)
        ti.loop_config(serialize=True)
        for b in range(self.model.body_count[None]):   # E_new, E_accepted + resolution, slope, a
            k = island[b]
            self.island_sums[k] += ti.Vector([E[b], self.newton.body_E_accepted[b] + self.newton.body_resolution[b],
                                              self.newton.body_slope[b] * self.newton.searching[b], 0.0])
            if self.newton.searching[b]:
                self.island_sums[k][3] = self.newton.body_step[b]
        left = 0
        ti.loop_config(serialize=True)
        for b in range(self.model.body_count[None]):
            if self.newton.searching[b]:
                s = self.island_sums[island[b]]
                if s[0] <= s[1] + ARMIJO * s[3] * s[2]:
                    self.newton.searching[b] = 0
                else:
                    self.newton.body_step[b] *= 0.5
                    left += 1
        return left
