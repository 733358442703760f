"""The broad phase of contact: which surface vertices and triangles, and which surface edges, may
be close (fem/implicit/contact.py).

A pair is a candidate where it is closer than the search radius r plus m_a + m_b, the most each side's
points may move in the line search to come (`motion`; 0 for a search at rest): a box resting in a pile
looks no further than r although a falling box beside it moves 4.5 cm. Each side's box grows by
r / 2 + its own m, and a pair is reported in the first grid cell that both grown boxes share.

Two uniform grids hashed into `buckets` buckets (Teschner et al. 2003), one of the triangles and one of
the edges, rebuilt at every new search (`near_pairs` filters the candidates of a wider search instead
while they still hold: a Verlet list). A cell is at least as wide as every triangle's grown box, so
each triangle and edge lies in at most 8 cells, and a vertex or an edge looks in the (at most 8) its
own grown box touches: O(n) work for n surface vertices, edges and triangles. An edge e looks only at
the edges f > e of each bucket, which a search on one thread lists in order (`first_after`).

Fields (n vertices, t triangles of the capacity):
    cell ()                 the cells' width, m
    buckets ()              the buckets in use: a power of two, 2 a triangle or more
    triangle_grid, edge_grid  the grids (`Grid`)
    motion (n,)             how far each surface vertex may move, m (times the search's `scale`)
    island (bodies,)        the lowest body id joined to a body by candidate pairs
    candidates (pairs,)     the pairs of the last search made wider than asked (`near_pairs`)
    candidate_count ()      how many
    searched_x (n, 3)       where the surface was then, m
    searched_motion (n,)    the motion that search allowed each surface vertex, m
    searched_radius ()      that search's radius, m (-1: none to use)
    moved ()                the most a surface vertex moved past what the candidates allow, m (> 0: stale)
"""

import taichi as ti


# A search for candidate pairs looks this many contact distances further than asked, and later searches filter
# its pairs while the surface moved less than half that: the pile's 14 Newton iterations a step searched 14
# times (2.3 ms each, 25 % of its step), now about 2 (a Verlet list)
MARGIN = 1.0
# ... and searches again, fewer candidates, once a search would be this many times narrower: filtering the pile's
# 1,900 candidates of a step's first search costs 0.2 ms, a new search 3 to 4 ms (2: 1.5 ms a step more)
TOO_MANY = 4.0


def next_power_of_two(n):
    return 1 << max(10, (n - 1).bit_length())


@ti.func
def closest_weights(p, a, b, c):
    """Barycentric weights (w0, w1, w2) of the point of triangle (a, b, c) closest to p
    (Ericson, Real-Time Collision Detection, 5.1.5)."""
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = ab.dot(ap), ac.dot(ap)
    bp, cp = p - b, p - c
    d3, d4 = ab.dot(bp), ac.dot(bp)
    d5, d6 = ab.dot(cp), ac.dot(cp)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    w = ti.Vector([0.0, 0.0, 0.0])
    if d1 <= 0 and d2 <= 0:                                   # vertex region a
        w = ti.Vector([1.0, 0.0, 0.0])
    elif d3 >= 0 and d4 <= d3:                                # vertex region b
        w = ti.Vector([0.0, 1.0, 0.0])
    elif d6 >= 0 and d5 <= d6:                                # vertex region c
        w = ti.Vector([0.0, 0.0, 1.0])
    elif vc <= 0 and d1 >= 0 and d3 <= 0:                     # edge ab
        s = d1 / (d1 - d3)
        w = ti.Vector([1.0 - s, s, 0.0])
    elif vb <= 0 and d2 >= 0 and d6 <= 0:                     # edge ac
        s = d2 / (d2 - d6)
        w = ti.Vector([1.0 - s, 0.0, s])
    elif va <= 0 and d4 - d3 >= 0 and d5 - d6 >= 0:           # edge bc
        s = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        w = ti.Vector([0.0, 1.0 - s, s])
    else:                                                     # the face
        total = va + vb + vc
        w = ti.Vector([va / total, vb / total, vc / total])
    return w


