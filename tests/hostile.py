"""Input a hostile user would try (issue 24): each case is a command line and the files it needs,
run through `main.main` in a fresh folder. `tests/test_hostile.py` checks every case gives one
`error:` line and exit 2 (or runs, where that is the answer); `tools/robustness_table.py` lists
them in docs/robustness.md with what the program printed.
"""

import contextlib
import io
import os
import stat
from dataclasses import dataclass, field
from pathlib import Path

LONG = "a" * 300                      # longer than a file name may be (255 bytes)


def many_bodies(count):
    return "".join(f'[[body]]\nname = "b{i}"\nmesh = {{generator = "box", cells = [1, 1, 1]}}\n'
                   f'material = {{E = 1e4, nu = 0.3}}\nposition = [{2 * i}, 0, 0]\n' for i in range(count))


def sparse(size):
    """A file of `size` bytes that takes no disk (a hole)."""
    def make(path):
        with open(path, "wb") as f:
            f.truncate(size)
    return make


def text(content):
    return lambda path: Path(path).write_text(content)


def fifo(path):
    os.mkfifo(path)


def character_device(path):
    """A copy of /dev/null (root only; elsewhere a FIFO stands in)."""
    try:
        os.mknod(path, 0o666 | stat.S_IFCHR, os.makedev(1, 3))
    except PermissionError:
        os.mkfifo(path)


def open_sphere(path):
    """An icosphere with one face removed: a surface with a hole."""
    import trimesh
    sphere = trimesh.creation.icosphere(2)
    sphere.faces = sphere.faces[1:]
    sphere.export(path)


@dataclass
class Hostile:
    kind: str                          # the class of input, as docs/robustness.md groups them
    name: str
    argv: list
    files: dict = field(default_factory=dict)    # {name: make(path)}
    exit: int = 2                      # the expected exit code


