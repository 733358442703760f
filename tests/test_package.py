"""`pip install .` makes a package: `fem` importable from any folder, the scenes with it,
and a `softfem` command that is `python main.py`.

The package is built from this checkout without its dependencies (they are the ones this
environment already has) into a temporary folder, and used from another one.
"""

import importlib.util
import os
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def test_pyproject_names_the_packages_the_command_and_the_requirements():
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())
    assert project["project"]["scripts"] == {"softfem": "app.cli:main"}
    # every folder of the product that is a package, sub-packages included (fem.implicit, app.commands, ...):
    # setuptools installs only those named
    packages = {str(init.parent.relative_to(ROOT)).replace("/", ".")
                for top in ("fem", "app", "assets", "scenes") for init in (ROOT / top).rglob("__init__.py")}
    assert {"fem", "fem.implicit", "app", "app.commands", "assets", "scenes"} <= packages
    assert set(project["tool"]["setuptools"]["packages"]) == packages
    # The same dependencies as requirements.txt, which also has the test tools.
    required = {line.split(">")[0].split("=")[0].strip().lower()
                for line in (ROOT / "requirements.txt").read_text().splitlines()
                if line.strip() and not line.startswith("#")}
    declared = {d.split(">")[0].split("=")[0].strip().lower() for d in project["project"]["dependencies"]}
    test_tools = {d.split(">")[0].strip().lower() for d in project["project"]["optional-dependencies"]["test"]}
    assert declared | test_tools | {"setuptools", "wheel"} == required


@pytest.fixture(scope="module")
def installed(tmp_path_factory):
    """The package installed (without dependencies) into a folder of its own."""
    if importlib.util.find_spec("wheel") is None or importlib.util.find_spec("setuptools") is None:
        pytest.skip("building the package here needs setuptools and wheel (both in requirements.txt)")
    target = tmp_path_factory.mktemp("site")
    build = subprocess.run([sys.executable, "-m", "pip", "install", "--quiet", "--no-deps",
                            "--no-build-isolation", "--no-index", "--target", str(target), str(ROOT)],
                           capture_output=True, text=True, timeout=300)
    assert build.returncode == 0, build.stderr
    return target


def in_another_folder(installed, tmp_path, command):
    env = {**os.environ, "PYTHONPATH": str(installed)}
    return subprocess.run(command, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300)


def test_fem_imports_from_any_folder_with_its_scenes(installed, tmp_path):
    code = ("import fem, scenes; print(fem.__file__); print(sorted(scenes.builtin_scenes())); "
            "print(len(scenes.load_scene('cube86').bodies))")
    run = in_another_folder(installed, tmp_path, [sys.executable, "-c", code])
    assert run.returncode == 0, run.stderr
    where, scenes, bodies = run.stdout.splitlines()
    assert Path(where).is_relative_to(installed)             # the installed copy, not this checkout
    assert "epcot" in scenes and bodies == "2"


def test_the_installed_package_has_every_module_of_the_checkout(installed, tmp_path):
    """Sub-packages included (app.commands, app.render, ...), and each imports from the installed copy."""
    modules = sorted(".".join(path.relative_to(ROOT).with_suffix("").parts).removesuffix(".__init__")
                     for top in ("fem", "app", "assets", "scenes") for path in (ROOT / top).rglob("*.py"))
    code = ("import importlib, sys\n"
            "for name in sys.argv[1:]:\n"
            "    print(importlib.import_module(name).__file__)")
    run = in_another_folder(installed, tmp_path, [sys.executable, "-c", code, *modules])
    assert run.returncode == 0, run.stderr
    assert all(Path(where).is_relative_to(installed) for where in run.stdout.splitlines())
    assert len(run.stdout.splitlines()) == len(modules)


def test_softfem_is_the_command_line(installed, tmp_path):
    script = installed / "bin" / "softfem"
    assert script.is_file()
    run = in_another_folder(installed, tmp_path, [sys.executable, str(script), "help"])
    assert run.returncode == 0, run.stderr
    assert run.stdout.startswith("usage: softfem ") and "simulate" in run.stdout
    run = in_another_folder(installed, tmp_path, [sys.executable, str(script), "simulate", "nothere"])
    assert run.returncode == 2 and run.stderr.startswith("error: nothere: no such scene")
