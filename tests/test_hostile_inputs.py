"""Issue 37's hostile inputs, past what tests/test_hostile.py checks (one `error:` line, exit 2):
the numbers and the way out each message gives, the right result where the answer is to run,
an export whose folder is removed while it writes, and environments, through subprocesses.

`S.toml` is the issue's scene: a 1 m box of 2 x 2 x 2 cells (40 tets), E 2 kPa, nu 0.3,
density 100 kg/m^3, moving at 1 m/s (50 J of kinetic energy).
"""

import os
import re
import shutil
import subprocess
import sys

import numpy as np
import pytest
from PIL import Image

from app.commands import export
from test_cli import ROOT, final_error_line, one_error_line, run

S = """\
[[body]]
name = "b"
mesh = {generator = "box", size = [1, 1, 1], cells = [2, 2, 2]}
material = {E = 2e3, nu = 0.3, density = 100}

[[initial]]
velocity = [1, 0, 0]
"""
TET = ("MeshVersionFormatted 1\nDimension 3\nVertices\n4\n0 0 0 0\n1 0 0 0\n0 1 0 0\n0 0 1 0\n"
       "Tetrahedra\n1\n1 2 3 4 0\nEnd\n")


@pytest.fixture
def here(tmp_path, monkeypatch):
    """An empty current folder holding S.toml, with a mesh cache of its own."""
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("FEM_CACHE_DIR", str(tmp_path / "cache"))
    (tmp_path / "S.toml").write_text(S)
    return tmp_path


def summary_number(stdout, name):
    """A number of the summary's energy line, e.g. summary_number(out, "total") -> 50.0."""
    return float(re.search(rf"{name} ([-\d.e+]+) J", stdout)[1])


# ---------------------------------------------------------------- sizes: the numbers in the message

@pytest.mark.parametrize("setting", ["body.0.mesh.cells=[1e20,1,1]", "body.0.mesh.cells=[-1e20,1,1]",
                                     "body.0.mesh.cells=[1e200,1e200,1e200]"])
def test_a_box_of_more_cells_than_an_int32_holds_is_refused(here, setting):
    """1e20 was a TypeError; 1e200 an OverflowError in the memory the message names."""
    code, _, err = run("simulate", "S.toml", "--steps", "1", "--set", setting)
    assert code == 2
    one_error_line(err, "body 'b'.mesh: cells[0] must be an integer between -2,147,483,647 and 2,147,483,647")


@pytest.mark.parametrize("scene", ["fertility", "epcot"])
def test_a_resolution_of_1e20_is_refused(here, scene):
    code, _, err = run("simulate", scene, "--steps", "1", "--set", "body.0.mesh.resolution=1e20")
    assert code == 2
    one_error_line(err, "resolution must be an integer between", "got 1e+20")


@pytest.mark.parametrize("scene, resolution", [("fertility", 12345678), ("epcot", 2_000_000),
                                               ("epcot", 2**31 - 1)])
def test_a_lattice_of_huge_resolution_names_its_cell_count_unwrapped(here, scene, resolution):
    """The count was an int64 that wrapped (negative, or too small to pass the limit)."""
    code, _, err = run("simulate", scene, "--steps", "1", "--set", f"body.0.mesh.resolution={resolution}")
    assert code == 2
    line = one_error_line(err, "cells (at least one tet each) is more than the limit", "GB of memory")
    cells = float(re.search(r"a lattice of ([\d,.e+]+) cells", line)[1].replace(",", ""))
    assert 0.1 * resolution**3 < cells < 10 * resolution**3


def test_a_count_past_any_float_is_still_refused_with_a_message():
    """From Python, cells of 1e200 each made an integer that no float holds: the memory in the
    message raised OverflowError."""
    from assets.generators import box
    from fem.errors import SizeLimitError
    with pytest.raises(SizeLimitError, match=r"5\.00e\+600 tets is more than the limit .* about 2\.75e\+594 GB"):
        box(cells=(10**200, 10**200, 10**200))


def test_a_scene_file_over_the_limit_is_refused_before_parsing_and_says_the_limit(here):
    """A 240 MB TOML took 6 GB and three minutes to fail; 17 MB is refused before it is read."""
    (here / "big.toml").write_text(f'name = "{"a" * 17 * 2**20}"\n')
    code, _, err = run("simulate", "big.toml", "--steps", "1")
    assert code == 2
    one_error_line(err, "big.toml: a file of 17 MB is more than the limit of 16 MB", "--allow-large")