@ti.func
def segment_weights(a0, a1, b0, b1):
    """(s, t): the closest points a0 + s (a1 - a0) and b0 + t (b1 - b0) of two segments
    (Ericson, Real-Time Collision Detection, 5.1.9); parallel ones take s = 0 or its clamp."""
    d1, d2, r = a1 - a0, b1 - b0, a0 - b0
    a, e, f = d1.dot(d1), d2.dot(d2), d2.dot(r)
    c, b = d1.dot(r), d1.dot(d2)
    denom = a * e - b * b
    s = 0.0
    if denom > 1e-6 * a * e:                                  # not parallel
        s = ti.min(ti.max((b * f - c * e) / denom, 0.0), 1.0)
    t = (b * s + f) / e
    if t < 0.0:
        t, s = 0.0, ti.min(ti.max(-c / a, 0.0), 1.0)
    elif t > 1.0:
        t, s = 1.0, ti.min(ti.max((b - c) / a, 0.0), 1.0)
    return s, t


@ti.data_oriented
@ti.data_oriented
class Grid:
    """Items (triangles or edges) in the buckets of a hashed uniform grid: each in every bucket its grown
    box touches, once (`BroadPhase.fill`)."""

    def __init__(self, size, items):
        self.count = ti.field(ti.i32, size)         # items per bucket, then a cursor while filling
        self.start = ti.field(ti.i32, size + 1)     # where each bucket's items start in `entries`
        self.entries = ti.field(ti.i32, 8 * items)  # the items of every bucket, bucket by bucket
        self.lowest = ti.Vector.field(3, ti.i32, items)   # each item's grown box, as its lowest and highest cells
        self.highest = ti.Vector.field(3, ti.i32, items)

    @ti.func
    def first_shared(self, k, c, lo):
        """Cell c is the first cell (lowest) that item k's box shares with a box whose lowest cell is lo."""
        return (c == ti.max(self.lowest[k], lo)).all() and (c <= self.highest[k]).all()


