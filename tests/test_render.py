"""Renderers, camera and overlays: the checks one would do by eye, as numbers."""

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import taichi as ti

from app.render.camera import Camera, auto_frame
from app.render.overlay import (BODY_PALETTE, body_colors, draw_legend, draw_text_overlay, scalar_colors,
                                volume_line)
from app.render.factory import make_renderer

WIDTH, HEIGHT = 160, 120
REPO = Path(__file__).resolve().parents[1]
RED = (0.9, 0.1, 0.1)
BLUE = (0.1, 0.2, 0.9)


def cube(size=1.0):
    """Unit cube centred at the origin: vertices (8, 3), outward counter-clockwise faces (12, 3)."""
    vertices = (np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], float) - 0.5) * size
    quads = [[0, 1, 3, 2], [4, 6, 7, 5], [0, 4, 5, 1], [2, 3, 7, 6], [0, 2, 6, 4], [1, 5, 7, 3]]
    faces = [[a, b, c] for a, b, c, d in quads] + [[a, c, d] for a, b, c, d in quads]
    return vertices, np.array(faces, np.int32)


def reddish(image):
    """Mask (H, W) of pixels clearly redder than anything grey or blue."""
    rgb = image.astype(int)
    return (rgb[..., 0] > rgb[..., 1] + 60) & (rgb[..., 0] > rgb[..., 2] + 60)


def run_python(code, cwd=REPO, **env):
    """Run code in a fresh interpreter, with the repository importable.

    GGUI leaves an imgui.ini in the working directory, so tests that open a
    GGUI window run in a temporary one.
    """
    return subprocess.run([sys.executable, "-c", code], cwd=cwd, capture_output=True, text=True,
                          timeout=300, env={**os.environ, "PYTHONPATH": str(REPO), **env})


@pytest.fixture(scope="module", params=[ti.f32, ti.f64], ids=["f32", "f64"])
def software(request):
    """A software renderer, under each precision the engine may start Taichi with."""
    ti.init(arch=ti.cpu, default_fp=request.param)
    return make_renderer("software", WIDTH, HEIGHT)


@pytest.fixture(scope="module")
def cube_scene():
    vertices, faces = cube()
    colors = np.tile(RED, (len(vertices), 1))
    camera = auto_frame(vertices.min(0), vertices.max(0), aspect=WIDTH / HEIGHT)
    return vertices, faces, colors, camera


def test_camera_ray_goes_through_the_projected_point():
    camera = Camera(eye=[2.0, 1.0, 3.0], target=[0.0, 0.2, 0.0])
    point = np.array([0.3, -0.1, 0.4])
    clip = camera.view_proj(WIDTH / HEIGHT) @ np.append(point, 1.0)
    px = (clip[0] / clip[3] + 1) / 2 * WIDTH
    py = (1 - clip[1] / clip[3]) / 2 * HEIGHT
    origin, direction = camera.ray(px, py, WIDTH, HEIGHT)
    to_point = point - origin
    assert np.linalg.norm(np.cross(direction, to_point)) < 1e-9 * np.linalg.norm(to_point)
    assert direction @ to_point > 0


def test_auto_frame_keeps_every_vertex_in_the_image():
    rng = np.random.default_rng(0)
    for aspect in (WIDTH / HEIGHT, 0.5, 2.0):
        points = rng.uniform([-3.0, 0.0, 1.0], [1.0, 0.5, 9.0], size=(500, 3))
        camera = auto_frame(points.min(0), points.max(0), aspect=aspect)
        clip = camera.view_proj(aspect) @ np.c_[points, np.ones(len(points))].T
        ndc = clip[:3] / clip[3]
        assert np.all(np.abs(ndc[:2]) < 1.0), aspect
        assert np.all(clip[3] > camera.near)