def test_a_coursework_scene_file_over_the_scene_limit_is_refused(here):
    """Split into words, a coursework file takes about 15 times its size: 256 MB would be 4 GB."""
    (here / "big-scene.txt").write_text("1\ntet.mesh 100 200 0.1 0 0 0 0 1 0 0 0\n" + "12345 " * 3 * 2**20)
    code, _, err = run("simulate", "big-scene.txt", "--steps", "1")
    assert code == 2
    one_error_line(err, "big-scene.txt: a file of 18 MB is more than the limit of 16 MB")


# ---------------------------------------------------------------- meshes with no shape

@pytest.mark.parametrize("side", [0.0, 1e-200], ids=["a point", "1e-200 m"])
def test_a_closed_surface_of_no_size_is_refused(here, side):
    """Was a ZeroDivisionError in the one-body scene made of a mesh file."""
    corners = [(0, 0, 0), (side, 0, 0), (0, side, 0), (0, 0, side)]
    (here / "point.obj").write_text("".join(f"v {x} {y} {z}\n" for x, y, z in corners)
                                    + "f 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n")
    code, _, err = run("simulate", "point.obj", "--steps", "1")
    assert code == 2
    one_error_line(err, "point.obj: every vertex is at the same point")


def test_a_mesh_of_one_tet_twice_is_refused_before_the_export(here):
    """Two copies of one tet leave no surface to draw: export failed on an empty array."""
    (here / "twice.mesh").write_text(TET.replace("Tetrahedra\n1\n1 2 3 4 0\n", "Tetrahedra\n2\n1 2 3 4 0\n1 2 3 4 0\n"))
    code, _, err = run("export", "twice.mesh", "--frames", "1", "--size", "64x48", "--out", "o")
    assert code == 2
    one_error_line(err, "twice.mesh:11: tet 0 (vertices [0, 1, 2, 3]) appears 2 times")
    assert not (here / "o").exists() or not any((here / "o").iterdir())


def test_a_truncated_cache_entry_of_a_generated_mesh_is_rebuilt(here):
    """The README promises a rebuild of a damaged cache entry; this was a BadZipFile."""
    assert run("simulate", "epcot", "--steps", "1")[0] == 0
    [entry] = (here / "cache").glob("generated-*.npz")
    entry.write_bytes(entry.read_bytes()[:-40])
    code, out, err = run("simulate", "epcot", "--steps", "1")
    assert code == 0, err
    assert "1 step to t =" in out
    assert entry.stat().st_size > 1000                 # rebuilt in place


def test_a_cache_entry_that_is_a_folder_is_built_around_and_leaves_nothing(here):
    """Each run left a temporary file of the mesh in the cache, which it could not rename."""
    assert run("simulate", "epcot", "--steps", "1")[0] == 0
    [entry] = (here / "cache").glob("generated-*.npz")
    entry.unlink()
    entry.mkdir()
    code, out, err = run("simulate", "epcot", "--steps", "1")
    assert code == 0, err
    assert "warning: could not cache the tet mesh" in err and "1 step to t =" in out
    assert [path.name for path in (here / "cache").iterdir()] == [entry.name]


# ---------------------------------------------------------------- an export whose folder goes away

def remove_after(monkeypatch, frames, folder):
    """Make the export remove `folder` (its --out, or the working folder) once `frames` frames
    are written, as `rm -r` from another terminal would."""
    written = []

    def write_png(path, image, kept=""):
        if len(written) == frames:
            shutil.rmtree(folder)
        write_png_before(path, image, kept)
        written.append(path)

    write_png_before = export.write_png
    monkeypatch.setattr(export, "write_png", write_png)


def test_an_export_whose_out_folder_is_removed_says_its_frames_went_with_it(here, monkeypatch):
    """The folder was made again for the later frames, and the run said it wrote them all."""
    remove_after(monkeypatch, 2, here / "o")
    code, out, err = run("export", "S.toml", "--frames", "5", "--size", "64x48", "--out", "o")
    assert code == 2
    final_error_line(err, "--out o was removed while this run wrote into it; the 2 frames written before "
                          "went with it")
    assert "wrote" not in out
    assert not (here / "o").exists()


def test_an_export_whose_working_folder_is_removed_says_its_frames_went_with_it(here, monkeypatch):
    (here / "w").mkdir()
    monkeypatch.chdir(here / "w")
    remove_after(monkeypatch, 3, here / "w")
    code, _, err = run("export", str(here / "S.toml"), "--frames", "5", "--size", "64x48", "--out", "o")
    assert code == 2
    final_error_line(err, "--out o was removed while this run wrote into it; the 3 frames written before "
                          "went with it")
    assert not (here / "w").exists()