HOSTILE = [
    Hostile("special file", "--video is a FIFO", ["export", "cube", "--frames", "2", "--video", "v.mp4"],
            {"v.mp4": fifo}),
    Hostile("special file", "--out is a FIFO", ["export", "cube", "--frames", "2", "--out", "o"], {"o": fifo}),
    Hostile("special file", "--stats is a character device (streamed to)",
            ["simulate", "cube", "--steps", "2", "--stats", "mynull"], {"mynull": character_device}, exit=0),
    Hostile("size", "box of 1500^3 cells", ["simulate", "cube", "--set", "body.0.mesh.cells=[1500,1500,1500]"]),
    Hostile("size", "box of 2000^3 cells", ["simulate", "cube", "--set", "body.0.mesh.cells=[2000,2000,2000]"]),
    Hostile("size", "10000 bodies", ["simulate", "many.toml"], {"many.toml": text(many_bodies(10_000))}),
    Hostile("size", "a 3 GB mesh file", ["simulate", "big.mesh"], {"big.mesh": sparse(3 * 2**30)}),
    Hostile("size", "a 3 GB surface file", ["simulate", "big.obj"], {"big.obj": sparse(3 * 2**30)}),
    Hostile("size", "dome with a million legs", ["simulate", "epcot", "--set", "body.0.mesh.legs=1000000"]),
    Hostile("size", "statue of resolution 100000", ["simulate", "fertility", "--set",
                                                     "body.0.mesh.resolution=100000"]),
    Hostile("size", "frames of 100000 x 100000 pixels", ["export", "cube", "--size", "100000x100000"]),
    Hostile("time", "--speed 1e300", ["export", "cube", "--frames", "2", "--speed", "1e300"]),
    Hostile("time", "--fps 1e-9", ["export", "cube", "--frames", "2", "--fps", "1e-9"]),
    Hostile("number", "E = 1e308", ["simulate", "cube", "--set", "body.0.material.E=1e308"]),
    Hostile("number", "E = 1e14", ["simulate", "cube", "--set", "body.0.material.E=1e14"]),
    Hostile("number", "density = 1e308", ["simulate", "cube", "--set", "body.0.material.density=1e308"]),
    Hostile("number", "position 1e308 m", ["simulate", "cube", "--set", "body.0.position=[1e308, 0, 0]"]),
    Hostile("number", "position 1e16 m", ["simulate", "cube", "--set", "body.0.position=[1e16, 0, 0]"]),
    Hostile("number", "scale 1e-300", ["simulate", "cube", "--set", "body.0.scale=1e-300"]),
    Hostile("number", "box size inf", ["simulate", "cube", "--set", "body.0.mesh.size=[inf, 1, 1]"]),
    Hostile("number", "box size 1e-300", ["simulate", "cube", "--set", "body.0.mesh.size=[1e-300, 1, 1]"]),
    Hostile("number", "gravity 1e308", ["simulate", "cube", "--set", "effects.gravity=[0, -1e308, 0]"]),
    Hostile("number", "velocity 1e308", ["simulate", "cube", "--set", "initial=[{velocity=[1e308, 0, 0]}]"]),
    Hostile("number", "--dt 1e-300", ["simulate", "cube", "--dt", "1e-300"]),
    Hostile("number", "--dt 1e6", ["simulate", "cube", "--dt", "1e6"]),
    Hostile("nesting", "TOML lists 1000 deep", ["simulate", "deep.toml"],
            {"deep.toml": text("x = " + "[" * 1000 + "]" * 1000 + "\n")}),
    Hostile("nesting", "TOML tables 1000 deep", ["simulate", "deep.toml"],
            {"deep.toml": text("x = " + "{a = " * 1000 + "1" + "}" * 1000 + "\n")}),
    Hostile("nesting", "--set value 1000 deep", ["simulate", "cube", "--set", "x=" + "[" * 1000 + "]" * 1000]),
    Hostile("nesting", "--set key 3000 deep", ["simulate", "cube", "--set", "a" + ".a" * 3000 + "=1"]),
    Hostile("name", "scene file name of 300 characters", ["simulate", f"{LONG}.toml"]),
    Hostile("name", "mesh file name of 300 characters", ["simulate", "cube", "--set",
                                                          f'body.0.mesh={{file="{LONG}.mesh"}}']),
    Hostile("name", "--stats name of 300 characters", ["simulate", "cube", "--stats", f"{LONG}.jsonl"]),
    Hostile("excerpt", "a .mesh whose first line is 5 kB with escape codes", ["simulate", "system.mesh"],
            {"system.mesh": text("1 root:x:0:0:" + "x" * 5000 + "\x1b[31m\n")}),
    Hostile("surface", "an icosphere with one face removed", ["simulate", "open.obj"], {"open.obj": open_sphere}),
    Hostile("surface", "one triangle", ["simulate", "triangle.obj"],
            {"triangle.obj": text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")}),
    Hostile("surface", "random bytes as .stl", ["simulate", "random.stl"],
            {"random.stl": lambda path: Path(path).write_bytes(bytes(range(256)) * 3)}),
    Hostile("option", "abbreviated --steps for --steps-per-frame", ["export", "cube86", "--steps", "5"]),
    Hostile("option", "abbreviated --stat for --stats", ["simulate", "cube86", "--stat", "x"]),
    # Issue 37.
    Hostile("special file", "--stats /dev/full", ["simulate", "cube", "--steps", "2", "--stats", "/dev/full"]),
    Hostile("name", "--video name of 250 characters (its temporary name is longer)",
            ["export", "cube", "--frames", "2", "--size", "64x64", "--video", "a" * 246 + ".mp4"], exit=0),
    Hostile("time", "--fps 1e300 with --video", ["export", "cube", "--frames", "2", "--fps", "1e300",
                                                 "--video", "v.mp4"]),
    Hostile("time", "--speed 1e-300 with --video", ["export", "cube", "--frames", "2", "--speed", "1e-300",
                                                    "--video", "v.mp4"]),
    Hostile("time", "--fps 1e-5 into an MP4 (no stream)", ["export", "cube", "--frames", "2", "--fps", "1e-5",
                                                           "--steps-per-frame", "1", "--video", "v.mp4"]),
    Hostile("time", "--fps 1e-5 into a GIF", ["export", "cube", "--frames", "2", "--fps", "1e-5",
                                              "--steps-per-frame", "1", "--video", "v.gif"]),
    Hostile("size", "box of 1e20 cells", ["simulate", "cube", "--set", "body.0.mesh.cells=[1e20, 1, 1]"]),
    Hostile("size", "box of -1e20 cells", ["simulate", "cube", "--set", "body.0.mesh.cells=[-1e20, 1, 1]"]),
    Hostile("size", "statue of resolution 2e6", ["simulate", "fertility", "--set", "body.0.mesh.resolution=2e6"]),
    Hostile("size", "dome of resolution 1e20", ["simulate", "epcot", "--set", "body.0.mesh.resolution=1e20"]),
    Hostile("size", "a 100 MB scene file", ["simulate", "big.toml"], {"big.toml": sparse(100 * 2**20)}),
    Hostile("surface", "a closed surface of size 0", ["simulate", "point.obj"],
            {"point.obj": text("v 1 1 1\nv 1 1 1\nv 1 1 1\nv 1 1 1\nf 1 2 3\nf 1 3 4\nf 1 4 2\nf 2 4 3\n")}),
    Hostile("surface", "a mesh of two copies of one tet (no surface)", ["export", "twice.mesh", "--frames", "1"],
            {"twice.mesh": text("MeshVersionFormatted 1\nDimension 3\nVertices\n4\n0 0 0 0\n1 0 0 0\n0 1 0 0\n"
                                "0 0 1 0\nTetrahedra\n2\n1 2 3 4 0\n1 2 3 4 0\nEnd\n")}),
    Hostile("name", "a mesh path ~nouser/x.mesh", ["simulate", "~nouser/x.mesh"]),
    Hostile("name", "--set a mesh file ~nouser/x.mesh", ["simulate", "cube", "--set",
                                                         'body.0.mesh={file="~nouser/x.mesh"}']),
    Hostile("number", "f32: 1 cm tets 1e5 m from the origin", ["simulate", "cube", "--set", "body.0.position=[1e5, 0, 0]",
                                                              "--set", "body.0.scale=0.01", "--set", "initial=[]"]),
    Hostile("number", "f32: nu = 0.49999999999999994", ["simulate", "cube", "--set",
                                                        "body.0.material.nu=0.49999999999999994"]),
    Hostile("number", "f32: nu = 0.49999999999", ["simulate", "cube", "--set", "body.0.material.nu=0.49999999999"]),
    Hostile("number", "camera eye equal to target", ["export", "cube", "--frames", "1", "--set",
                                                     "camera={eye=[1, 1, 1], target=[1, 1, 1]}"]),
]



def run_hostile(case, folder):
    """(exit code, stderr) of the case's command line, run in `folder` with its files made."""
    import main
    folder = Path(folder)
    for name, make in case.files.items():
        make(folder / name)
    out, err = io.StringIO(), io.StringIO()
    before = os.getcwd()
    os.chdir(folder)
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            try:
                code = main.main(case.argv + (["--steps", "1"] if case.argv[0] == "simulate"
                                               and "--steps" not in case.argv else []))
            except SystemExit as exit:
                code = exit.code
    finally:
        os.chdir(before)
    return code, err.getvalue()
