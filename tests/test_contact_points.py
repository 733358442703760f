"""Contact points in pictures: `export --contact-points` (app/render/overlay.draw_points) marks
Simulation.contact_points with magenta dots where the frame's camera sees them.

The exports run in this process through main.main, so that the Simulation the test steps beside
them reuses their compiled kernels; a small box starts 15 mm above another (a start closer than the
contact distance, 1 cm, is refused) moving down at 0.6 m/s, so the first step already has contact points.
"""

import contextlib
import io
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

import fem
import main
import scenes
from app.commands.export import View
from app.render.camera import Camera
from app.render.overlay import CONTACT_COLOR, CONTACT_OUTLINE, draw_points

REPO = Path(__file__).resolve().parents[1]
WIDTH, HEIGHT = 160, 128
CAPTION_ROWS = 64           # the caption's panel at the top-left, over the picture at this size
BOX_ON_A_BOX = """
name = "box on a box"
[solver]
dt = 0.02
[effects]
gravity = [0.0, -9.81, 0.0]
ground = { height = 0.0, friction = 0.5 }
contact = { distance = 0.01, friction = 0.5 }
[camera]
eye = [1.6, 1.4, 2.4]
target = [0.0, 0.45, 0.0]
[[body]]
name = "lower"
mesh = { generator = "box", size = [1.0, 0.4, 1.0], cells = [2, 1, 2] }
material = { E = 1e5, nu = 0.3, density = 1000.0 }
position = [0.0, 0.2, 0.0]
[[body]]
name = "upper"
mesh = { generator = "box", size = [0.5, 0.5, 0.5], cells = [1, 1, 1] }
material = { E = 1e5, nu = 0.3, density = 1000.0 }
position = [0.1, 0.665, 0.05]
[[initial]]
body = "upper"
velocity = [0.0, -0.6, 0.0]
"""


def export(*args, cwd):
    """`main.py export SCENE ... --size WxH` in this process: (exit code, stderr)."""
    err = io.StringIO()
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(err):
        code = main.main(["export", *args, "--size", f"{WIDTH}x{HEIGHT}"])
    return code, err.getvalue()


def picture(folder, index):
    return np.asarray(Image.open(Path(folder) / f"frame_{index:05d}.png").convert("RGB"))


def magenta(image):
    """Mask (H, W): pixels of exactly the markers' colour (a PNG keeps it exactly)."""
    return (image == CONTACT_COLOR).all(axis=-1)


@pytest.fixture(scope="module")
def scene_file(tmp_path_factory):
    folder = tmp_path_factory.mktemp("contact-points")
    (folder / "boxes.toml").write_text(BOX_ON_A_BOX)
    return folder / "boxes.toml"


@pytest.fixture(scope="module")
def exported(scene_file):
    """Two frames, one step apart, with and without the option: {name: folder}."""
    folders = {}
    for name, extra in (("marked", ["--contact-points"]), ("plain", [])):
        folders[name] = scene_file.parent / name
        code, err = export(str(scene_file), "--frames", "2", "--steps-per-frame", "1", "--out",
                           str(folders[name]), *extra, cwd=scene_file.parent)
        assert code == 0, err
    return folders


def test_dots_are_drawn_where_the_camera_sees_the_contact_points(scene_file, exported):
    # The same scene stepped as the export did: one step after frame 0, the same camera.
    scene = scenes.load_scene(scene_file)
    sim = fem.Simulation(scene)
    view = View(sim, scene, False, "body", "software", WIDTH, HEIGHT, contact_points=True)
    view.picture(sim)
    sim.step()
    view.picture(sim)
    assert len(sim.contact_points) >= 4, "the boxes do not touch after the first step"
    pixels, ahead = view.camera.to_pixels(sim.contact_points, WIDTH, HEIGHT)
    assert ahead.all() and ((pixels > 0) & (pixels < [WIDTH, HEIGHT])).all()

    before, after = picture(exported["marked"], 0), picture(exported["marked"], 1)
    assert not magenta(before).any(), "frame 0 comes before any step: no contact point yet"
    # A dot of radius 2 pixels (at this size) centred on the pixel each point falls in, outlined
    # by one more pixel; only the caption's translucent panel (the top rows) may dim one.
    dots, centres = magenta(after), np.floor(pixels) + 0.5
    radius = max(2, round(HEIGHT / 160))
    assert dots[tuple(np.floor(pixels).astype(int).T[::-1])].all()
    assert (within(centres, radius + 0.5) == dots)[CAPTION_ROWS:].all()
    # Between the boxes: below the upper box's centre as seen (points at ~0.4 m, its centre at 0.65 m).
    upper = sim.positions()[sim.model.bodies[1].vertices].mean(axis=0)
    assert centres[:, 1].mean() > view.camera.to_pixels(upper, WIDTH, HEIGHT)[0][0, 1]
    # Without the option: no dot, and the same picture but for the dots and their outlines.
    plain = picture(exported["plain"], 1)
    assert not magenta(plain).any()
    assert ((plain != after).any(axis=-1) <= within(centres, radius + 1.5)).all()


