"""The interactive window: picking and pushing (pure numpy), camera moves, and the
real window under a virtual X display, driven with xdotool."""

import contextlib
import ctypes.util
import glob
import json
import os
import re
import shutil
import subprocess
import sys
import time

import numpy as np
import pytest

from app.window import orbit, picking
from app.render.camera import Camera

# Two unit squares facing +z, one at z = 0 and one behind it at z = -1, as triangles.
SQUARE = np.array([[-0.5, -0.5, 0], [0.5, -0.5, 0], [0.5, 0.5, 0], [-0.5, 0.5, 0]], float)
TWO_SQUARES = np.concatenate([SQUARE, SQUARE + [0, 0, -1]])
TRIANGLES = np.array([[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7]])


# ---------------------------------------------------------------- picking

def test_ray_hits_the_triangle_it_points_at():
    hit = picking.pick([0.2, 0.1, 5.0], [0, 0, -1.0], SQUARE, TRIANGLES[:2])
    assert hit is not None
    np.testing.assert_allclose(hit.point, [0.2, 0.1, 0.0], atol=1e-12)
    assert hit.distance == pytest.approx(5.0)
    assert hit.triangle == 0          # x > y: the lower-right triangle (0, 1, 2)
    assert hit.vertex == 2            # (0.5, 0.5) is the nearest corner of that triangle


def test_ray_that_misses_hits_nothing():
    assert picking.pick([2.0, 0.0, 5.0], [0, 0, -1.0], SQUARE, TRIANGLES[:2]) is None
    # pointing away from the square: the triangle is behind the origin
    assert picking.pick([0.0, 0.0, 5.0], [0, 0, 1.0], SQUARE, TRIANGLES[:2]) is None
    # parallel to the square's plane
    assert picking.pick([-2.0, 0.0, 0.5], [1.0, 0, 0], SQUARE, TRIANGLES[:2]) is None


def test_nearest_of_two_bodies_wins_from_either_side():
    front = picking.pick([0.1, 0.1, 5.0], [0, 0, -1.0], TWO_SQUARES, TRIANGLES)
    assert front.triangle in (0, 1) and front.point[2] == pytest.approx(0.0)
    back = picking.pick([0.1, 0.1, -5.0], [0, 0, 1.0], TWO_SQUARES, TRIANGLES)
    assert back.triangle in (2, 3) and back.point[2] == pytest.approx(-1.0)
    assert back.distance == pytest.approx(4.0)


def test_distances_of_every_triangle_at_once():
    d = picking.ray_triangle_distances([-0.1, 0.1, 2.0], [0, 0, -1.0], TWO_SQUARES, TRIANGLES)
    assert d.shape == (4,)
    assert np.isinf(d[[0, 2]]).all()             # the ray passes through triangles 1 and 3 (y > x)
    np.testing.assert_allclose(d[[1, 3]], [2.0, 3.0])


# ---------------------------------------------------------------- impulse falloff

def test_falloff_is_one_at_the_hit_and_fades_smoothly_to_zero_at_the_radius():
    r = 0.5
    d = np.linspace(0.0, 1.0, 201)
    w = picking.falloff(d, r)
    assert w[0] == 1.0
    assert (w[d >= r] == 0).all()
    assert (np.diff(w) <= 0).all()                # never grows with distance
    h = 1e-6                                      # no kink at either end: zero slope
    assert abs(picking.falloff(h, r) - 1.0) / h < 1e-4
    assert abs(picking.falloff(r - h, r)) / h < 1e-4
    assert picking.falloff(r / 2, r) == pytest.approx(0.75 ** 2)


def test_push_reaches_only_vertices_within_the_radius():
    positions = np.array([[0, 0, 0], [0.1, 0, 0], [0.3, 0, 0], [1.0, 0, 0], [0.05, 0, 0]], float)
    ids, dv = picking.push(positions, [0, 1, 2, 3], [0, 0, 0], radius=0.5, delta_v=[0, 0, -2.0])
    assert ids.tolist() == [0, 1, 2]              # 3 is too far, 4 is not a candidate
    np.testing.assert_allclose(dv[:, 2], -2.0 * picking.falloff([0, 0.1, 0.3], 0.5))
    np.testing.assert_allclose(dv[:, :2], 0.0)


