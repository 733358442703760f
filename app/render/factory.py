"""The renderer by name: the one place that knows both back ends (they and their base,
app/render/frame.py, import only downwards)."""

from app.render.frame import Renderer
from app.render.ggui import GGUIRenderer
from app.render.software import SoftwareRenderer


def make_renderer(kind: str, width: int, height: int, smooth: bool = True) -> Renderer:
    """A renderer of the given kind: "software", "ggui" or "auto" (the software one).

    "auto" takes the software renderer: it draws the same triangles and needs no Vulkan, on a
    CPU it runs 2 to 3 times faster than GGUI over a software Vulkan driver, and it holds its
    memory, where GGUI's offscreen 3D scene in Taichi 1.7 keeps about 250 kB per frame (4 GB
    for a 10-minute video). `kind="ggui"` still draws with GGUI.
    Taichi must already be initialised (the engine does it).
    """
    if kind in ("software", "auto"):
        return SoftwareRenderer(width, height, smooth)
    if kind == "ggui":
        return GGUIRenderer(width, height, smooth)
    raise ValueError(f"unknown renderer kind {kind!r}: use 'auto', 'ggui' or 'software'")
