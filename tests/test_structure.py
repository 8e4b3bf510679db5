"""The package's shape: the library (gsmn/) never imports the app (app/), and the model imports without the
simulator or the mesh builder, so a checkpoint loads where neither is installed. And the tests' own: every test
module names its tier, and no test of the fast tier starts a `gsmn serve` process or a browser."""

from __future__ import annotations

import ast
import re
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.unit

ROOT = Path(__file__).resolve().parents[1]


def _imported_top_level(module: str) -> set[str]:
    """The top-level packages a fresh interpreter holds after `import module`."""
    code = f"import sys, {module}; print(' '.join(sorted({{m.split('.')[0] for m in sys.modules}})))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=ROOT)
    return set(out.stdout.split())


def _imports(path: Path) -> set[str]:
    """Every module a source file names in an import statement, at any depth (lazy imports included)."""
    names = set()
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names.add(node.module)
    return names


def test_no_library_module_imports_the_app():
    offenders = {str(p.relative_to(ROOT)): sorted(n for n in _imports(p) if n.split(".")[0] == "app")
                 for p in sorted((ROOT / "gsmn").rglob("*.py"))}
    assert {k: v for k, v in offenders.items() if v} == {}


def test_importing_the_command_line_leaves_the_app_out():
    assert "app" not in _imported_top_level("gsmn.cli")


@pytest.mark.parametrize("module", ["gsmn.model", "gsmn.model.checkpoint"])
def test_importing_the_model_pulls_in_neither_the_simulator_nor_the_mesh_builder(module):
    loaded = _imported_top_level(module)
    assert "torch" in loaded
    assert not loaded & {"mujoco", "trimesh", "app"}


def _declared() -> set[str]:
    """Every distribution pyproject.toml declares, runtime and extras, by its normalised name."""
    import tomllib

    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    specs = [*project["dependencies"], *(s for extra in project["optional-dependencies"].values() for s in extra)]
    return {re.split(r"[<>=!~;\[ ]", spec, maxsplit=1)[0].lower().replace("_", "-") for spec in specs}


def test_every_third_party_import_is_declared_in_pyproject():
    """What gsmn/, app/, scripts/ and tests/ import is declared (runtime, `dev` or `docs`), not left to arrive as
    another package's dependency."""
    from importlib.metadata import packages_distributions

    local = {"gsmn", "app", "__future__"} | {p.stem for p in (ROOT / "scripts").glob("*.py")} \
        | {p.stem for p in (ROOT / "tests").glob("*.py")}
    distributions = packages_distributions()
    declared = _declared()
    undeclared = {}
    for folder in ("gsmn", "app", "scripts", "tests"):
        for path in sorted((ROOT / folder).rglob("*.py")):
            for name in _imports(path):
                top = name.split(".")[0]
                if top in sys.stdlib_module_names or top in local:
                    continue
                names = {d.lower().replace("_", "-") for d in distributions.get(top, [top])}
                if not names & declared:
                    undeclared.setdefault(top, []).append(str(path.relative_to(ROOT)))
    assert undeclared == {}


def test_the_repository_stays_lean():
    """Every clone carries every version of every file: no tracked file over 2 MB outside checkpoints/, and no
    pickle in checkpoints/ (weights and optimizer state are safetensors; a pickle can run code when loaded)."""
    tracked = subprocess.run(["git", "ls-files", "-z"], capture_output=True, text=True, check=True, cwd=ROOT)
    paths = [p for p in tracked.stdout.split("\0") if p and (ROOT / p).is_file()]
    large = [p for p in paths if not p.startswith("checkpoints/") and (ROOT / p).stat().st_size > 2 * 2**20]
    assert large == [], f"tracked files over 2 MB outside checkpoints/: {large}"
    pickles = [p for p in paths if p.startswith("checkpoints/") and p.rsplit(".", 1)[-1] in
               ("pt", "pth", "pkl", "pickle", "ckpt", "bin")]
    assert pickles == [], f"pickles in checkpoints/: {pickles}"
    on_disk = [str(p.relative_to(ROOT)) for p in (ROOT / "checkpoints").rglob("*")
               if p.suffix in (".pt", ".pth", ".pkl", ".pickle", ".ckpt")]
    assert on_disk == [], f"pickles in checkpoints/ (not tracked yet): {on_disk}"


# -- the app's layers --------------------------------------------------------------------------------------------
# app/'s packages from the bottom up: a module imports only from packages below its own, or from its own package.
# api and page are side by side (neither imports the other); the modules at the top (app/server.py, app/cli.py) tie
# them together. docs/dashboard.md's code map says what each holds and which thread it runs on.
APP_LAYERS = {"live": 0, "jobs": 1, "render": 2, "api": 3, "page": 3}
TOP = 4
MAX_MODULE_LINES, MAX_FUNCTION_LINES = 500, 60