@ti.data_oriented
class BroadPhase:
    """The candidate pairs of `contact` (its triangles, surface and pair fields), and islands."""

    def __init__(self, model, contact, switches):
        t = 4 * model.capacity.tets
        self.model, self.contact = model, contact
        self.serial_vertices = switches.serial_vertices
        self.table_size = next_power_of_two(2 * t)
        self.cell = ti.field(float, ())
        self.buckets = ti.field(ti.i32, ())     # the table's buckets in use, a power of two
        self.triangle_grid = Grid(self.table_size, t)
        self.edge_grid = Grid(self.table_size, contact.edges.shape[0])
        self.island = ti.field(ti.i32, model.capacity.bodies)
        self.candidates = ti.Vector.field(2, ti.i32, contact.pair_capacity)
        self.candidate_count = ti.field(ti.i32, ())
        self.searched_x = ti.Vector.field(3, float, model.capacity.vertices)
        self.searched_motion = ti.field(float, model.capacity.vertices)
        self.motion = ti.field(float, model.capacity.vertices)
        self.searched_radius = ti.field(float, ())
        self.moved = ti.field(float, ())

    def forget(self):
        """A new surface: the candidates are none, and a table of 2 buckets a triangle."""
        self.searched_radius[None] = -1.0
        self.buckets[None] = min(self.table_size, next_power_of_two(2 * self.contact.triangle_count[None]))

    @ti.func
    def cell_of(self, p):
        return ti.floor(p / self.cell[None]).cast(ti.i32)

    @ti.func
    def bucket(self, c):
        """The table entry of grid cell c (a spatial hash, Teschner et al. 2003)."""
        h = (c[0] * 73856093) ^ (c[1] * 19349663) ^ (c[2] * 83492791)
        return h & (self.buckets[None] - 1)

    @ti.func
    def motion_of(self, i, scale):
        """How far surface vertex i may move in the search's step: scale * motion[i] (m)."""
        return scale * self.motion[i]

    @ti.func
    def triangle_motion(self, k, scale):
        t = self.contact.triangles[k]
        return ti.max(self.motion_of(t[0], scale), self.motion_of(t[1], scale), self.motion_of(t[2], scale))

    @ti.func
    def edge_motion(self, e, scale):
        ends = self.contact.edges[e]
        return ti.max(self.motion_of(ends[0], scale), self.motion_of(ends[1], scale))

    @ti.func
    def triangle_cells(self, x: ti.template(), k, grow):
        """The lowest and highest grid cells of triangle k's box grown by `grow`."""
        t = self.contact.triangles[k]
        lo = ti.min(x[t[0]], x[t[1]], x[t[2]]) - grow
        hi = ti.max(x[t[0]], x[t[1]], x[t[2]]) + grow
        return self.cell_of(lo), self.cell_of(hi)

    @ti.func
    def box_buckets(self, lo, hi):
        """The buckets of the (at most 8) cells of box [lo, hi], in loop order, -1 where the box has no such
        cell or an earlier one has the same bucket: each item goes into a bucket once."""
        out = ti.Vector([-1] * 8, ti.i32)
        for n in ti.static(range(8)):
            c = lo + ti.Vector([n // 4, n // 2 % 2, n % 2])
            if (c <= hi).all():
                out[n] = self.bucket(c)
                for m in ti.static(range(n)):
                    if out[m] == out[n]:
                        out[n] = -1
        return out

    @ti.func
    def find_pairs(self, x: ti.template(), radius, scale=0.0, on=1):
        """pairs <- every (surface vertex, triangle not containing it) and every (surface edge, edge
        sharing no vertex with it) closer than radius + m_a + m_b at x, m the most either side's
        points move (`motion_of`: scale * motion; none where scale = 0). Each side's box grows by
        radius / 2 + its m, and a pair is found in the first grid cell that both grown boxes share.
        on = 0: the loops run over nothing."""
        nt, ne = self.contact.triangle_count[None], self.contact.edge_count[None]
        half = 0.5 * radius
        self.cell[None] = 0.0
        ti.loop_config(serialize=self.serial_vertices)
        for k in range(nt * on):
            t = self.contact.triangles[k]
            size = ti.max(x[t[0]], x[t[1]], x[t[2]]) - ti.min(x[t[0]], x[t[1]], x[t[2]])
            ti.atomic_max(self.cell[None], size.max() + 2.0 * (half + self.triangle_motion(k, scale)))
        ti.loop_config(serialize=self.serial_vertices)
        for k in range(nt * on):
            lo, hi = self.triangle_cells(x, k, half + self.triangle_motion(k, scale))
            self.triangle_grid.lowest[k], self.triangle_grid.highest[k] = lo, hi
        ti.loop_config(serialize=self.serial_vertices)
        for e in range(ne * on):          # an edge's grown box lies in its triangles': at most 2 cells a side
            ends, grow = self.contact.edges[e], half + self.edge_motion(e, scale)
            a, b = x[ends[0]], x[ends[1]]
            self.edge_grid.lowest[e], self.edge_grid.highest[e] = \
                self.cell_of(ti.min(a, b) - grow), self.cell_of(ti.max(a, b) + grow)
        self.fill(self.triangle_grid, nt, on)
        self.fill(self.edge_grid, ne, on)
        if on:
            self.contact.pair_count[None], self.contact.overflow[None] = 0, 0
        ti.loop_config(serialize=self.serial_vertices)
        for s in range(self.contact.surface_count[None] * on):
            self.vertex_pairs(x, self.contact.surface[s], half, scale)
        ti.loop_config(serialize=self.serial_vertices)
        for e in range(self.contact.edge_count[None] * on):       # edge-edge: the pair (e, f), e < f, once
            self.edge_pairs(x, e, half, scale)
        ti.loop_config(serialize=True)
        for _ in range(on):
            self.contact.pair_count[None] = ti.min(self.contact.pair_count[None], ti.static(self.contact.pair_capacity))

    @ti.func
    def fill(self, grid: ti.template(), n, on):
        """grid's buckets <- its first n items, each in the bucket of every cell of its box (lowest to
        highest) once (on = 0: nothing)."""
        ti.loop_config(serialize=self.serial_vertices)
        for b in range(self.buckets[None] * on):
            grid.count[b] = 0
        ti.loop_config(serialize=self.serial_vertices)
        for k in range(n * on):
            cells = self.box_buckets(grid.lowest[k], grid.highest[k])
            for m in ti.static(range(8)):
                if cells[m] >= 0:
                    ti.atomic_add(grid.count[cells[m]], 1)
        ti.loop_config(serialize=True)
        for _ in range(on):
            total = 0
            for b in range(self.buckets[None]):
                grid.start[b] = total
                total += grid.count[b]
                grid.count[b] = 0
            grid.start[self.buckets[None]] = total
        ti.loop_config(serialize=self.serial_vertices)
        for k in range(n * on):
            cells = self.box_buckets(grid.lowest[k], grid.highest[k])
            for m in ti.static(range(8)):
                if cells[m] >= 0:
                    grid.entries[grid.start[cells[m]] + ti.atomic_add(grid.count[cells[m]], 1)] = k

    @ti.func
    def near_pairs(self, x: ti.template(), radius, scale=0.0):
        """pairs <- as find_pairs(x, radius, scale), the same pairs, taken from the candidates of an earlier
        search while they hold: it was made wider (radius R, motions M_i) and no surface vertex i has moved
        further since than R / 2 + M_i - radius / 2 - m_i (no pair came closer than it may); else, or where
        the earlier search was more than TOO_MANY times as wide as a new one would be, a search 2 MARGIN d_hat
        wider than radius makes new candidates. (One that overflowed is filtered too, and not reused: its pairs are
        all there is room for.)"""
        surface = ti.static(self.contact.surface)
        self.moved[None] = 0.0             # the most a vertex came past what the candidates allow (> 0: stale)
        wide, asked = 0.0, 0.0
        ti.loop_config(serialize=self.serial_vertices)
        for s in range(self.contact.surface_count[None]):
            i = surface[s]
            m = self.motion_of(i, scale)
            room = 0.5 * (self.searched_radius[None] - radius) + self.searched_motion[i] - m
            ti.atomic_max(self.moved[None], (x[i] - self.searched_x[i]).norm() - room)
            ti.atomic_max(wide, self.searched_motion[i])
            ti.atomic_max(asked, m)
        wider = radius + ti.static(2.0 * MARGIN) * self.contact.distance[None]
        stale = int(self.moved[None] > 0.0 or self.searched_radius[None] < 0.0 or        # a pair may have come closer
                    self.searched_radius[None] + 2.0 * wide > TOO_MANY * (wider + 2.0 * asked))   # too many to filter
        self.find_pairs(x, wider, scale, stale)
        ti.loop_config(serialize=self.serial_vertices)
        for q in range(self.contact.pair_count[None] * stale):
            self.candidates[q] = self.contact.pairs[q]
        ti.loop_config(serialize=self.serial_vertices)
        for s in range(self.contact.surface_count[None] * stale):
            i = surface[s]
            self.searched_x[i], self.searched_motion[i] = x[i], self.motion_of(i, scale)
        ti.loop_config(serialize=True)
        for _ in range(1):
            if stale:
                self.candidate_count[None] = self.contact.pair_count[None]
                self.searched_radius[None] = wider
                if self.contact.overflow[None]:               # some left out (the run warns): none to reuse
                    self.searched_radius[None] = -1.0
            self.contact.pair_count[None] = 0
            for q in range(self.candidate_count[None]):
                pair = self.candidates[q]
                if self.pair_distance(x, pair[0], pair[1]) < radius + self.pair_motion(pair, scale):
                    self.contact.pairs[self.contact.pair_count[None]] = pair
                    self.contact.pair_count[None] += 1

    @ti.func
    def pair_motion(self, pair, scale):
        """m_a + m_b of a candidate pair (`pair_distance`'s kinds)."""
        m = 0.0
        if pair[0] >= 0:
            m = self.motion_of(pair[0], scale) + self.triangle_motion(pair[1], scale)
        else:
            m = self.edge_motion(-pair[0] - 1, scale) + self.edge_motion(pair[1], scale)
        return m

    @ti.func
    def pair_distance(self, x: ti.template(), first, second):
        """The distance of a candidate pair (`Contact.corners`): surface vertex `first` and triangle `second`,
        or (first < 0) edge -first - 1 and edge `second`; m."""
        d = 0.0
        if first >= 0:
            t = self.contact.triangles[second]
            w = closest_weights(x[first], x[t[0]], x[t[1]], x[t[2]])
            d = (x[first] - (w[0] * x[t[0]] + w[1] * x[t[1]] + w[2] * x[t[2]])).norm()
        else:
            ea, fb = self.contact.edges[-first - 1], self.contact.edges[second]
            a0, a1, b0, b1 = x[ea[0]], x[ea[1]], x[fb[0]], x[fb[1]]
            s, t = segment_weights(a0, a1, b0, b1)
            d = ((a0 + s * (a1 - a0)) - (b0 + t * (b1 - b0))).norm()
        return d

    @ti.func
    def add_pair(self, first, second):
        slot = ti.atomic_add(self.contact.pair_count[None], 1)
        if slot < ti.static(self.contact.pair_capacity):
            self.contact.pairs[slot] = ti.Vector([first, second])
        else:
            self.contact.overflow[None] = 1

    @ti.func
    def vertex_pairs(self, x: ti.template(), i, half, scale):
        """The vertex-triangle pairs (i, k) of surface vertex i closer than 2 half + m_i + m_k, each found in
        the first cell of both grown boxes (a cell is wider than either: at most 2 a side)."""
        m_i = self.motion_of(i, scale)
        grow_i = half + m_i
        lo_i, hi_i = self.cell_of(x[i] - grow_i), self.cell_of(x[i] + grow_i)
        for a, b, l in ti.ndrange(2, 2, 2):
            c = lo_i + ti.Vector([a, b, l])
            if (c <= hi_i).all():
                bucket = self.bucket(c)
                for slot in range(self.triangle_grid.start[bucket], self.triangle_grid.start[bucket + 1]):
                    # nested tests, cheapest first: Taichi's `and` evaluates both sides
                    k = self.triangle_grid.entries[slot]
                    if self.triangle_grid.first_shared(k, c, lo_i):
                        t = self.contact.triangles[k]
                        if (t != i).all():
                            reach = 2.0 * half + m_i + self.triangle_motion(k, scale)
                            if (x[i] >= ti.min(x[t[0]], x[t[1]], x[t[2]]) - reach).all() and \
                                    (x[i] <= ti.max(x[t[0]], x[t[1]], x[t[2]]) + reach).all():   # in its grown box
                                if self.pair_distance(x, i, k) < reach:
                                    self.add_pair(i, k)

    @ti.func
    def first_after(self, b, e):
        """The first slot of bucket b whose edge is above e: a serial fill lists each bucket's edges in order."""
        lo, hi = self.edge_grid.start[b], self.edge_grid.start[b + 1]
        if ti.static(self.serial_vertices):
            while lo < hi:
                mid = (lo + hi) // 2
                if self.edge_grid.entries[mid] > e:
                    hi = mid
                else:
                    lo = mid + 1
        return lo

    @ti.func
    def edge_pairs(self, x: ti.template(), e, half, scale):
        """The edge-edge pairs (-e - 1, f) of surface edge e with the edges f > e closer than 2 half + m_e +
        m_f that share no vertex with it, each found in the first cell of both grown boxes."""
        ea = self.contact.edges[e]
        a0, a1 = x[ea[0]], x[ea[1]]
        m_e = self.edge_motion(e, scale)
        lo_e, hi_e = self.edge_grid.lowest[e], self.edge_grid.highest[e]
        for i, j, l in ti.ndrange(2, 2, 2):
            c = lo_e + ti.Vector([i, j, l])
            if (c <= hi_e).all():
                b = self.bucket(c)
                for slot in range(self.first_after(b, e), self.edge_grid.start[b + 1]):
                    f = self.edge_grid.entries[slot]            # nested tests, cheapest first (as in vertex_pairs)
                    if f > e:
                        if self.edge_grid.first_shared(f, c, lo_e):
                            fb = self.contact.edges[f]
                            if fb[0] != ea[0] and fb[0] != ea[1] and fb[1] != ea[0] and fb[1] != ea[1]:
                                b0, b1 = x[fb[0]], x[fb[1]]
                                reach = 2.0 * half + m_e + self.edge_motion(f, scale)
                                # closer than reach only if their boxes, one grown by reach, meet
                                if (ti.min(a0, a1) - reach <= ti.max(b0, b1)).all() and \
                                        (ti.max(a0, a1) + reach >= ti.min(b0, b1)).all():
                                    if self.pair_distance(x, -e - 1, f) < reach:
                                        self.add_pair(-e - 1, f)

    @ti.func
    def find_islands(self):
        """island[b] <- the lowest body id that body b is joined to through candidate pairs or the step's
        friction pairs: bodies in different islands cannot meet in this line search, nor rub, so each
        island searches alone. (A friction pair's E counts in its first body's E_b and its gradient in
        both: one whose bodies had parted further than the candidates reach left a body's search with a
        slope its E did not have, and it halved to nothing at every iteration: the pile, f64, 5 of 60 steps
        not converged, now 1.)"""
        sticks, stick_count = ti.static(self.contact.sticking.sticks, self.contact.sticking.stick_count)
        ti.loop_config(serialize=True)
        for _ in range(1):
            for b in range(self.model.body_count[None]):
                self.island[b] = b
            changed = 1
            count = self.contact.pair_count[None]
            rubbing = stick_count[None] * (self.contact.friction[None] > 0)
            while changed:
                changed = 0
                for q in range(count + rubbing):
                    ids = self.contact.vertices(q)[0]
                    if q >= count:
                        ids = self.contact.corners(sticks[q - count])[0]
                    a, c = self.model.vertex_body[ids[0]], self.model.vertex_body[ids[3]]
                    low = ti.min(self.island[a], self.island[c])
                    if self.island[a] != low or self.island[c] != low:
                        self.island[a], self.island[c], changed = low, low, 1

    @ti.kernel
    def meeting(self, x: ti.template(), radius: float, motion: ti.types.ndarray(), woken: ti.types.ndarray()):
        """woken[b] <- 1 for each sleeping body b (motion[b] = 0) that a moving body (motion 2; 1:
        awake but resting) comes closer to than radius at x: a body hit wakes before the step, and
        is pushed instead of acting as a wall. Leaves those pairs in the contact's pair list."""
        self.near_pairs(x, radius)
        for q in range(self.contact.pair_count[None]):
            ids = self.contact.vertices(q)[0]
            a, c = self.model.vertex_body[ids[0]], self.model.vertex_body[ids[3]]
            if motion[a] == 2 and motion[c] == 0:
                woken[c] = 1
            if motion[c] == 2 and motion[a] == 0:
                woken[a] = 1

    @ti.kernel
    def touching(self, x: ti.template(), bodies: ti.types.ndarray()):
        """bodies[b] <- 1 where body b has a pair of the current list closer than d_hat at x (it
        rests on or against a body, and friction holds it there up to a creep: fem/simulation.py)."""
        for q in range(self.contact.pair_count[None]):
            ids, edge = self.contact.vertices(q)
            if self.contact.gap(x, ids, edge)[0] < self.contact.distance[None]:
                bodies[self.model.vertex_body[ids[0]]] = 1
                bodies[self.model.vertex_body[ids[3]]] = 1