def within(centres, reach):
    """Mask (HEIGHT, WIDTH): the pixels whose centre is within reach pixels of one of centres (n, 2)."""
    ys, xs = np.mgrid[0:HEIGHT, 0:WIDTH] + 0.5
    grid = np.stack([xs.ravel(), ys.ravel()], axis=1)
    return (np.linalg.norm(grid[:, None] - centres[None], axis=2).min(axis=1) <= reach).reshape(HEIGHT, WIDTH)


def test_compare_marks_the_contact_in_both_panels(scene_file):
    folder = scene_file.parent / "compare"
    code, err = export(str(scene_file), "--compare", "--contact-points", "--frames", "2",
                       "--steps-per-frame", "1", "--out", str(folder), cwd=scene_file.parent)
    assert code == 0, err
    columns = np.flatnonzero(magenta(picture(folder, 1)).any(axis=0))
    left, right = columns[columns < WIDTH // 2], columns[columns >= WIDTH // 2]
    assert len(left) >= 3 and len(right) >= 3
    # Each copy's contact in the same place of its own panel: the two copies start alike.
    assert abs(left.mean() + WIDTH // 2 - right.mean()) <= 3


def test_ggui_renderer_gets_the_same_dots(scene_file, exported):
    folder = scene_file.parent / "ggui"
    code, err = export(str(scene_file), "--renderer", "ggui", "--contact-points", "--frames", "2",
                       "--steps-per-frame", "1", "--out", str(folder), cwd=scene_file.parent)
    if code != 0:
        assert code == 2 and err.startswith("error: --renderer ggui"), err
        pytest.skip(f"GGUI cannot open here: {err.strip()}")
    # Drawn after rendering, from the same points and camera: the very same pixels.
    np.testing.assert_array_equal(magenta(picture(folder, 1)), magenta(picture(exported["marked"], 1)))


def test_points_behind_the_camera_or_off_the_picture_are_not_drawn():
    camera = Camera(eye=[0.0, 0.0, 5.0], target=[0.0, 0.0, 0.0], near=0.1, far=100.0)
    grey = np.full((HEIGHT, WIDTH, 3), 128, np.uint8)
    drawn = draw_points(grey, np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 10.0], [1e6, 0.0, 0.0]]), camera)
    dots = magenta(drawn)
    ys, xs = np.nonzero(dots)
    # Only the origin's dot, at the image's centre, a few pixels wide ...
    assert (xs.mean(), ys.mean()) == pytest.approx((WIDTH / 2 - 0.5, HEIGHT / 2 - 0.5), abs=0.5)
    assert 3 <= np.ptp(xs) + 1 <= 7
    # ... with a dark outline: every pixel beside the dot has the outline's colour, and nothing else changed.
    beside = np.zeros_like(dots)
    beside[1:] |= dots[:-1]
    beside[:-1] |= dots[1:]
    beside[:, 1:] |= dots[:, :-1]
    beside[:, :-1] |= dots[:, 1:]
    beside &= ~dots
    assert (drawn[beside] == CONTACT_OUTLINE).all()
    changed = (drawn != grey).any(axis=-1)
    assert changed.sum() <= 2 * dots.sum() and not changed[:, :WIDTH // 3].any()


@pytest.mark.parametrize("extra", [[], ["--compare"]])
def test_a_scene_without_contact_is_refused_in_one_line(tmp_path, extra):
    run = subprocess.run([sys.executable, str(REPO / "main.py"), "export", "cube86", "--contact-points",
                          "--out", "frames", *extra], cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert run.returncode == 2
    assert run.stderr.startswith("error: --contact-points: cube86") and len(run.stderr.splitlines()) == 1
    assert "--contact" in run.stderr.split(";")[1]
    assert not (tmp_path / "frames").exists()