def test_software_cube_is_drawn_where_it_projects(software, cube_scene):
    vertices, faces, colors, camera = cube_scene
    image = software.render(vertices, faces, colors, camera)
    assert image.shape == (HEIGHT, WIDTH, 3) and image.dtype == np.uint8
    rows, cols = np.nonzero(reddish(image))
    assert len(rows) > 0.1 * WIDTH * HEIGHT
    # The red pixels lie inside the box spanned by the projected corners.
    clip = camera.view_proj(WIDTH / HEIGHT) @ np.c_[vertices, np.ones(8)].T
    px = (clip[0] / clip[3] + 1) / 2 * WIDTH
    py = (1 - clip[1] / clip[3]) / 2 * HEIGHT
    assert px.min() - 1 <= cols.min() and cols.max() <= px.max() + 1
    assert py.min() - 1 <= rows.min() and rows.max() <= py.max() + 1
    assert reddish(image)[HEIGHT // 2, WIDTH // 2]


def test_the_windows_picture_is_the_software_image_in_ggui_layout(software, cube_scene):
    """The window shows the rasteriser's image through GGUI's canvas (not GGUI's leaking 3D
    scene): columns first, row 0 at the bottom, colours in 0..1."""
    from app.render.ggui import _to_ggui_layout
    from app.render.software import to_window_layout

    image = software.render(*cube_scene)
    picture = ti.Vector.field(3, ti.f32, (WIDTH, HEIGHT))
    to_window_layout(software.image, picture)
    np.testing.assert_allclose(picture.to_numpy(), _to_ggui_layout(image) / 255.0, atol=1e-6)


def test_software_near_triangle_hides_far_one_in_either_order(software):
    near = [[-1.0, -1.0, 0.5], [1.0, -1.0, 0.5], [0.0, 1.0, 0.5]]
    far = [[-1.0, -1.0, -0.5], [1.0, -1.0, -0.5], [0.0, 1.0, -0.5]]
    vertices, colors = np.array(near + far), np.array([RED] * 3 + [BLUE] * 3)
    camera = Camera(eye=[0.0, 0.0, 4.0], target=[0.0, 0.0, 0.0], near=0.1, far=20.0)
    for faces in ([[0, 1, 2], [3, 4, 5]], [[3, 4, 5], [0, 1, 2]]):
        image = software.render(vertices, np.array(faces), colors, camera, ground_y=-5.0)
        assert reddish(image)[HEIGHT // 2, WIDTH // 2]


def test_software_is_deterministic(software, cube_scene):
    vertices, faces, colors, camera = cube_scene
    first = software.render(vertices, faces, colors, camera)
    again = software.render(vertices, faces, colors, camera)
    fresh = make_renderer("software", WIDTH, HEIGHT).render(vertices, faces, colors, camera)
    assert np.array_equal(first, again) and np.array_equal(first, fresh)


def test_flat_and_smooth_shading_differ_on_a_cube(software, cube_scene):
    vertices, faces, colors, camera = cube_scene
    flat = make_renderer("software", WIDTH, HEIGHT, smooth=False).render(vertices, faces, colors, camera)
    smooth = software.render(vertices, faces, colors, camera)
    assert reddish(flat).sum() > 0.1 * WIDTH * HEIGHT
    assert not np.array_equal(flat, smooth)


def vulkan_probe(workdir):
    """None when a GGUI offscreen window opens in a fresh process, else why not."""
    probe = run_python("import taichi as ti; ti.init(arch=ti.cpu); "
                       "ti.ui.Window('probe', (32, 32), show_window=False)", cwd=workdir)
    return None if probe.returncode == 0 else (probe.stderr.strip().splitlines() or ["crashed"])[-1]


GGUI_AND_SOFTWARE = """
import numpy as np, taichi as ti
from app.render.camera import Camera
from app.render.factory import make_renderer
ti.init(arch=ti.cpu)
scene = np.load("scene.npz")
camera = Camera(*scene["camera"][:3], near=scene["camera"][3, 0], far=scene["camera"][3, 1])
for kind in ("ggui", "software"):
    renderer = make_renderer(kind, {width}, {height})
    np.save(kind, renderer.render(scene["vertices"], scene["faces"], scene["colors"], camera))
"""


def test_ggui_cube_matches_the_software_picture(cube_scene, tmp_path):
    reason = vulkan_probe(tmp_path)
    if reason:
        pytest.skip(f"GGUI needs a working Vulkan driver (apt: libvulkan1 mesa-vulkan-drivers): {reason}")
    vertices, faces, colors, camera = cube_scene
    camera_rows = [camera.eye, camera.target, camera.up, [camera.near, camera.far, 0.0]]
    np.savez(tmp_path / "scene.npz", vertices=vertices, faces=faces, colors=colors, camera=camera_rows)
    result = run_python(GGUI_AND_SOFTWARE.format(width=WIDTH, height=HEIGHT), cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    image, reference = np.load(tmp_path / "ggui.npy"), np.load(tmp_path / "software.npy")
    assert image.shape == (HEIGHT, WIDTH, 3) and image.dtype == np.uint8
    assert reddish(image).sum() > 0.1 * WIDTH * HEIGHT
    difference = np.abs(image.astype(int) - reference.astype(int)).max(axis=2)
    assert np.mean(difference > 16) < 0.01  # only a few edge pixels may differ


def test_auto_is_the_software_renderer_and_needs_no_vulkan():
    result = run_python(
        "import sys, numpy as np, taichi as ti\n"
        "ti.init(arch=ti.cpu)\n"
        "from app.render.camera import Camera\n"
        "from app.render.factory import make_renderer\n"
        "renderer = make_renderer('auto', 32, 24)\n"
        "image = renderer.render(np.eye(3), np.array([[0, 1, 2]]), np.ones((3, 3)),\n"
        "                        Camera(eye=[2.0, 2.0, 2.0], target=[0.0, 0.0, 0.0]))\n"
        "print(renderer.name, image.shape)\n",
        VK_ICD_FILENAMES="/nonexistent")
    assert result.returncode == 0, result.stderr
    assert "software (24, 32, 3)" in result.stdout
    assert "Vulkan" not in result.stderr and "GGUI" not in result.stderr, result.stderr


def test_text_overlay_changes_only_its_corner():
    image = np.full((HEIGHT, WIDTH, 3), 200, np.uint8)
    drawn = draw_text_overlay(image, ["t = 0.50 s", "frame 30"], corner="top-left")
    changed = np.any(drawn != image, axis=2)
    assert changed[:HEIGHT // 4, :WIDTH // 4].any()
    assert not changed[HEIGHT // 2:, :].any() and not changed[:, WIDTH // 2:].any()
    assert image.min() == 200  # the input is left alone


def test_the_caption_says_each_fact_once_and_each_volume_ratio():
    """The export's caption said "epcot (linear vs corotational) / left linear, right corotational:
    epcot" and no volume ratio."""
    compare = ["epcot", volume_line([("epcot", "linear", 1.8249), ("epcot", "corotational", 0.9996)])]
    assert compare == ["epcot", "volume / rest volume: linear 1.82 | corotational 1.00"]
    text = " ".join(compare)
    assert [text.count(word) for word in ("epcot", "linear", "corotational")] == [1, 1, 1]
    assert volume_line([("epcot", "corotational", 1.0)]) == "volume / rest volume: corotational 1.00"
    # Several bodies: each name once, then its ratio under each method in the same order.
    pair = [("soft", "linear", 1.31), ("stiff", "linear", 1.02), ("soft", "corotational", 1.0),
            ("stiff", "corotational", 0.994)]
    assert volume_line(pair) == "volume / rest volume of soft, stiff: linear 1.31, 1.02 | corotational 1.00, 0.99"
    # Bodies under different methods: each ratio named by its body.
    assert volume_line([("soft", "linear", 1.31), ("stiff", "corotational", 1.0)]) == \
        "volume / rest volume: linear soft 1.31 | corotational stiff 1.00"
    # A pile: each method's range, so that the line fits on the frame's panel.
    pile = [(f"box{k}", method, 1.0 + 0.01 * k - (0.02 if method == "linear" else 0.0))
            for method in ("linear", "corotational") for k in range(20)]
    assert volume_line(pile) == "volume / rest volume of 20 bodies: linear 0.98 to 1.17 | corotational 1.00 to 1.19"
    assert volume_line(pile[20:]) == "volume / rest volume of 20 bodies: corotational 1.00 to 1.19"
    assert volume_line(pile[:5] + pile[25:]) == \
        "volume / rest volume: linear 5 bodies 0.98 to 1.02 | corotational 15 bodies 1.05 to 1.19"


def test_an_overlay_blends_only_its_panel_exactly_as_over_the_whole_frame():
    """Blending the whole frame took more time than drawing; the part drawn on gives the same pixels."""
    from PIL import Image, ImageDraw

    from app.render.overlay import PANEL_COLOR, blended
    image = np.random.default_rng(0).integers(0, 256, (HEIGHT, WIDTH, 3), dtype=np.uint8)
    layer = Image.new("RGBA", (WIDTH, HEIGHT), (0, 0, 0, 0))
    ImageDraw.Draw(layer).rounded_rectangle([10, 12, 70, 40], radius=4, fill=PANEL_COLOR)
    whole = Image.alpha_composite(Image.fromarray(image).convert("RGBA"), layer).convert("RGB")
    np.testing.assert_array_equal(blended(image, layer), np.asarray(whole))


def test_legend_shows_the_colour_ramp():
    image = np.full((HEIGHT * 2, WIDTH * 2, 3), 200, np.uint8)
    drawn = draw_legend(image, "J", 0.8, 1.2, corner="bottom-right")
    changed = np.any(drawn != image, axis=2)
    assert changed[HEIGHT:, WIDTH:].any() and not changed[:HEIGHT, :].any()
    ends = (np.round(scalar_colors([0.8, 1.2], 0.8, 1.2) * 255)).astype(int)
    for colour in ends:
        assert np.any(np.abs(drawn.astype(int) - colour).max(axis=2) <= 2)


def test_colour_maps():
    blue, grey, red = scalar_colors([0.5, 1.0, 7.0], 0.8, 1.2)
    assert blue[2] > blue[0] and red[0] > red[2]
    assert np.ptp(grey) < 0.01  # unchanged volume is neutral
    palette = body_colors(np.arange(6))
    assert palette.shape == (6, 3) and len(np.unique(palette, axis=0)) == 6
    assert np.array_equal(body_colors([0]), body_colors([len(BODY_PALETTE)]))  # colours cycle


# ---------------------------------------------------------------- floor, shadow, colour scales

def test_no_floor_without_a_ground_only_the_backdrop(software, cube_scene):
    from app.render.frame import background
    vertices, faces, colors, camera = cube_scene
    image = software.render(vertices, faces, colors, camera, ground_y=None)
    backdrop = np.round(background(WIDTH, HEIGHT) * 255)
    away = ~reddish(image)
    assert np.abs(image[away].astype(int) - backdrop[away]).max() <= 1


def test_a_body_above_the_ground_casts_a_shadow_straight_below(software):
    vertices, faces = cube(0.5)
    vertices = vertices + [0.0, 1.0, 0.0]                  # floating 0.75 m above y = 0
    colors = np.tile(RED, (len(vertices), 1))
    camera = Camera(eye=[0.0, 4.0, 3.0], target=[0.0, 0.5, 0.0], near=0.1, far=50.0)
    lit = software.render(vertices, faces, colors, camera, ground_y=0.0)
    bare = software.render(vertices + [100.0, 0, 0], faces, colors, camera, ground_y=0.0)

    def pixel(point):
        clip = camera.view_proj(WIDTH / HEIGHT) @ np.append(point, 1.0)
        return round((1 - clip[1] / clip[3]) / 2 * HEIGHT), round((clip[0] / clip[3] + 1) / 2 * WIDTH)

    below = pixel([0.0, 0.0, 0.0])
    assert not reddish(lit)[below]                                  # the floor, not the cube
    assert lit[below].astype(int).sum() < 0.8 * bare[below].astype(int).sum()   # darker: the shadow


def test_window_and_export_colour_with_the_same_scales():
    from app.render import colors
    from app.window import viewer
    assert viewer.VertexColoring is colors.VertexColoring
    assert not hasattr(viewer, "VOLUME_RANGE")


class FakeSimulation:
    """What VertexColoring reads: two tets, one body, and per-tet values that can be set."""

    def __init__(self, energy):
        from types import SimpleNamespace
        from fem.scene import Material
        self.model = SimpleNamespace(tets_np=np.array([[0, 1, 2, 3], [1, 2, 3, 4]]), n_vertices=5,
                                     vertex_body_np=np.zeros(5, int),
                                     bodies=[SimpleNamespace(material=Material(1e4, 0.3, 1000.0))])
        self.energy = np.asarray(energy, float)

    def tet_values(self):
        return np.ones(2), self.energy


def test_strain_scale_grows_to_the_scene_and_never_shrinks():
    from app.render.colors import VertexColoring, nice_ceiling
    sim = FakeSimulation([0.0, 0.0])
    coloring = VertexColoring(sim, "strain")
    start = coloring.vmax
    coloring.colors(sim)
    assert coloring.vmax == start                     # nothing strained: the initial scale
    sim.energy = np.array([10.0, 730.0]) * start
    top = coloring.colors(sim)
    assert coloring.vmax == nice_ceiling(np.percentile(sim.energy, 99)) >= sim.energy.max() * 0.99
    assert not np.allclose(top[0], top[4])            # not one saturated colour
    sim.energy = np.zeros(2)
    coloring.colors(sim)
    assert coloring.vmax == nice_ceiling(np.percentile([10.0 * start, 730.0 * start], 99))
    assert [nice_ceiling(v) for v in (1.0, 1.5, 3.3, 7.0, 0.0123)] == pytest.approx([1, 2, 5, 10, 0.02])


@pytest.mark.parametrize("eye", [[0.0, 5.0, 0.0], [0.0, -5.0, 0.0]], ids=["top-down", "bottom-up"])
def test_a_camera_looking_along_up_still_sees(eye):
    """A scene's camera straight above its target (eye - target parallel to up) drew blank frames:
    its basis was 0 / 0. It now shows the x axis across the picture."""
    camera = Camera(eye=eye, target=[0.0, 0.0, 0.0])
    right, true_up, forward = camera.basis()
    assert np.allclose(np.array([right, true_up, forward]) @ np.array([right, true_up, forward]).T, np.eye(3))
    clip = camera.view_proj(1.0) @ np.array([[0, 0, 0, 1], [1, 0, 0, 1]], float).T
    ndc = (clip[:2] / clip[3]).T
    assert np.allclose(ndc[0], 0) and abs(ndc[1][0]) > 0.1 and abs(ndc[1][1]) < 1e-9