def _module_of(path: Path) -> str:
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _module_graph(package: str) -> dict[str, set[str]]:
    """Each module of `package` -> the modules of `package` it imports, lazy imports included (`from a.b import c`
    counts as importing a.b.c where that is a module)."""
    paths = sorted((ROOT / package).rglob("*.py"))
    modules = {_module_of(p) for p in paths}
    graph: dict[str, set[str]] = {}
    for path in paths:
        me, found = _module_of(path), set()
        for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
            if isinstance(node, ast.Import):
                found.update(a.name for a in node.names)
            elif isinstance(node, ast.ImportFrom) and node.module:
                base = node.module
                if node.level:
                    here = me.split(".") if path.name == "__init__.py" else me.split(".")[:-1]
                    base = ".".join(here[:len(here) - node.level + 1] + [node.module])
                found.add(base)
                found.update(f"{base}.{a.name}" for a in node.names if f"{base}.{a.name}" in modules)
        graph[me] = {m for m in found if m in modules and m != me and not me.startswith(m + ".")}
    return graph


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The import circles: strongly connected components of more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    out: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        for w in graph.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                out.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def _layer(module: str) -> tuple[str, int]:
    parts = module.split(".")
    if len(parts) > 2 or (len(parts) == 2 and parts[1] in APP_LAYERS):
        return parts[1], APP_LAYERS[parts[1]]
    return module, TOP


@pytest.mark.parametrize("package", ["app", "gsmn"])
def test_no_import_circle(package):
    assert _cycles(_module_graph(package)) == []


def test_every_app_module_lies_in_a_known_layer():
    unknown = [m for m in _module_graph("app") if m.count(".") >= 2 and m.split(".")[1] not in APP_LAYERS]
    assert unknown == [], f"a package of app/ missing from APP_LAYERS: {unknown}"


def test_app_arrows_run_one_way():
    """No module imports from a package above its own or beside it; the package graph is printed."""
    arrows: dict[tuple[str, str], int] = {}
    wrong = []
    for module, imported in _module_graph("app").items():
        (mine, rank) = _layer(module)
        for other in imported:
            (theirs, their_rank) = _layer(other)
            if theirs == mine:
                continue
            arrows[(mine, theirs)] = arrows.get((mine, theirs), 0) + 1
            if their_rank > rank or (their_rank == rank and rank != TOP):
                wrong.append(f"{module} -> {other}")
    ranks = sorted(set(APP_LAYERS.values()))
    print("\napp/ packages, bottom up:", " < ".join("{" + ", ".join(p for p, r in APP_LAYERS.items() if r == rank) + "}"
                                                   for rank in ranks), "< app/*.py")
    for (a, b), n in sorted(arrows.items()):
        print(f"  {a} -> {b} ({n} import{'s' if n > 1 else ''})")
    assert wrong == []


def test_app_modules_and_functions_are_short():
    long_modules, long_functions = [], []
    for path in sorted((ROOT / "app").rglob("*.py")):
        text = path.read_text()
        name = str(path.relative_to(ROOT))
        if text.count("\n") > MAX_MODULE_LINES:
            long_modules.append(f"{name}: {text.count(chr(10))} lines")
        for node in ast.walk(ast.parse(text)):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                n = node.end_lineno - node.lineno + 1
                if n > MAX_FUNCTION_LINES:
                    long_functions.append(f"{name}:{node.lineno} {node.name}: {n} lines")
    assert long_modules == [] and long_functions == []


def _code_map() -> dict[str, str]:
    """docs/dashboard.md's code map: path -> its thread column."""
    text = (ROOT / "docs" / "dashboard.md").read_text()
    section = text.split("## Code map", 1)[1].split("\n## ", 1)[0]
    rows = re.findall(r"^\| `(app/[\w/.]*)` \| [^|]+ \| ([^|]+) \|$", section, flags=re.M)
    return {path: thread.strip() for path, thread in rows}


def test_the_code_map_names_every_package_and_module_of_the_app():
    listed = _code_map()
    actual = {str(p.relative_to(ROOT)) for p in (ROOT / "app").rglob("*.py") if p.name != "__init__.py"}
    actual |= {str(p.relative_to(ROOT)) + "/" for p in (ROOT / "app").iterdir() if (p / "__init__.py").is_file()}
    assert sorted(actual - set(listed)) == [], "modules missing from docs/dashboard.md's code map"
    assert sorted(set(listed) - actual) == [], "the code map names modules that are gone"
    assert all(listed.values()), "every row names the thread it runs on"


# -- the tiers (conftest.py, README.md "Tests") -------------------------------------------------------------------
TIERS = {"unit", "server", "browser", "training", "cluster", "slow"}  # a module's pytestmark names at least one
# names that, reached from a test through its module's functions and fixtures, start what needs a tier of its own
STARTS = {"gsmn_serve": "server", "Serve": "server", "serve_command": "server", "chromium": "browser",
          "page_on": "browser", "sync_playwright": "browser", "playwright_api": "browser"}


