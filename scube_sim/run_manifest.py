"""Run manifests: the proof that an output folder holds one particular run, and how far it got.

A run (a `replay`, later each task of a batch) writes ``<OUT>/manifest.json`` first, before any
output, and rewrites it (atomically) when it ends::

    {"format": "scube-sim-run", "version": 1, "command": "replay",
     "inputs":   {"<role>": "<sha256>", ...},                every file the run reads, by role
                                                            (e.g. "scenario", "scene.voxsplat")
     "settings": {...},                                     everything else that shapes the outputs
     "status":   "running" | "complete" | "failed" | "interrupted",
     "error":    null | "<one line>",
     "outputs":  {"<path relative to OUT>": {"sha256": ..., "bytes": ...}, ...}}

Two runs are *the same* when command, inputs (checksums) and settings are equal: then, as every
output is a deterministic function of them, the outputs are too. `prepare_output` is the one
place that decides what may happen to an output folder:

- missing or empty (cache folders aside): a new run;
- not empty: refused, unless ``overwrite`` (clears a folder that holds a run manifest; one without
  is never cleared) or ``resume`` (continues the same run: complete and its outputs unchanged ->
  nothing to do; otherwise the outputs are cleared and the run is redone, which gives the same
  bytes as an uninterrupted run).

Cache folders (``keep``, e.g. the VoxSplat chunk cache ``scene_chunks``) survive both: their
entries carry their own keys and checksums. Timings are not stored, so a rerun's folder is
byte-identical.
"""

from __future__ import annotations

import hashlib
import json
import shutil
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from .atomic import atomic_path
from .config import json_loads
from .errors import InputError

MANIFEST_NAME = "manifest.json"
FORMAT = "scube-sim-run"
VERSION = 1
Status = Literal["running", "complete", "failed", "interrupted"]
STATUSES = ("running", "complete", "failed", "interrupted")


class OutputFolderError(InputError):
    """An output folder that this run may not write into (not empty, or another run's)."""


def sha256_file(path: str | Path, chunk: int = 1 << 20) -> str:
    """Hex SHA-256 of a file's bytes."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        while block := fh.read(chunk):
            h.update(block)
    return h.hexdigest()


@dataclass
class RunManifest:
    """See the module doc. `inputs`: path -> sha256; `outputs`: relative path -> {sha256, bytes}."""

    command: str
    inputs: dict[str, str] = field(default_factory=dict)
    settings: dict = field(default_factory=dict)
    status: Status = "running"
    error: str | None = None
    outputs: dict[str, dict] = field(default_factory=dict)

    @classmethod
    def for_inputs(cls, command: str, inputs: dict, settings: dict) -> RunManifest:
        """A new manifest; `inputs`: role -> file path, checksummed now and keyed by role (so a
        folder of inputs that moves, unchanged, is still the same run)."""
        sums = {}
        for role, p in inputs.items():
            p = Path(p)
            if not p.is_file():
                raise InputError(f"{role}: {p}: no such input file")
            sums[role] = sha256_file(p)
        return cls(command, sums, json.loads(json.dumps(settings)))

    def identity(self) -> dict:
        return {"command": self.command, "inputs": self.inputs, "settings": self.settings}

    def to_json(self) -> dict:
        return {"format": FORMAT, "version": VERSION, "command": self.command, "inputs": self.inputs,
                "settings": self.settings, "status": self.status, "error": self.error, "outputs": self.outputs}

    @classmethod
    def from_json(cls, data, source: str) -> RunManifest:
        if not isinstance(data, dict) or data.get("format") != FORMAT:
            raise InputError(f"{source}: not a scube-sim run manifest (expected 'format': {FORMAT!r})")
        if data.get("version") != VERSION:
            raise InputError(f"{source}: run manifest version {data.get('version')!r}; this scube-sim reads "
                             f"version {VERSION}")
        kinds = {"command": str, "inputs": dict, "settings": dict, "outputs": dict}
        for key, kind in kinds.items():
            if not isinstance(data.get(key), kind):
                raise InputError(f"{source}: key {key!r}: expected a {kind.__name__}, got {data.get(key)!r:.60}")
        if data.get("status") not in STATUSES:
            raise InputError(f"{source}: key 'status': expected one of {', '.join(STATUSES)}, "
                             f"got {data.get('status')!r:.60}")
        return cls(data["command"], data["inputs"], data["settings"], data["status"], data.get("error"),
                   data["outputs"])

    def save(self, folder: str | Path) -> Path:
        path = Path(folder) / MANIFEST_NAME
        with atomic_path(path) as tmp:
            Path(tmp).write_text(json.dumps(self.to_json(), indent=1, sort_keys=True) + "\n", encoding="utf-8")
        return path


def read_manifest(folder: str | Path) -> RunManifest | None:
    """The folder's run manifest, or None if it has none; a broken one is an `InputError`."""
    path = Path(folder) / MANIFEST_NAME
    if not path.is_file():
        return None
    try:
        data = json_loads(path.read_text(encoding="utf-8"), path, InputError)  # a key twice: refused
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputError(f"{path}: not valid JSON ({exc})") from exc
    return RunManifest.from_json(data, str(path))


