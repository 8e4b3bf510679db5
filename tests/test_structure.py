"""The package's shape: the library (gsmn/) never imports the app (app/), and the model imports without the
simulator or the mesh builder, so a checkpoint loads where neither is installed."""

from __future__ import annotations

import ast
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