def test_an_export_whose_folder_and_video_are_removed_is_one_error(here, monkeypatch):
    """The video's check of the free space raised FileNotFoundError on its removed folder."""
    remove_after(monkeypatch, 2, here / "all")
    code, _, err = run("export", "S.toml", "--frames", "4", "--size", "64x48", "--out", "all/o",
                       "--video", "all/v.mp4")
    assert code == 2
    final_error_line(err, "all/v.mp4: its folder was removed while this run wrote into it; the video was "
                          "not written", "--out all/o was removed")
    assert not (here / "all").exists()


# ---------------------------------------------------------------- results that looked valid

def test_f32_far_from_the_origin_is_refused_and_f64_gives_the_right_result(here):
    """1 cm tets 100 km away: f32 reported a body at rest with volume ratio 1.557."""
    far = ["--set", "body.0.position=[1e5,0,0]", "--set", "body.0.scale=0.01", "--set", "initial=[]"]
    code, _, err = run("simulate", "S.toml", "--steps", "1", *far)
    assert code == 2
    one_error_line(err, "S.toml: body 'b': 1e+05 m from the origin, f32 rounds coordinates to 0.012 m",
                   "use precision f64")
    f64 = subprocess.run([sys.executable, str(ROOT / "main.py"), "simulate", "S.toml", "--steps", "5",
                          "--precision", "f64", *far], cwd=here, capture_output=True, text=True, timeout=600)
    assert f64.returncode == 0, f64.stderr
    assert "volume ratio now 1.0000" in f64.stdout


@pytest.mark.parametrize("nu", ["0.49999999999999994", "0.4999999999999", "0.49999999999"])
def test_nu_closer_to_one_half_than_f32_can_hold_is_refused(here, nu):
    """The energy went from 50 J to 9e5 J (0.49999999999999994) or 55 J (0.49999999999)."""
    code, _, err = run("simulate", "S.toml", "--steps", "1", "--set", f"body.0.material.nu={nu}")
    assert code == 2
    one_error_line(err, f"nu = {nu} makes lam", "more than f32 can add mu to; use nu <= 0.4999994 or "
                                                "precision f64")


def test_nu_near_one_half_that_f32_can_hold_keeps_the_energy(here):
    code, out, err = run("simulate", "S.toml", "--steps", "20", "--set", "body.0.material.nu=0.49999")
    assert code == 0, err
    assert summary_number(out, "total") == pytest.approx(50, rel=0.02)


@pytest.mark.parametrize("eye", [[0, 5, 0], [0, -5, 0]], ids=["top-down", "bottom-up"])
def test_a_camera_straight_above_its_target_draws_the_body(here, eye):
    """The frames were blank: the look-at basis was 0 / 0."""
    code, _, err = run("export", "S.toml", "--frames", "1", "--size", "64x48", "--out", "o", "--set",
                       f"camera={{eye={eye}, target=[0, 0, 0]}}")
    assert code == 0, err
    image = np.asarray(Image.open(here / "o" / "frame_00000.png")).astype(int)
    body = image[..., 0] > image[..., 2] + 40          # the box is orange, the sky blue-grey
    assert body.mean() > 0.005                         # a blank frame has none


def test_a_camera_whose_eye_is_its_target_is_refused(here):
    code, _, err = run("export", "S.toml", "--frames", "1", "--size", "64x48", "--out", "o", "--set",
                       "camera={eye=[1, 1, 1], target=[1, 1, 1]}")
    assert code == 2
    one_error_line(err, "camera: eye and target are the same point")


def test_a_coursework_quaternion_of_1e300_rotates_the_body(here):
    """Its norm overflowed to inf and the body was placed unrotated."""
    from fem.coursework import read_coursework_scene
    (here / "tet.mesh").write_text(TET)

    def placed(quaternion):
        (here / "q-scene.txt").write_text(f"1\ntet.mesh 100 200 0.1 0 0 0 0 {quaternion}\n0\n")
        return read_coursework_scene(here / "q-scene.txt").bodies[0].mesh.vertices

    np.testing.assert_allclose(placed("1e300 1e300 0 0"), placed("1 1 0 0"), atol=1e-12)
    assert np.abs(placed("1 1 0 0") - placed("1 0 0 0")).max() > 0.1



def test_a_scene_quaternion_of_1e_300_rotates_the_body(here):
    """Its norm underflowed to 0, and the quaternion was refused as zero."""
    from scenes import load_scene

    def placed(rotation):
        return load_scene("S.toml", overrides=[f"body.0.rotation={rotation}"]).bodies[0].mesh.vertices

    np.testing.assert_allclose(placed("[1e-300, 1e-300, 0, 0]"), placed("[1, 1, 0, 0]"), atol=1e-12)
    assert np.abs(placed("[1, 1, 0, 0]") - placed("[1, 0, 0, 0]")).max() > 0.1