def _marks(nodes) -> set[str]:
    """The marker names in decorators or a pytestmark value: pytest.mark.NAME, pytest.mark.NAME(...)."""
    names = set()
    for node in nodes:
        node = node.func if isinstance(node, ast.Call) else node
        if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Attribute) and node.value.attr == "mark":
            names.add(node.attr)
    return names


def tier_problems(source: str) -> list[str]:
    """What is wrong with a test module's tier: no module-level `pytestmark` naming one of TIERS, a test that
    reaches a `gsmn serve` process or a browser without the marker that says so, or a `gsmn serve` command line
    built here rather than through conftest.py's `gsmn_serve` (support.Serve)."""
    tree = ast.parse(source)
    module_marks = None
    functions: dict[str, ast.FunctionDef] = {}
    for node in tree.body:
        if isinstance(node, ast.Assign) and any(isinstance(t, ast.Name) and t.id == "pytestmark"
                                                for t in node.targets):
            value = node.value
            module_marks = _marks(value.elts if isinstance(value, (ast.List, ast.Tuple)) else [value])
        elif isinstance(node, ast.FunctionDef):
            functions[node.name] = node
    problems = []
    if not module_marks or not module_marks & TIERS:
        problems.append(f"no tier: a module-level pytestmark names none of {sorted(TIERS)}")
    module_marks = module_marks or set()

    def names(function: ast.FunctionDef) -> set[str]:
        found = {a.arg for a in function.args.args}
        for node in ast.walk(function):
            if isinstance(node, ast.Name):
                found.add(node.id)
            elif isinstance(node, ast.Attribute):
                found.add(node.attr)
        return found

    for name, function in functions.items():
        if not name.startswith("test"):
            continue
        reached, todo = set(), [name]
        while todo:  # through the module's own helpers and fixtures
            for n in names(functions[todo.pop()]) - reached:
                reached.add(n)
                if n in functions:
                    todo.append(n)
        needed = {STARTS[n] for n in reached if n in STARTS}
        missing = needed - module_marks - _marks(function.decorator_list)
        if missing:
            problems.append(f"{name} starts what needs {sorted(missing)} but is not marked so")
    for node in ast.walk(tree):
        if isinstance(node, ast.List) and {"gsmn.cli", "serve"} <= {
                e.value for e in node.elts if isinstance(e, ast.Constant)}:
            problems.append(f"line {node.lineno}: a `gsmn serve` command line of its own (use support.serve_command "
                            "or the gsmn_serve fixture)")
    return problems


def test_every_test_module_has_a_tier_and_fast_tests_start_no_server_and_no_browser():
    problems = {p.name: tier_problems(p.read_text()) for p in sorted((ROOT / "tests").glob("test_*.py"))}
    assert {k: v for k, v in problems.items() if v} == {}


def test_the_tier_check_sees_a_missing_tier_and_a_server_in_the_fast_tier():
    assert tier_problems("def test_x():\n    pass\n") == [f"no tier: a module-level pytestmark names none of "
                                                         f"{sorted(TIERS)}"]
    fast = "import pytest\npytestmark = pytest.mark.unit\n"
    server = "@pytest.fixture\ndef api(gsmn_serve):\n    return gsmn_serve()\n\ndef test_x(api):\n    pass\n"
    assert tier_problems(fast + server) == ["test_x starts what needs ['server'] but is not marked so"]
    assert tier_problems(fast + server.replace("def test_x", "@pytest.mark.server\ndef test_x")) == []
    browser = "def test_y():\n    with browser_support.chromium() as b:\n        pass\n"
    assert tier_problems(fast + browser) == ["test_y starts what needs ['browser'] but is not marked so"]
    assert tier_problems(fast.replace("unit", "browser") + browser) == []
    assert tier_problems(fast + "def test_z():\n    subprocess.run(['python', '-m', 'gsmn.cli', 'serve'])\n") \
        == ["line 4: a `gsmn serve` command line of its own (use support.serve_command or the gsmn_serve fixture)"]


def test_the_tiers_are_registered_markers_and_markers_are_strict():
    import tomllib

    options = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["pytest"]["ini_options"]
    registered = {m.split(":")[0].strip() for m in options["markers"]}
    assert TIERS | {"fast"} <= registered
    assert "--strict-markers" in options["addopts"].split()
    heavy = next(ast.literal_eval(node.value) for node in ast.parse((ROOT / "tests" / "conftest.py").read_text()).body
                 if isinstance(node, ast.Assign) and getattr(node.targets[0], "id", None) == "HEAVY")
    assert set(heavy) == TIERS - {"unit"}  # what conftest.py keeps out of the fast tier