def test_mirrored_ids_are_the_same_local_vertices_of_the_twin():
    starts = np.array([0, 10, 25, 35])            # bodies 0, 1 linear; 2, 3 their corotational twins
    np.testing.assert_array_equal(picking.mirrored([12, 14], starts, 1, 3), [37, 39])
    np.testing.assert_array_equal(picking.mirrored([27], starts, 2, 0), [2])


# ---------------------------------------------------------------- camera moves

def camera():
    return Camera(eye=[0.0, 1.0, 5.0], target=[0.0, 1.0, 0.0], fov_deg=45.0, near=0.1, far=100.0)


def test_orbit_keeps_the_distance_and_the_target():
    moved = orbit.orbit(camera(), 150, -40)
    np.testing.assert_allclose(moved.target, camera().target)
    assert np.linalg.norm(moved.eye - moved.target) == pytest.approx(5.0)
    assert moved.eye[1] < 1.0                      # dragged up: the eye goes below
    assert orbit.orbit(camera(), 0, 1e4).eye[1] < 1.0 + 5.0   # clamped short of the pole


def test_pan_moves_eye_and_target_together_in_the_image_plane():
    moved = orbit.pan(camera(), 100, 0, height=500)
    shift = moved.eye - camera().eye
    np.testing.assert_allclose(moved.target - camera().target, shift)
    assert shift[0] < 0 and abs(shift[1]) < 1e-12 and abs(shift[2]) < 1e-12


def test_zoom_scales_the_distance_and_the_clip_planes():
    moved = orbit.zoom(camera(), 0.5)
    assert np.linalg.norm(moved.eye - moved.target) == pytest.approx(2.5)
    assert (moved.near, moved.far) == pytest.approx((0.05, 50.0))


# ---------------------------------------------------------------- compare labels, recordings

def test_compare_labels_sit_over_their_copies():
    from app.window.viewer import copy_labels
    linear = np.array([[-2.0, 0, 0], [-1.0, 1.0, 0]])
    corotational = linear + [3.0, 0, 0]
    cam = Camera(eye=[0.5, 0.5, 8.0], target=[0.5, 0.5, 0.0], near=0.1, far=100.0)
    (first, x1), (second, x2) = copy_labels(np.vstack([linear, corotational]), 2, cam, 4 / 3)
    assert (first, second) == ("linear", "corotational")
    for points, x in ((linear, x1), (corotational, x2)):    # over the middle of each copy
        clip = np.c_[points, np.ones(2)] @ cam.view_proj(4 / 3).T
        assert x == pytest.approx(np.mean((clip[:, 0] / clip[:, 3] + 1) / 2), abs=0.02)
    assert x1 < 0.5 < x2


def test_the_panel_shows_no_figure_before_it_is_measured():
    from app.window.panel import numbers
    before = {"step": 0, "t": 0.0, "solver": "pcg", "kinetic_energy": 0.0}      # Simulation.stats() at the start
    lines = numbers(before, fps=None, steps_per_frame=0, render_ms=None, paused=False)
    assert lines == ["t = 0.00 s, step 0", "fps: measuring", "pcg: no step yet"]
    stepped = dict(before, step=1, t=0.02, preconditioner="jacobi", residual=6.5e-4, solver_iters=35,
                   converged=False, rotation_ms=6.9, solve_ms=125.6)
    lines = numbers(stepped, fps=12.34, steps_per_frame=2, render_ms=45.0, paused=True)
    assert lines == ["t = 0.02 s, step 1   PAUSED", "12.3 fps, 2 step(s)/frame", "ms/frame rendering: 45.0",
                     "ms/step: rotations 6.9, solve 125.6", "pcg (jacobi): 35 iterations",
                     "residual 6.5e-04  NOT CONVERGED"]


def test_the_panel_holds_its_longest_lines_at_any_window_width():
    from app.window.panel import CHAR_WIDTH, PANEL_MARGIN, panel_chars, panel_width
    for width in (640, 1280, 1920, 3840):
        pixels = panel_width(width) * width
        assert pixels <= width / 2
        assert panel_chars(width) * CHAR_WIDTH + PANEL_MARGIN <= pixels
    # A slider takes 65 % of the panel; its label ("strength [m/s]") and the margins the rest.
    assert 0.35 * panel_width(1280) * 1280 >= 14 * CHAR_WIDTH + 34


