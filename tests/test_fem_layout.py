"""The engine's layout: fem/ imports nothing of the app, the assets, the scenes or the tools,
and no module of fem/ imports itself through others (no circles)."""

import ast
from pathlib import Path

FEM = Path(__file__).resolve().parents[1] / "fem"
OUTSIDE = ("app", "assets", "scenes", "tools")


def module_name(path):
    parts = path.relative_to(FEM.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


MODULES = {module_name(path): path for path in sorted(FEM.rglob("*.py"))}


def imports(path):
    """Every module name an import statement in the file names, in functions too: for
    `from a import b` the module a.b when it is one, else a."""
    names = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            names += [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0:
            names += [f"{node.module}.{alias.name}" if f"{node.module}.{alias.name}" in MODULES else node.module
                      for alias in node.names]
    return names


def graph():
    """{fem module: the fem modules it imports}."""
    return {name: sorted({n for n in imports(path) if n in MODULES and n != name})
            for name, path in MODULES.items()}


def circles(edges):
    """Every import circle, each as the list of modules around it (depth-first search)."""
    found, state = [], {}

    def visit(name, path):
        state[name] = "open"
        for other in edges[name]:
            if state.get(other) == "open":
                found.append(path[path.index(other):] + [other])
            elif other not in state:
                visit(other, path + [other])
        state[name] = "done"

    for name in edges:
        if name not in state:
            visit(name, [name])
    return found


def test_the_layout_is_read_from_every_module():
    assert {"fem", "fem.pool", "fem.implicit.solver", "fem.implicit.newton"} <= set(MODULES)
    assert "fem.implicit.potential" in graph()["fem.implicit.newton"]


def test_fem_imports_nothing_of_the_app_assets_scenes_or_tools():
    outside = {name: [n for n in imports(path) if n.split(".")[0] in OUTSIDE] for name, path in MODULES.items()}
    assert not {name: found for name, found in outside.items() if found}


def test_fem_has_no_import_circles():
    assert circles(graph()) == []


def test_the_circle_finder_finds_a_circle():
    assert circles({"a": ["b"], "b": ["c"], "c": ["a"], "d": ["a"]}) == [["a", "b", "c", "a"]]
