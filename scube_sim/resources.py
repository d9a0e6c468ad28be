"""Where the shipped sensor definitions live (`sensors/` in the repo, `scube_sim/_sensors` in a wheel)."""

from __future__ import annotations

import importlib.util
from pathlib import Path


def sensors_dir() -> Path:
    """The folder holding `lidar/*.yaml` presets and `rigs/*.yaml` camera rigs."""
    spec = importlib.util.find_spec("scube_sim._sensors")
    if spec is not None and spec.submodule_search_locations:
        return Path(list(spec.submodule_search_locations)[0])
    # Source checkout or editable install: the top-level data folder beside the package.
    return Path(__file__).resolve().parent.parent / "sensors"