class ScriptedWindow:
    """A stand-in for the GGUI window: `polls` is a list of (presses, releases, cursor) that each
    read of the events returns in turn (cursor: (x, y) in [0, 1], y up, as GGUI gives it)."""

    def __init__(self, polls):
        self.polls, self.cursor, self.releases = list(polls), (0.5, 0.5), []

    def get_events(self, tag):
        from types import SimpleNamespace

        import taichi as ti
        if tag == ti.ui.PRESS:
            if not self.polls:
                return []
            presses, self.releases, self.cursor = self.polls.pop(0)
            return [SimpleNamespace(key=key) for key in presses]
        return [SimpleNamespace(key=key) for key in self.releases]

    def get_cursor_pos(self):
        return self.cursor

    def is_pressed(self, key):
        return False


def test_input_read_while_kernels_compile_waits_for_the_first_step():
    from app.window.controls import Controls

    class Viewer(Controls):
        """The little of the viewer that its input handling reads; it notes what it does."""
        width, height, show_help, strength = WIDTH, HEIGHT, False, 1.0

        def __init__(self, window):
            self.window, self.camera, self.waiting, self.press, self.done = window, camera(), [], None, []

        def pick(self, pixel):
            self.done.append(("pick", pixel.tolist()))
            return picking.Hit(0, np.zeros(3), 5.0, 0)

        def push(self, hit, delta_v, waited_s=0.0):
            self.done.append("push")

        def toggle_corotation(self):
            self.done.append("c")

    # A click at (100, 120) px and c, read in the frame before warm_up; then the cursor moves away.
    window = ScriptedWindow([(["LMB", "c"], ["LMB"], (100 / WIDTH, 1 - 120 / HEIGHT)), ([], [], (0.9, 0.9))])
    viewer = Viewer(window)
    viewer.warm_up_due = True
    viewer.handle_keys()
    assert viewer.done == [] and len(viewer.waiting) == 3      # warm_up would undo them: kept
    viewer.warm_up_due = False
    viewer.handle_keys()
    # In the order read (presses first: Taichi's events carry no order between the two kinds),
    # the click picked where the cursor was when it was read.
    assert viewer.done == [("pick", [100.0, 120.0]), "c", "push"] and viewer.waiting == []


def test_a_recording_plays_at_the_speed_it_was_seen(monkeypatch):
    from types import SimpleNamespace

    from app.window import viewer
    frames = []
    window = SimpleNamespace(video=SimpleNamespace(append_data=frames.append), video_start=0.0,
                             video_frames=0)
    clock = iter([0.0, 0.5, 0.51, 2.0])                # seconds when four window frames were shown
    monkeypatch.setattr(viewer.time, "perf_counter", lambda: next(clock))
    for image in "abcd":
        viewer.Viewer.record(window, image)
    # At 30 frames per second each image fills the time since the one before; a quick one adds none.
    assert len(frames) == int(2.0 * viewer.VIDEO_FPS) + 1
    assert [frames.count(image) for image in "abcd"] == [1, 15, 0, 45]


# ---------------------------------------------------------------- the real window

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
WIDTH, HEIGHT = 640, 480


def missing_tools():
    """Why the window cannot be tested here, or None."""
    for tool in ("Xvfb", "xdotool", "import"):
        if shutil.which(tool) is None:
            return f"{tool} not installed (apt-get install xvfb xdotool imagemagick)"
    if ctypes.util.find_library("vulkan") is None:
        return "no Vulkan loader (apt-get install libvulkan1 mesa-vulkan-drivers)"
    icds = glob.glob("/usr/share/vulkan/icd.d/*.json") + glob.glob("/etc/vulkan/icd.d/*.json")
    if not icds:
        return "no Vulkan driver (apt-get install mesa-vulkan-drivers)"
    return None