# ---------------------------------------------------------------- did you mean

@pytest.mark.parametrize("argv, hint", [(["simulat", "epcot"], "no command 'simulat'; did you mean simulate?"),
                                        (["exprot"], "no command 'exprot'; did you mean export?"),
                                        (["help", "simulat"], "no command 'simulat'; did you mean simulate?"),
                                        (["simulate", "epcot", "--stpes=3"], "--stpes=3; did you mean --steps?"),
                                        (["simulate", "epcot", "--fps", "3"], "--fps 3; --fps is an option of export"),
                                        (["simulate", "epcot", "--quick"], "--quick is an option of bench and figures")])
def test_a_mistyped_command_or_option_gets_a_did_you_mean(here, argv, hint):
    """Another command's option was answered 'did you mean' itself (--frames), or a look-alike
    (--fps: 'did you mean --steps?')."""
    code, _, err = run(*argv)
    assert code == 2
    one_error_line(err, hint)


# ---------------------------------------------------------------- the environment (subprocesses)

def main_py(folder, *argv, env):
    """main.py argv in folder, with the environment changed as env says (a value None unsets)."""
    changed = {**os.environ, "FEM_CACHE_DIR": str(folder / "cache"), **env}
    changed = {name: value for name, value in changed.items() if value is not None}
    return subprocess.run([sys.executable, str(ROOT / "main.py"), *argv], cwd=folder, env=changed,
                          capture_output=True, text=True, timeout=600)


@pytest.mark.parametrize("name, value", [("TI_CPU_MAX_NUM_THREADS", "-1"), ("TI_CPU_MAX_NUM_THREADS", "\u00b2"),
                                         ("TI_LOG_LEVEL", "WARN")])
def test_a_taichi_variable_it_cannot_use_is_one_error_line_before_taichi_starts(here, name, value):
    """'\u00b2' passed str.isdigit() and failed int(); Taichi takes log levels in lower case only
    (both were tracebacks)."""
    run_ = main_py(here, "simulate", "S.toml", "--steps", "1", env={name: value})
    assert run_.returncode == 2
    one_error_line(run_.stderr, f"environment variable {name}={value!r}")


def test_an_empty_home_still_runs(here):
    """HOME unset aborted `import taichi` (SIGABRT); an empty HOME is the same to Taichi."""
    run_ = main_py(here, "simulate", "S.toml", "--steps", "1", env={"HOME": ""})
    assert run_.returncode == 0, run_.stderr
    assert "1 step to t =" in run_.stdout


def test_a_non_ascii_scene_name_on_an_ascii_terminal_is_one_error_line(here):
    """Was a UnicodeEncodeError while printing the error."""
    run_ = main_py(here, "simulate", "épcot", "--steps", "1", env={"PYTHONIOENCODING": "ascii"})
    assert run_.returncode == 2
    one_error_line(run_.stderr, "\\xe9pcot: no such scene file or built-in scene", "did you mean 'epcot'?")



def test_a_run_started_in_a_removed_folder_is_one_error_line(here):
    """Taichi's start asks for the current folder: a FileNotFoundError traceback."""
    (here / "gone").mkdir()
    run_ = subprocess.run(["bash", "-c", f'cd gone && rmdir ../gone && exec "{sys.executable}" '
                                         f'"{ROOT / "main.py"}" simulate ../S.toml --steps 1'],
                          cwd=here, capture_output=True, text=True, timeout=600)
    assert run_.returncode == 2
    one_error_line(run_.stderr, "the current folder was removed; change to one that exists")


def test_no_cache_folder_taichi_can_write_is_one_error_line(here):
    """With neither the asked folder nor the temporary one usable, Taichi ran without a cache and
    crashed at exit (SIGSEGV, exit 139) after the run's output."""
    (here / "tmp").mkdir()
    (here / "tmp" / f"softfem-taichi-cache-{os.getuid()}").write_text("not a folder")
    run_ = main_py(here, "simulate", "S.toml", "--steps", "1", env={"HOME": "/dev/null", "XDG_CACHE_HOME": None,
                                                                    "TMPDIR": str(here / "tmp")})
    assert run_.returncode == 2
    one_error_line(run_.stderr, "kernel cache folder /dev/null/.cache/taichi/ticache cannot be written, nor",
                   "set TI_OFFLINE_CACHE_FILE_PATH to a folder you can write")