def output_files(folder: str | Path, keep=()) -> dict[str, dict]:
    """Every file under `folder` except the manifest and the `keep` folders:
    relative POSIX path -> {"sha256", "bytes"}, sorted by path."""
    folder = Path(folder)
    out = {}
    for p in sorted(folder.rglob("*")):
        rel = p.relative_to(folder)
        if not p.is_file() or rel.parts[0] in keep or rel.as_posix() == MANIFEST_NAME:
            continue
        out[rel.as_posix()] = {"sha256": sha256_file(p), "bytes": p.stat().st_size}
    return out


def differences(old: RunManifest, new: RunManifest, limit: int = 3) -> list[str]:
    """What makes two runs not the same, as short phrases (at most `limit`)."""
    out = []
    if old.command != new.command:
        out.append(f"command {old.command!r} vs {new.command!r}")
    for key in sorted(set(old.inputs) | set(new.inputs)):
        if old.inputs.get(key) != new.inputs.get(key):
            what = "not an input" if key not in new.inputs else "new input" if key not in old.inputs else "changed"
            out.append(f"input {key} ({what})")
    out += [f"setting {k}" for k in _diff_keys(old.settings, new.settings)]
    return out[:limit]


def _diff_keys(a, b, prefix: str = "") -> list[str]:
    if isinstance(a, dict) and isinstance(b, dict):
        keys = []
        for k in sorted(set(a) | set(b), key=str):
            keys += _diff_keys(a.get(k), b.get(k), f"{prefix}{k}.")
        return keys
    return [] if a == b else [prefix.rstrip(".") or "(all)"]


def _entries(folder: Path, keep) -> list[Path]:
    return sorted(p for p in folder.iterdir() if p.name not in keep)


def _clear(folder: Path, keep) -> None:
    for p in _entries(folder, keep):
        if p.is_dir() and not p.is_symlink():
            shutil.rmtree(p)
        else:
            p.unlink()


def is_complete(folder: str | Path, manifest: RunManifest, keep=()) -> bool:
    """Whether `folder` holds the run `manifest` describes (same command, inputs and settings),
    complete, with every output file's checksum as recorded. A broken manifest counts as not."""
    try:
        old = read_manifest(folder)
    except InputError:
        return False
    return (old is not None and old.status == "complete" and not differences(old, manifest)
            and output_files(folder, keep) == old.outputs)


def prepare_output(folder: str | Path, manifest: RunManifest, *, overwrite: bool = False, resume: bool = False,
                   keep=()) -> str:
    """Make `folder` ready for the run `manifest` describes (see the module doc) and return
    "new" (start the run), "redo" (the same run, incomplete: start it again) or "complete"
    (the same run, finished, outputs verified: nothing to do). Writes the manifest with status
    "running" unless "complete". Raises `OutputFolderError` naming the folder otherwise."""
    folder = Path(folder)
    if overwrite and resume:
        raise OutputFolderError("--overwrite and --resume: give one (clear the folder, or continue its run)")
    if folder.exists() and not folder.is_dir():
        raise OutputFolderError(f"{folder}: the output folder is a file")
    entries = _entries(folder, keep) if folder.is_dir() else []
    old = read_manifest(folder) if entries else None
    if not entries:
        if resume:
            raise OutputFolderError(f"{folder}: --resume: nothing to resume (no run manifest {MANIFEST_NAME})")
        state = "new"
    elif overwrite:
        if old is None:
            raise OutputFolderError(f"{folder}: --overwrite: the folder holds files but no run manifest "
                                    f"({MANIFEST_NAME}); it is not ours to clear: choose another folder")
        _clear(folder, keep)
        state = "new"
    elif resume:
        if old is None:
            raise OutputFolderError(f"{folder}: --resume: the folder holds no run manifest ({MANIFEST_NAME})")
        diff = differences(old, manifest)
        if diff:
            raise OutputFolderError(f"{folder}: --resume: not the same run ({'; '.join(diff)}); use --overwrite "
                                    f"to replace it or another folder")
        if old.status == "complete" and output_files(folder, keep) == old.outputs:
            manifest.status, manifest.error, manifest.outputs = old.status, old.error, old.outputs
            return "complete"
        _clear(folder, keep)
        state = "redo"
    else:
        what = (f"a {old.command} run, status {old.status}" if old is not None
                else f"{len(entries)} entries, no run manifest")
        raise OutputFolderError(f"{folder}: the output folder is not empty ({what}); pass --overwrite to clear "
                                f"it or --resume to continue the same run")
    folder.mkdir(parents=True, exist_ok=True)
    manifest.status, manifest.error, manifest.outputs = "running", None, {}
    manifest.save(folder)
    return state


def finish_run(folder: str | Path, manifest: RunManifest, status: Status, error: str | None = None,
               keep=()) -> Path:
    """Record the end of a run: status, a one-line error, and every output file's checksum
    (on a failure: the files that are there, each of them complete, as every output is atomic)."""
    manifest.status, manifest.error = status, error
    manifest.outputs = output_files(folder, keep)
    return manifest.save(folder)
