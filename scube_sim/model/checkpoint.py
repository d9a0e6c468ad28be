"""Training checkpoints: tensors and plain Python values only, written atomically, read back with
`torch.load(weights_only=True)` so that loading a file never runs code from it.

A checkpoint is a dict (see `trainer` for the keys it writes) carrying `format` = FORMAT and
`version` = VERSION. RNG states are stored as a torch uint8 tensor (torch's CPU generator) and
plain ints/lists/floats (numpy's global MT19937, Python's `random`).
"""

from __future__ import annotations

import pickle
import random
import re
import warnings
import zipfile
from pathlib import Path

import numpy as np
import torch
from torch import nn

from ..atomic import atomic_path
from ..config import normalize_name
from ..errors import InputError
from .config import RunConfig, config_from_dict, stage_configs
from .stages import Stage, get_stage

SHIPPED_DIR = Path(__file__).resolve().parent / "checkpoints"  # <name>/model.pt, with its README
FORMAT = "scube-sim-train"
VERSION = 1

_PLAIN = (int, float, bool, str, type(None))


class CheckpointError(InputError):
    """A checkpoint file that cannot be used; the message names the file."""


def check_plain(obj: object, where: str = "checkpoint") -> None:
    """Raise TypeError unless `obj` is built from tensors, dicts, lists, tuples and plain scalars.

    Exact types, not isinstance: numpy scalars subclass float but would be pickled as numpy
    objects, which `weights_only` loading refuses.
    """
    if isinstance(obj, torch.Tensor) or type(obj) in _PLAIN:
        return
    if isinstance(obj, dict):  # includes the OrderedDict of a state_dict
        for k, v in obj.items():
            if type(k) not in (str, int):
                raise TypeError(f"{where}: key {k!r} is a {type(k).__name__}, expected str or int")
            check_plain(v, f"{where}.{k}")
        return
    if type(obj) in (list, tuple):
        for i, v in enumerate(obj):
            check_plain(v, f"{where}[{i}]")
        return
    raise TypeError(f"{where}: {type(obj).__module__}.{type(obj).__qualname__} is not a tensor or a plain value")


def save_checkpoint(path: str | Path, state: dict) -> Path:
    """Write `state` (plus format and version) to `path` through a temporary file and a rename,
    so `path` always holds a complete checkpoint, even if the process dies mid-write."""
    path = Path(path)
    state = {"format": FORMAT, "version": VERSION, **state}
    check_plain(state)
    with atomic_path(path) as tmp:
        torch.save(state, tmp)
    return path


def shipped_checkpoints() -> dict[str, Path]:
    """The checkpoints that ship with the package: name -> model.pt (`SHIPPED_DIR/<name>/`)."""
    if not SHIPPED_DIR.is_dir():
        return {}
    return {d.name: d / "model.pt" for d in sorted(SHIPPED_DIR.iterdir()) if (d / "model.pt").is_file()}


def resolve_checkpoint(name_or_path: str | Path) -> Path:
    """A checkpoint file: an existing path, or the name of a shipped checkpoint (e.g.
    ``appearance-cpu``); otherwise an error naming both the path and the shipped names."""
    p = Path(name_or_path)
    if p.is_file():
        return p
    shipped = shipped_checkpoints()
    if str(name_or_path) in shipped:
        return shipped[str(name_or_path)]
    raise CheckpointError(f"{p}: no such checkpoint file, nor a shipped checkpoint "
                          f"(shipped: {', '.join(shipped) or 'none'})")


