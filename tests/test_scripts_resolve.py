"""The benchmarks (`bench/`), experiments (`experiments/`) and tools (`tools/`) are scripts no test runs end to end (they train
and time for minutes to hours), so a rename in the package can leave one that crashes on start.
Every name they import from `scube_sim` must exist: read from their source with `ast`, looked up
in the imported module."""

import ast
import importlib
import importlib.util
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SCRIPTS = sorted([*REPO.glob("bench/*.py"), *REPO.glob("experiments/*.py"), *REPO.glob("tools/*.py")])


def _package_imports(path: Path) -> list[tuple[str, str]]:
    """(module, name) for each `from scube_sim... import name` in the file, at any depth."""
    out = []
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.ImportFrom) and node.level == 0 and (node.module or "").split(".")[0] == "scube_sim":
            out += [(node.module, a.name) for a in node.names]
    return out


def test_scripts_found():
    assert len(SCRIPTS) > 10, SCRIPTS


@pytest.mark.parametrize("path", SCRIPTS, ids=lambda p: f"{p.parent.name}/{p.name}")
def test_script_imports_resolve(path):
    for module, name in _package_imports(path):
        mod = importlib.import_module(module)
        # or a submodule imported by name (`from scube_sim.model import trainer`)
        found = hasattr(mod, name) or (hasattr(mod, "__path__") and importlib.util.find_spec(f"{module}.{name}") is not None)
        assert found, f"{path.relative_to(REPO)}: `from {module} import {name}`: {module} has no {name!r}"


@pytest.mark.parametrize("path", SCRIPTS, ids=lambda p: f"{p.parent.name}/{p.name}")
def test_scripts_use_only_public_names(path):
    """A script reaches the package through public names: an internal it needs is made public
    where it lives (tests may reach into internals; scripts are users)."""
    private = [f"{module}.{name}" for module, name in _package_imports(path)
               if name.startswith("_") or any(p.startswith("_") for p in module.split(".")[1:])]
    assert not private, f"{path.relative_to(REPO)} imports private names: {', '.join(private)}"
