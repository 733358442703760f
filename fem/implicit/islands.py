"""Newton's line search where contact couples bodies (fem/implicit/newton.py, contact.py).

Without contact E is a sum of independent E_b and every body searches alone. Contact pairs
couple the bodies they join, so the bodies of one island (joined through candidate pairs,
BroadPhase.find_islands) share one step and one Armijo test on their summed E; bodies of
different islands still search alone.

A change of E within its round-off (Newton.body_resolution) cannot tell a better trial from a
worse one: near the answer a sticking contact's friction changes E by less than that (float32),
and a search that took such trials on E alone wandered (the 20-box pile's gradient rose and fell
tenfold for 30 iterations). There the trial's own slope g(a) . d decides: along a quadratic, E(a)
<= E(0) + ARMIJO a g(0) . d exactly when g(a) . d <= (1 - 2 ARMIJO) |g(0) . d|. The pile, f32, 60
steps: 13 -> 2 unconverged, 19.3 -> 14.4 Newton iterations a step (f64: the same steps, E resolves).

Fields (bodies of the capacity):
    island_sums (bodies, 6)   float64 sums over an island's bodies (indexed by its lowest id)
    trial_slope (bodies,)     g(a) . d_b at the trial iterate, J
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
        self.island_sums = ti.Vector.field(6, ti.f64, model.capacity.bodies)
        self.trial_slope = ti.field(ti.f64, model.capacity.bodies)
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
            self.island_sums[b] = ti.Vector.zero(ti.f64, 6)
            self.island_limit[b] = 1.0
        ti.loop_config(serialize=True)
        for b in range(self.model.body_count[None]):  # slope, resolution, unconverged bodies
            unconverged = gradient[b] > tolerance * tolerance * scale[b] + floor[b] + self.newton.effects.round_off(b)
            self.island_sums[island[b]] += ti.Vector([self.newton.body_slope[b], self.newton.body_resolution[b],
                                                      ti.cast(unconverged, ti.f64), 0.0, 0.0, 0.0])
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
    def armijo(self, h):
        """Newton.armijo where contact couples the bodies: E is no longer a sum of independent E_b, so
        the bodies of one island (joined by contact pairs, Contact.find_islands) share one step
        and one test on their summed E (those that do not search keep their iterate, and a pair's
        terms count once), or on their summed slope where E changed within its round-off. Returns how
        many bodies still search."""
        E, island = ti.static(self.newton.potential.body_E, self.contact.island)
        newton = self.newton
        newton.sleep.sums.reduce(self.slope_at_trial, self.store_slope, h)
        ti.loop_config(serialize=True)
        for b in range(self.model.body_count[None]):
            self.island_sums[b] = ti.Vector.zero(ti.f64, 6)
        ti.loop_config(serialize=True)
        for b in range(self.model.body_count[None]):   # E_new, E_accepted, resolution, slope, a, trial slope
            on = ti.cast(newton.searching[b], ti.f64)
            self.island_sums[island[b]] += ti.Vector([E[b], newton.body_E_accepted[b], newton.body_resolution[b],
                                                      newton.body_slope[b] * on, 0.0, self.trial_slope[b] * on])
            if newton.searching[b]:
                self.island_sums[island[b]][4] = newton.body_step[b]
        left = 0
        ti.loop_config(serialize=True)
        for b in range(self.model.body_count[None]):
            if newton.searching[b]:
                s = self.island_sums[island[b]]
                descent = s[0] <= s[1] + ARMIJO * s[4] * s[3]
                if not descent and s[0] <= s[1] + s[2]:     # within E's round-off: the slope tells
                    descent = s[5] <= -(1.0 - 2.0 * ARMIJO) * s[3]
                if descent:
                    newton.searching[b] = 0
                else:
                    newton.body_step[b] *= 0.5
                    left += 1
        return left

    @ti.func
    def slope_at_trial(self, i, b, data: ti.template()):
        """Vertex i's share of g(a) . d_b at the trial iterate (`vertex_gradient`'s -grad E there)."""
        p = self.newton.potential
        p.vertex_gradient(i, b, (p.x, p.v0, p.v, data, 0))
        s = -self.newton.effects.filtered(i, p.rhs[i]).dot(self.newton.linear.solution[i])
        return ti.Vector([ti.cast(s, ti.f64), 0, 0, 0, 0, 0, 0, 0, 0, 0], ti.f64)

    @ti.func
    def store_slope(self, b, total, data: ti.template()):
        self.trial_slope[b] = total[0]
