"""Per-vertex colours of the bodies' surfaces: by body, by volume change or by strain energy.

The engine measures per tet (`Simulation.tet_values`); a vertex shows the mean
over the tets that share it, so colours vary smoothly over the surface. The
window and the exporter both colour through `VertexColoring`, so a quantity has
the same colours in both. The volume scale is fixed; the strain scale starts at
the energy of a small strain and only ever grows, to a round number above the
largest energy seen so far (99th percentile over the tets), so a scene's range
is shown rather than a saturated colour, equal colours mean equal values in
both copies of --compare, and the legend says the scale of every frame.
"""

import numpy as np

from app.render.frame import nice_step
from app.render.overlay import body_colors, draw_legend, scalar_colors

# Strain energy above this percentile of the tets (a few bad slivers) does not stretch the scale.
STRAIN_PERCENTILE = 99

MODES = ("body", "volume", "strain")

# Volume ratio J = det F: halved (blue) .. unchanged (grey) .. 1.5 times (red); beyond clamps.
VOLUME_RANGE = (0.5, 1.5)
# The strain scale tops out at the energy density of this uniaxial strain in the stiffest body.
REFERENCE_STRAIN = 0.05


class VertexColoring:
    """Colours (n, 3) in [0, 1] for every vertex of a simulation, and the legend that reads them.

    mode: "body" (one palette colour per body), "volume" (volume ratio J,
    diverging around 1) or "strain" (strain energy density, J/m^3, from 0).
    copies: how many times the scene's bodies repeat in the simulation (2 for
    Scene.side_by_side); every copy of a body gets that body's colour.
    """

    def __init__(self, sim, mode: str, copies: int = 1):
        if mode not in MODES:
            raise ValueError(f"unknown colour mode {mode!r}: use one of {MODES}")
        self.mode = mode
        self.tets = sim.model.tets_np
        self.tets_per_vertex = np.bincount(self.tets.ravel(), minlength=sim.model.n_vertices)
        self.body = body_colors(sim.model.vertex_body_np % (len(sim.model.bodies) // copies))
        if mode == "volume":
            self.title, self.colormap = "volume ratio J = det F", "coolwarm"
            self.vmin, self.vmax = VOLUME_RANGE
        elif mode == "strain":
            self.title, self.colormap = "strain energy, J/m^3", "viridis"  # a density
            self.vmin, self.vmax = 0.0, strain_energy_scale(sim.model.bodies)

    def colors(self, sim) -> np.ndarray:
        """Colours (n, 3) of the simulation's vertices now."""
        if self.mode == "body":
            return self.body
        volume_ratio, energy_density = sim.tet_values()
        per_tet = volume_ratio if self.mode == "volume" else energy_density
        if self.mode == "strain":
            top = float(np.percentile(per_tet, STRAIN_PERCENTILE))
            if np.isfinite(top) and top > self.vmax:
                self.vmax = nice_ceiling(top)
        return scalar_colors(self.vertex_mean(per_tet), self.vmin, self.vmax, self.colormap)

    def vertex_mean(self, per_tet: np.ndarray) -> np.ndarray:
        """Mean (n,) over the tets sharing each vertex of a per-tet value (m,)."""
        sums = np.bincount(self.tets.ravel(), np.repeat(per_tet, 4), minlength=len(self.tets_per_vertex))
        return sums / np.maximum(self.tets_per_vertex, 1)

    def draw_legend(self, image: np.ndarray) -> np.ndarray:
        """image (H, W, 3) uint8 with the colour bar of a scalar mode; unchanged for "body"."""
        if self.mode == "body":
            return image
        return draw_legend(image, self.title, self.vmin, self.vmax, self.colormap)


def nice_ceiling(value: float) -> float:
    """The number 1, 2 or 5 times a power of ten at or just above value (> 0)."""
    power = 10.0 ** np.floor(np.log10(value))
    return min(s * power for s in (1.0, 2.0, 5.0, 10.0) if s * power >= value)


def strain_energy_scale(bodies) -> float:
    """A round top for the strain energy scale (J/m^3): the energy density
    (mu + lam/2) eps^2 of a uniaxial strain eps = REFERENCE_STRAIN in the stiffest body."""
    def density(material):
        mu, lam = material.lame
        return (mu + lam / 2) * REFERENCE_STRAIN**2

    return nice_step(max(density(b.material) for b in bodies))
