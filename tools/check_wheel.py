"""The installed package, not the source tree: build the wheel, install it into a fresh virtual
environment, and use it from there. `make test` runs on an editable install, which reads the
source tree and so cannot notice a subpackage or data file that pyproject.toml forgot to ship;
this can. Checks, with the wheel's copy of scube_sim (never the source tree's):

- every source file of the package (Python modules, shipped checkpoints, profiles, configs, sensor
  presets and rigs) is in the wheel;
- every module imports; the console script `scube-sim --help` runs;
- every shipped checkpoint loads into its stage's model, every converter profile loads its models,
  every training config, LiDAR preset and camera rig validates.

The wheel is built from a copy of the files git knows (a stale build/ folder cannot hide a
missing file). The fresh environment takes the dependencies from the development one (`.venv`) through a path
file, so nothing is downloaded; the editable install there is not activated (path files inside a
listed folder are not read). Usage: `make check-wheel` (CI runs it after `make test`; a minute or
two, most of it compiling the tracer core).
"""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
import sysconfig
import tempfile
import zipfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
# folders of data files that setuptools also names as packages it leaves out (their files ship as package data)
DATA_FOLDERS = {"scube_sim._sensors.lidar", "scube_sim._sensors.rigs", "scube_sim.model.checkpoints"}

CHECK = r"""
import importlib, pkgutil, sys
from pathlib import Path
import scube_sim
src = Path(sys.argv[1])
assert src not in Path(scube_sim.__file__).resolve().parents, f"scube_sim imported from the source tree: {scube_sim.__file__}"
modules = [m.name for m in pkgutil.walk_packages(scube_sim.__path__, "scube_sim.") if not m.name.endswith(".__main__")]
for name in modules:
    importlib.import_module(name)
from scube_sim.camera.rig import load_rig, rig_paths
from scube_sim.lidar.config import list_presets
from scube_sim.model.checkpoint import load_checkpoint, load_model, shipped_checkpoints
from scube_sim.model.config import config_names, load_config
from scube_sim.converter.pipeline import Converter
from scube_sim.converter.profile import shipped_profiles
checkpoints = shipped_checkpoints()
for name, path in checkpoints.items():
    load_model(load_checkpoint(path)["stage"], name)
profiles = shipped_profiles()
for p in profiles:
    Converter(p)  # loads the profile's checkpoints
configs = config_names()
for c in configs:
    load_config(c)
presets = list_presets()
rigs = [load_rig(r) for r in rig_paths()]
print(f"{len(modules)} modules, {len(checkpoints)} checkpoints, {len(profiles)} profiles, {len(configs)} "
      f"configs, {len(presets)} LiDAR presets, {len(rigs)} rigs: from {Path(scube_sim.__file__).parent}")
"""


def expected_files() -> set[str]:
    """Paths inside the wheel that the source tree says must be there (git's tracked files)."""
    tracked = subprocess.run(["git", "ls-files", "scube_sim", "sensors"], cwd=ROOT, capture_output=True, text=True,
                             check=True).stdout.split()
    out = set()
    for f in tracked:
        if Path(f).name.startswith("."):  # folder placeholders (.keep)
            continue
        if f.startswith("sensors/"):
            out.add("scube_sim/_sensors/" + f[len("sensors/"):])
        elif not f.endswith((".cpp", ".h")):
            out.add(f)
    return out


def run(cmd: list, **kw) -> subprocess.CompletedProcess:
    print("$", " ".join(str(c) if len(str(c)) < 80 else "<script>" for c in cmd), flush=True)
    return subprocess.run([str(c) for c in cmd], check=True, **kw)


def main() -> int:
    with tempfile.TemporaryDirectory(prefix="scube-wheel-") as tmp:
        tmp = Path(tmp)
        # built from a copy of the files git knows (tracked, or new and not ignored), as a fresh clone
        # would be: a build/ folder left in the tree would otherwise hand stale files to the wheel
        src = tmp / "src"
        listed = subprocess.run(["git", "ls-files", "--cached", "--others", "--exclude-standard"], cwd=ROOT,
                                capture_output=True, text=True, check=True).stdout.split("\n")
        for f in filter(None, listed):
            if (ROOT / f).is_file():
                (src / f).parent.mkdir(parents=True, exist_ok=True)
                shutil.copy2(ROOT / f, src / f)
        built = run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "--no-build-isolation", "-w",
                     tmp / "dist", src], capture_output=True, text=True)
        # setuptools still ships a package missing from the hand-written list, with a warning; a
        # later setuptools will not: fail on the warning now
        absent = sorted(set(re.findall(r"Package '([\w.]+)' is absent from the `packages` configuration",
                                       built.stdout + built.stderr)) - DATA_FOLDERS)
        if absent:
            print(f"error: pyproject.toml's [tool.setuptools] packages lacks {', '.join(absent)}", file=sys.stderr)
            return 1
        wheel = next((tmp / "dist").glob("scube_sim-*.whl"))
        names = set(zipfile.ZipFile(wheel).namelist())
        missing = sorted(expected_files() - names)
        if missing:
            print(f"error: {wheel.name} lacks {len(missing)} file(s) of the source tree (pyproject.toml's packages "
                  f"or package-data): " + ", ".join(missing[:20]), file=sys.stderr)
            return 1
        print(f"{wheel.name}: {len(names)} files, every tracked package file among them")
        venv = tmp / "venv"
        run([sys.executable, "-m", "venv", venv])
        py = venv / "bin" / "python"
        site = Path(subprocess.run([py, "-c", "import sysconfig; print(sysconfig.get_path('purelib'))"],
                                   capture_output=True, text=True, check=True).stdout.strip())
        (site / "dev-dependencies.pth").write_text(sysconfig.get_path("purelib") + "\n")
        run([py, "-m", "pip", "install", "-q", "--no-deps", "--no-index", wheel])
        # -I: no current folder and no PYTHON* variables on the path, so only the installed copy is seen
        run([py, "-I", "-c", CHECK, ROOT], cwd=tmp)
        run([venv / "bin" / "scube-sim", "--help"], cwd=tmp, stdout=subprocess.DEVNULL)
    print("wheel check passed")
    return 0


if __name__ == "__main__":
    sys.exit(main())