@contextlib.contextmanager
def virtual_display(width, height):
    """A fresh virtual X screen of width x height pixels (Xvfb picks a free number); yields its
    DISPLAY value."""
    reason = missing_tools()
    if reason:
        pytest.skip(reason)
    read, write = os.pipe()
    server = subprocess.Popen(["Xvfb", "-displayfd", str(write), "-screen", "0", f"{width}x{height}x24",
                               "-nolisten", "tcp"], pass_fds=[write],
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    os.close(write)
    with os.fdopen(read) as f:
        number = f.readline().strip()
    if not number:
        server.kill()
        pytest.skip("Xvfb did not start")
    try:
        yield f":{number}"
    finally:
        server.terminate()
        server.wait(10)


@pytest.fixture
def display():
    with virtual_display(WIDTH, HEIGHT) as name:
        yield name


def xdotool(env, *args, timeout=300):
    return subprocess.run(["xdotool", *args], env=env, capture_output=True, text=True,
                          timeout=timeout, check=True).stdout


def pixel_of(point, camera_):
    """Window pixel (x right, y down) where a world point appears."""
    clip = camera_.view_proj(WIDTH / HEIGHT) @ np.append(point, 1.0)
    ndc = clip[:2] / clip[3]
    return round((ndc[0] + 1) / 2 * WIDTH), round((1 - ndc[1]) / 2 * HEIGHT)


# A loaded machine (4 CPU-bound processes beside the suite on 2 cores) draws the window about
# 3 times slower: every wait allows this long, and a passing run never waits it out.
PATIENCE = 300      # s


def wait_for(condition, what, timeout=PATIENCE):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if condition():
            return
        time.sleep(0.2)
    raise AssertionError(f"timed out after {timeout} s waiting for {what}")


def quit_window(env, wid, window, log_path):
    """Press Escape in the viewer's window and check that it ends with exit code 0."""
    try:
        xdotool(env, "key", "--window", wid, "Escape")
    except subprocess.CalledProcessError:
        # Seen twice in ~10 loaded suite runs: X said BadWindow for the id the keys before
        # reached while the viewer ran on. Look the window up again and press Escape there.
        # (Seen once more under load with the lookup failing too: then the key goes to the
        # focused window, the only one on this display.)
        try:
            again = xdotool(env, "search", "--onlyvisible", "--name", "softfem", timeout=60).split()
            xdotool(env, "key", "--window", again[0], "Escape")
        except (subprocess.CalledProcessError, IndexError):
            try:
                xdotool(env, "key", "Escape")
            except subprocess.CalledProcessError as failure:
                raise AssertionError(f"{getattr(failure, 'stderr', failure)} (window exit code "
                                     f"{window.poll()}):\n" + log_path.read_text()) from failure
    assert window.wait(30) == 0, log_path.read_text()


def stats_rows(path):
    """The complete rows the viewer has streamed into its stats file so far."""
    return [json.loads(line) for line in path.read_text().splitlines(keepends=True)
            if line.endswith("\n")] if path.exists() else []


def frames_after_event(folder, kind):
    """Complete stats rows streamed after the first event of `kind` (0 before it)."""
    rows = [json.loads(line) for part in folder.glob("s.jsonl")
            for line in part.read_text().splitlines(keepends=True) if line.endswith("\n")]
    frames = [row["frame"] for row in rows if any(e["type"] == kind for e in row["events"])]
    return sum(row["frame"] > frames[0] for row in rows) if frames else 0


# Two boxes at rest, no gravity: nothing moves until clicked.
RESTING_BOXES = """
name = "two resting boxes"
[solver]
dt = 0.01
[[body]]
name = "left"
mesh = { generator = "box", size = [1.0, 1.0, 1.0], cells = [2, 2, 2] }
material = { E = 1e4, nu = 0.3, density = 100.0 }
position = [-0.8, 0.0, 0.0]
[[body]]
name = "right"
mesh = { generator = "box", size = [1.0, 1.0, 1.0], cells = [2, 2, 2] }
material = { E = 1e4, nu = 0.3, density = 100.0 }
position = [0.8, 0.0, 0.0]
"""


def test_click_pushes_the_body_and_c_flips_the_method(display, tmp_path):
    """A click made a second after the window appears, while the kernels compile, is kept and
    pushes the body once they are ready; then c, l and t, once it steps."""
    import scenes
    from app.window.viewer import initial_camera
    from PIL import Image

    scene_file = tmp_path / "boxes.toml"
    scene_file.write_text(RESTING_BOXES)
    scene = scenes.load_scene(scene_file)
    body = scene.bodies[1].mesh.vertices
    rest = np.concatenate([b.mesh.vertices for b in scene.bodies])
    target = pixel_of(body.mean(axis=0), initial_camera(rest, scene.camera, WIDTH, HEIGHT))

    env = dict(os.environ, DISPLAY=display)
    stats = tmp_path / "s.jsonl"
    log = open(tmp_path / "view.log", "w")
    window = subprocess.Popen([sys.executable, os.path.join(ROOT, "main.py"), "view", str(scene_file),
                               "--stats", str(stats), "--size", f"{WIDTH}x{HEIGHT}"],
                              cwd=tmp_path, env=env, stdout=log, stderr=subprocess.STDOUT)
    try:
        wid = xdotool(env, "search", "--sync", "--onlyvisible", "--name", "softfem").split()[0]
        time.sleep(1.0)
        xdotool(env, "mousemove", "--window", wid, str(target[0]), str(target[1]), "click", "1")
        # The stats file streams rows as the frames come (`tail -f` follows it).
        wait_for(lambda: frames_after_event(tmp_path, "click") >= 10, "frames after the click")
        xdotool(env, "key", "--window", wid, "c")
        wait_for(lambda: frames_after_event(tmp_path, "methods") >= 10, "frames after the toggle")
        xdotool(env, "key", "--window", wid, "l")
        wait_for(lambda: frames_after_event(tmp_path, "preconditioner") >= 5, "frames after l")
        xdotool(env, "key", "--window", wid, "t")       # no contact here: the panel says so, nothing drawn
        wait_for(lambda: frames_after_event(tmp_path, "contact_points") >= 5, "frames after t")
        subprocess.run(["import", "-window", "root", str(tmp_path / "shot.png")], env=env,
                       check=True, timeout=120)
        log.flush()
        quit_window(env, wid, window, tmp_path / "view.log")
    finally:
        if window.poll() is None:
            window.kill()
        log.close()

    shot = np.asarray(Image.open(tmp_path / "shot.png").convert("RGB"), float)
    assert shot.std() > 10, "the screenshot is blank"

    rows = [json.loads(line) for line in stats.read_text().splitlines()]
    events = [(row["frame"], e) for row in rows for e in row["events"]]
    clicks = [(frame, e) for frame, e in events if e["type"] == "click"]
    assert len(clicks) == 1, f"the click at {target} did not hit a body: {events}"
    click_frame, click = clicks[0]
    assert click["body"] == 1 and click["vertices"] > 0
    # Made while the kernels compiled: applied in the first frame that steps, where the start's
    # compiling ends, after waiting for it.
    compiled = [(frame, e) for frame, e in events if e["type"] == "compiled"]
    assert len(compiled) == 1 and compiled[0][1]["kernels"] > 0
    assert click_frame == compiled[0][0] and click["waited_s"] > 0.2, (click, compiled)
    before = [r["kinetic_energy"] for r in rows if r["frame"] < click_frame]
    after = [r["kinetic_energy"] for r in rows if r["frame"] > click_frame]
    assert before and max(before) < 1e-9          # at rest, up to rounding
    assert max(after) > 1e-3

    toggles = [e for _, e in events if e["type"] == "methods"]
    assert toggles and toggles[-1]["methods"] == ["linear", "linear"]
    stepped = [r["corotational"] for r in rows if "corotational" in r]
    assert stepped[0] == [True, True] and stepped[-1] == [False, False]

    switched = [(frame, e) for frame, e in events if e["type"] == "preconditioner"]
    assert [e["preconditioner"] for _, e in switched] == ["two-level"]   # auto -> two-level
    before = {r["preconditioner"] for r in rows if r["frame"] < switched[0][0] and "preconditioner" in r}
    after = {r["preconditioner"] for r in rows if r["frame"] > switched[0][0] and "preconditioner" in r}
    assert before == {"jacobi"} and after == {"two-level"}   # auto picked block Jacobi on these small boxes
    assert [e["shown"] for _, e in events if e["type"] == "contact_points"] == [True]


# A box 15 mm above a fixed block, moving down at 0.6 m/s (a start closer than the contact distance,
# 1 cm, is refused): inside the contact distance from the first step on, and it stays there.
BOX_ON_A_BLOCK = """
name = "box on a block"
[solver]
dt = 0.02
[effects]
gravity = [0.0, -9.81, 0.0]
damping = { alpha = 2.0, beta = 0.0 }
contact = { distance = 0.01, friction = 0.5 }
[camera]
eye = [1.6, 1.4, 2.4]
target = [0.0, 0.45, 0.0]
[[body]]
name = "block"
fixed = true
mesh = { generator = "box", size = [1.0, 0.4, 1.0], cells = [2, 1, 2] }
material = { E = 1e5, nu = 0.3, density = 1000.0 }
position = [0.0, 0.2, 0.0]
[[body]]
name = "box"
mesh = { generator = "box", size = [0.5, 0.5, 0.5], cells = [2, 2, 2] }
material = { E = 1e5, nu = 0.3, density = 1000.0 }
position = [0.0, 0.665, 0.0]
[[initial]]
body = "box"
velocity = [0.0, -0.6, 0.0]
"""


def test_t_marks_where_the_box_touches_the_block(display, tmp_path):
    import scenes
    from app.render.overlay import CONTACT_COLOR
    from app.window.viewer import initial_camera
    from PIL import Image

    scene_file = tmp_path / "box_on_a_block.toml"
    scene_file.write_text(BOX_ON_A_BLOCK)
    scene = scenes.load_scene(scene_file)
    camera_ = initial_camera(np.concatenate([b.mesh.vertices for b in scene.bodies]), scene.camera,
                             WIDTH, HEIGHT)
    env = dict(os.environ, DISPLAY=display)
    stats = tmp_path / "s.jsonl"
    log = open(tmp_path / "view.log", "w")
    window = subprocess.Popen([sys.executable, os.path.join(ROOT, "main.py"), "view", str(scene_file),
                               "--stats", str(stats), "--size", f"{WIDTH}x{HEIGHT}", "--out", str(tmp_path)],
                              cwd=tmp_path, env=env, stdout=log, stderr=subprocess.STDOUT)

    def shots():
        return [e["path"] for row in stats_rows(stats) for e in row["events"] if e["type"] == "screenshot"]

    try:
        wid = xdotool(env, "search", "--sync", "--onlyvisible", "--name", "softfem").split()[0]
        wait_for(lambda: any(row.get("contact_pairs") for row in stats_rows(stats)), "steps in contact")
        xdotool(env, "key", "--window", wid, "p")                    # the window's own screenshots
        wait_for(lambda: len(shots()) == 1, "the screenshot before t")
        xdotool(env, "key", "--window", wid, "t")
        wait_for(lambda: frames_after_event(tmp_path, "contact_points") >= 3, "frames after t")
        xdotool(env, "key", "--window", wid, "p")
        wait_for(lambda: len(shots()) == 2, "the screenshot after t")
        log.flush()
        quit_window(env, wid, window, tmp_path / "view.log")
    finally:
        if window.poll() is None:
            window.kill()
        log.close()

    rows = stats_rows(stats)
    assert [e["shown"] for row in rows for e in row["events"] if e["type"] == "contact_points"] == [True]
    assert all(row["contact_pairs"] > 0 for row in rows if row["frame"] > 1)
    before, after = (np.asarray(Image.open(path).convert("RGB")) for path in shots())
    assert before.shape == (HEIGHT, WIDTH, 3)
    assert not (before == CONTACT_COLOR).all(axis=-1).any()
    ys, xs = np.nonzero((after == CONTACT_COLOR).all(axis=-1))
    assert len(xs) > 50
    # Every dot on the block's top (y = 0.4 m), under the box (0.5 m wide), as the window's camera
    # sees it, give or take a dot's radius (3 pixels here) and its outline.
    footprint = np.array([pixel_of([x, 0.4, z], camera_) for x in (-0.25, 0.25) for z in (-0.25, 0.25)])
    lo, hi = footprint.min(axis=0) - 5, footprint.max(axis=0) + 5
    assert lo[0] <= xs.min() and xs.max() <= hi[0] and lo[1] <= ys.min() and ys.max() <= hi[1]
    # ... and over all of it: the dots reach its four corners.
    assert (xs.max() - xs.min()) > 0.8 * np.ptp(footprint[:, 0])


def test_view_without_a_display_is_one_clear_error():
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY")}
    for extra in ({}, {"DISPLAY": ":987"}):
        run = subprocess.run([sys.executable, "main.py", "view", "cube86"], cwd=ROOT, env={**env, **extra},
                             capture_output=True, text=True, timeout=300)
        assert run.returncode == 2
        assert run.stderr.startswith("error: view: no") and len(run.stderr.splitlines()) == 1


def test_the_benchmark_times_the_windows_first_frames(display):
    from app.bench import startup

    numbers = startup.view_seconds("cube86", repeats=1, display=display)
    assert set(numbers) == {"view_first_s", "view_stepped_s"}
    assert 0 < numbers["view_first_s"] < numbers["view_stepped_s"]


# ---------------------------------------------------------------- the panel on a whole screen

# Text the panel shows at its right end, whole, at either size (cut off, they read "str", "rac"),
# and before the first step "t = 0.00 s" (tesseract reads its "t" as anything).
WHOLE_LABELS = ["[h] help", "strength [m/s]", "radius [m]", "(--contact)"]


@pytest.fixture(scope="module", params=[(1280, 720), (1920, 1080)], ids=lambda size: f"{size[0]}x{size[1]}")
def compare_shots(request, tmp_path_factory):
    """`view epcot --compare` filling a virtual screen of its own size: the screen before the
    first step (a second after the first frame, while the kernels compile: "compiling" says
    whether they still did when it was taken) and after a few steps, the window's place on the
    screen, and the stats rows."""
    width, height = request.param
    folder = tmp_path_factory.mktemp(f"compare{width}")
    with virtual_display(width, height) as name:
        env = dict(os.environ, DISPLAY=name)
        stats = folder / "s.jsonl"
        log = open(folder / "view.log", "w")
        window = subprocess.Popen([sys.executable, os.path.join(ROOT, "main.py"), "view", "epcot", "--compare",
                                   "--size", f"{width}x{height}", "--stats", str(stats)],
                                  cwd=folder, env=env, stdout=log, stderr=subprocess.STDOUT)

        from PIL import Image

        def screenshot(name):
            subprocess.run(["import", "-window", "root", str(folder / name)], env=env, check=True, timeout=120)
            return np.asarray(Image.open(folder / name).convert("RGB"))

        try:
            wid = xdotool(env, "search", "--sync", "--onlyvisible", "--name", "softfem").split()[0]
            wait_for(lambda: stats_rows(stats), "the first frame")
            # The window's frames while warm_up compiles, a few times a second, once its first kernel
            # is announced: on a loaded machine that can be seconds after the first frame (drawn at rest
            # with the whole panel), so the screen is taken until it shows them or the steps began.
            for _ in range(20):
                time.sleep(0.5)
                before = screenshot("before.png")
                compiling = not any(row["step"] > 0 for row in stats_rows(stats))
                if not compiling or re.search(COMPILING, read_text(before[:, panel_columns(before)[0]:])):
                    break
            # A few frames after the first steps, so that the frame rate is measured.
            wait_for(lambda: sum(row["step"] > 0 for row in stats_rows(stats)) >= 4, "frames after the first steps")
            after = screenshot("after.png")
            geometry = xdotool(env, "getwindowgeometry", "--shell", wid)
            log.flush()
            quit_window(env, wid, window, folder / "view.log")
        finally:
            if window.poll() is None:
                window.kill()
            log.close()
    place = dict(line.split("=") for line in geometry.split())
    return {"size": (width, height), "before": before, "compiling": compiling, "after": after,
            "rows": stats_rows(stats),
            "window": [int(place[k]) for k in ("X", "Y", "WIDTH", "HEIGHT")]}


COMPILING = r"compiling kernels. \d+"      # the panel's line while kernels compile, as tesseract reads it


def text_pixels(image):
    """Where image (H, W, 3) uint8 shows the panel's text: white (GGUI draws it unblended)."""
    image = image.astype(int)
    return (image.min(axis=-1) >= 170) & (np.ptp(image, axis=-1) <= 25)


def panel_columns(shot):
    """(left, right, inner): the columns where the dark panel at the right edge of a screenshot
    (H, W, 3) begins and ends, and where its room for text ends (before its scroll bar, if any)."""
    height = shot.shape[0]
    rows = shot[height // 10: 9 * height // 10].astype(int)
    grab = (np.abs(rows - 79) <= 12).all(axis=-1)      # a scroll bar's grey grab
    # The panel's background and widgets are dark; the view (sky, bodies) is mostly light.
    dark = (rows.max(axis=-1) < 130).mean(axis=0) > 0.6
    right = len(dark)
    while right > len(dark) - 8 and not dark[right - 1]:      # a column or two of the view may show
        right -= 1
    left = right
    while left > 0 and dark[left - 1]:
        left -= 1
    inner = right - 14 if grab[:, right - 14: right].sum(axis=0).max() >= 20 else right
    return left, right, inner


def test_the_window_and_its_panel_fit_the_screen(compare_shots):
    width, height = compare_shots["size"]
    x, y, w, h = compare_shots["window"]
    for shot in (compare_shots["before"], compare_shots["after"]):
        left, right, inner = panel_columns(shot)
        assert 0.5 * width < left < width - 250, f"no panel at the right edge (from column {left})"
        # GGUI cuts text 4 pixels inside the panel's edge; text that fits ends 8 pixels inside.
        ys, xs = np.nonzero(text_pixels(shot[:, left:inner]))
        cut = sorted(set(ys[xs >= inner - left - 7].tolist()))
        assert not cut, f"text cut at the panel's right edge (column {inner}) in screen rows {cut[:3]}..."
    assert (x, y, x + w, y + h) == (0, 0, width, height), "the window does not fill the screen"


def test_the_compare_labels_are_not_empty_black_boxes(compare_shots):
    for shot in (compare_shots["before"], compare_shots["after"]):
        top = shot[: shot.shape[0] // 8, : panel_columns(shot)[0]]
        black = top.max(axis=-1) < 40
        assert black.sum() < 50, f"{black.sum()} black pixels at the top of the view"


def read_text(image, scale=3):
    """The text tesseract reads in image (H, W, 3) uint8: its white text, black on white,
    enlarged scale times (GGUI's 13-pixel font is too small for it)."""
    from PIL import Image
    text = Image.fromarray(np.where(text_pixels(image), 0, 255).astype(np.uint8))
    path = f"/tmp/ocr-{os.getpid()}.png"
    text.resize((scale * text.width, scale * text.height), Image.BICUBIC).save(path)
    try:
        return subprocess.run(["tesseract", path, "-", "--psm", "6"], capture_output=True, text=True,
                              check=True, timeout=120).stdout.replace(",", ".")   # "0,02": its misreading
    finally:
        os.remove(path)


@pytest.mark.skipif(shutil.which("tesseract") is None, reason="tesseract not installed (apt-get install tesseract-ocr)")
def test_the_panel_reads_whole_and_shows_no_figure_before_it_is_measured(compare_shots):
    before, after = compare_shots["before"], compare_shots["after"]
    first = read_text(before[:, panel_columns(before)[0]:])
    assert re.search(r"= \d\.\d\d s", first), first      # "t = 0.00 s" (its 0 reads as 8 at times)
    if compare_shots["compiling"]:       # "epcot: compiling kernels, 12 of 40 (3 s)"
        assert re.search(COMPILING, first), first
    assert "nan" not in first.lower(), first
    assert not re.search(r"\d[ \t]*fps", first), f"a frame rate before any frame was timed:\n{first}"
    text = read_text(after[:, panel_columns(after)[0]:])
    missing = [label for label in WHOLE_LABELS if label not in text]
    assert not missing, f"not read whole: {missing} in\n{text}"
    fps = re.search(r"([\d.]+) fps", text)
    assert fps and 0 < float(fps.group(1)) < 1000, text
    labels = read_text(after[: after.shape[0] // 8, : panel_columns(after)[0]], scale=1)
    assert "linear" in labels and "corotational" in labels, labels