def load_checkpoint(path: str | Path) -> dict:
    """The checkpoint dict at `path`, loaded with weights_only=True onto the CPU."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"{path}: no such checkpoint file")
    if path.stat().st_size == 0:
        raise CheckpointError(f"{path}: not a loadable checkpoint (an empty file)")
    if not zipfile.is_zipfile(path):  # torch.save writes a zip; a bare pickle is never unpickled
        raise CheckpointError(f"{path}: not a loadable checkpoint (not the zip archive torch.save writes: "
                              f"truncated, or another kind of file)")
    try:
        with warnings.catch_warnings():  # torch warns about pickle protocols before refusing
            warnings.simplefilter("ignore")
            state = torch.load(path, weights_only=True, map_location="cpu")
    except Exception as exc:  # anything the unpickler or the zip reader raises: the file is at fault
        raise CheckpointError(f"{path}: not a loadable checkpoint ({_load_failure(exc)})") from None
    if not isinstance(state, dict) or state.get("format") != FORMAT or state.get("version") != VERSION:
        got = (f"format {state.get('format')!r}, version {state.get('version')!r}" if isinstance(state, dict)
               else f"a {type(state).__name__}")
        raise CheckpointError(f"{path}: {got}; expected format {FORMAT!r}, version {VERSION}")
    return state


def _load_failure(exc: Exception) -> str:
    """Why torch.load(weights_only=True) refused a file, in our words: torch's own message tells
    the reader to load with weights_only=False, which would run whatever code the file holds."""
    text = str(exc)
    if isinstance(exc, pickle.UnpicklingError) or "weights_only" in text:
        m = re.search(r"GLOBAL ([\w.]+)", text)  # "Unsupported global: GLOBAL x.y was not ..." and others
        what = f"a pickled Python object ({m[1]})" if m else "pickle instructions other than tensors and plain values"
        return (f"it holds {what}; a checkpoint holds tensors and plain values only, and this file is refused "
                f"without running its code")
    first = text.strip().split(". ")[0].strip().rstrip(".") or type(exc).__name__
    return f"a damaged torch archive: {' '.join(first.split())}"


def rng_state() -> dict:
    """The torch CPU, numpy global and Python `random` generator states, as plain values."""
    kind, key, pos, has_gauss, cached = np.random.get_state()
    version, internal, gauss_next = random.getstate()
    return {
        "torch": torch.get_rng_state(),
        "numpy": {"bit_generator": str(kind), "key": [int(k) for k in key], "pos": int(pos),
                  "has_gauss": int(has_gauss), "cached_gaussian": float(cached)},
        "python": {"version": int(version), "internal": list(internal), "gauss_next": gauss_next},
    }


def set_rng_state(state: dict) -> None:
    """Restore what `rng_state` returned."""
    torch.set_rng_state(state["torch"])
    n = state["numpy"]
    np.random.set_state((n["bit_generator"], np.asarray(n["key"], dtype=np.uint32), n["pos"],
                         n["has_gauss"], n["cached_gaussian"]))
    p = state["python"]
    random.setstate((p["version"], tuple(p["internal"]), p["gauss_next"]))


def seed_everything(seed: int) -> None:
    """Seed torch, numpy's global generator and Python's `random` from one integer."""
    torch.manual_seed(seed)
    np.random.seed(seed % 2**32)
    random.seed(seed)


# --- models from checkpoints (inference loads through here, never through the trainer) --------


def model_from_checkpoint(stage: Stage, run: RunConfig, ck: dict, path: Path) -> nn.Module:
    """`stage`'s model for `run`'s config with the weights of checkpoint `ck` (read from `path`),
    in eval mode."""
    model_cfg, _ = stage_configs(run, stage.model_config, stage.data_config)
    model = stage.build_model(model_cfg)
    try:
        model.load_state_dict(ck["model"])
    except RuntimeError as exc:
        first = (str(exc).strip().splitlines() or ["mismatch"])[0]
        raise CheckpointError(f"{path}: does not fit stage {stage.name!r}'s model: {first}") from None
    return model.eval()


def stage_checkpoint(stage: Stage, name_or_path: str | Path) -> tuple[Path, dict]:
    """The checkpoint file (a path or a shipped name) and its contents, which must be `stage`'s."""
    path = resolve_checkpoint(name_or_path)
    ck = load_checkpoint(path)
    if "stage" not in ck:
        raise CheckpointError(f"{path}: records no stage; expected a checkpoint of stage {stage.name!r}")
    if normalize_name(str(ck.get("stage"))) != normalize_name(stage.name):
        raise CheckpointError(f"{path}: a checkpoint of stage {ck.get('stage')!r}, not {stage.name!r}")
    return path, ck


def load_model(stage: Stage | str, checkpoint: str | Path) -> tuple[nn.Module, RunConfig]:
    """The model of a checkpoint (a run's last.pt / best.pt, `export_weights`'s file, or a shipped
    checkpoint's name: `checkpoint.resolve_checkpoint`), in eval mode, and the run config it was
    trained with."""
    stage = get_stage(stage) if isinstance(stage, str) else stage
    checkpoint, ck = stage_checkpoint(stage, checkpoint)
    run = config_from_dict(ck["config"], f"{checkpoint} (config)")
    return model_from_checkpoint(stage, run, ck, checkpoint), run


def export_weights(checkpoint: str | Path, out: str | Path) -> Path:
    """A run's checkpoint without what only resuming needs (optimiser moments, RNG states, data
    position): stage, config, model weights, step, epoch and best record. `evaluate`,
    `load_model` and `eval` read it like any checkpoint; `train --resume` cannot."""
    ck = load_checkpoint(checkpoint)
    keep = {k: ck[k] for k in ("stage", "config", "model", "step", "epoch", "best") if k in ck}
    keep["exported_from"] = str(Path(checkpoint).name)
    return save_checkpoint(out, keep)


