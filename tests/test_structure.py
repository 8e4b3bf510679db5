"""The package's shape: the library (gsmn/) never imports the app (app/), and the model imports without the
simulator or the mesh builder, so a checkpoint loads where neither is installed."""

from __future__ import annotations

import ast
import re
import subprocess
import sys
from pathlib import Path

import pytest

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
