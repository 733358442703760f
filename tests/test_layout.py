"""The structure, checked as a reviewer would: read every module's imports (with `ast`, so
nothing is run) and ask the questions of issue 22.

- No import circles between the project's own modules, counting imports inside functions.
- The engine (`fem/`) imports nothing from the app, the meshes, the scenes or the tools.
- Nothing in the product imports the developer tools (`tools/`) or the script `main.py`.
- No code edits `sys.path` to find the project: tests get the root from pytest.ini
  (`pythonpath = .`), tools run as `python -m tools.NAME` from the root.
- The app's rooms import only downwards (see app/__init__.py).
- No module of the product is over MAX_LINES lines.
"""

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PRODUCT = ("fem", "app", "assets", "scenes")        # packages, plus main.py
MAX_LINES = 450
# What each part of app/ may import from app/ (a room is named by its package; `app` is the plumbing:
# app/__init__.py and the modules at app/'s top). Anything else is a layering breach.
ROOMS = {
    "app": {"app"},
    "app.render": {"app", "app.render"},
    "app.window": {"app", "app.render", "app.window"},
    "app.bench": {"app", "app.bench"},
    "app.commands": {"app", "app.render", "app.window", "app.bench", "app.commands"},
    "app.cli": {"app", "app.commands"},
}


def module_name(path):
    """fem/solver.py -> fem.solver; app/render/__init__.py -> app.render."""
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def product_files():
    return [ROOT / "main.py"] + sorted(p for top in PRODUCT for p in (ROOT / top).rglob("*.py"))


def tool_files():
    return sorted((ROOT / "tools").rglob("*.py"))


MODULES = {module_name(p): p for p in product_files()}


def imported_names(path):
    """Every module name an import statement in the file names, at any depth (functions included),
    with the line it is on: `from a.b import c` gives a.b.c when that is a module, else a.b."""
    package = module_name(path) if path.name == "__init__.py" else module_name(path).rpartition(".")[0]
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            for alias in node.names:
                yield alias.name, node.lineno
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:                                  # relative: from its own package upwards
                anchor = package.split(".")[:len(package.split(".")) - node.level + 1]
                base = ".".join(anchor + ([base] if base else []))
            for alias in node.names:
                yield (f"{base}.{alias.name}" if f"{base}.{alias.name}" in MODULES else base), node.lineno


def own_module(name):
    """The project's module that `import name` loads last (a.b.c -> a.b if c is not a module), or None."""
    while name and name not in MODULES:
        name = name.rpartition(".")[0]
    return name or None


def import_graph():
    """{module: {imported project module: line}}."""
    graph = {}
    for name, path in MODULES.items():
        edges = graph.setdefault(name, {})
        for imported, line in imported_names(path):
            target = own_module(imported)
            if target and target != name:
                edges.setdefault(target, line)
    return graph


def find_cycle(graph):
    """One import circle as [a, b, ..., a], or None (depth-first search, three colours)."""
    state, stack = {}, []

    def visit(node):
        state[node] = "open"
        stack.append(node)
        for nxt in sorted(graph.get(node, {})):
            if state.get(nxt) == "open":
                return stack[stack.index(nxt):] + [nxt]
            if nxt not in state and (cycle := visit(nxt)):
                return cycle
        state[node] = "done"
        stack.pop()
        return None

    for node in sorted(graph):
        if node not in state and (cycle := visit(node)):
            return cycle
    return None


def room(module):
    """The part of app/ a module belongs to (a key of ROOMS)."""
    parts = module.split(".")
    if module == "app.cli":
        return "app.cli"
    if len(parts) > 2 or module in ROOMS:
        return ".".join(parts[:2])
    return "app"


# ---------------------------------------------------------------- the checks

def test_the_checker_sees_a_circle_and_the_package_layout():
    assert find_cycle({"a": {"b": 1}, "b": {"c": 1}, "c": {"a": 1}}) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b": 1}, "b": {}, "c": {"a": 1, "b": 1}}) is None
    assert {"main", "fem", "app.cli", "app.commands.bench", "app.bench", "app.render.frame"} <= set(MODULES)
    assert room("app.files") == "app" and room("app.render.frame") == room("app.render") == "app.render"
    assert room("app.cli") == "app.cli" and room("app") == "app"


def test_no_import_circles():
    cycle = find_cycle(import_graph())
    assert cycle is None, "import circle: " + " -> ".join(cycle)


def test_the_engine_imports_nothing_from_the_app_meshes_scenes_or_tools():
    breaches = [f"{module_name(path)} imports {imported} (line {line})"
                for path in (ROOT / "fem").rglob("*.py") for imported, line in imported_names(path)
                if imported.split(".")[0] in ("app", "assets", "scenes", "tools", "main")]
    assert not breaches, breaches


def test_no_product_module_imports_the_tools_or_main():
    breaches = [f"{name} imports {imported} (line {line})"
                for name, path in MODULES.items() for imported, line in imported_names(path)
                if imported.split(".")[0] == "tools" or (imported == "main" and name != "main")]
    assert not breaches, breaches


def test_no_code_edits_sys_path():
    edits = []
    for path in product_files() + tool_files() + [ROOT / "tests" / "conftest.py"]:
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if (isinstance(node, ast.Attribute) and node.attr == "path"
                    and isinstance(node.value, ast.Name) and node.value.id == "sys"):
                edits.append(f"{path.relative_to(ROOT)}:{node.lineno}")
    assert not edits, f"sys.path used at {edits}: run from the root (python -m tools.NAME) instead"


def test_the_apps_rooms_import_only_downwards():
    breaches = [f"{name} ({room(name)}) imports {target} ({room(target)}), line {line}"
                for name, edges in import_graph().items() if name.split(".")[0] == "app"
                for target, line in edges.items()
                if target.split(".")[0] == "app" and room(target) not in ROOMS[room(name)]]
    assert not breaches, breaches


def test_every_module_of_the_product_is_short_enough_to_read():
    long = {str(path.relative_to(ROOT)): n for path in product_files()
            if (n := len(path.read_text().splitlines())) > MAX_LINES}
    assert not long, f"over {MAX_LINES} lines: {long}"
