"""What a conversion gives (`Conversion`) and what both routes share: checkpoint provenance, the
record of the instants used, and torch held to one thread while a network runs."""

from __future__ import annotations

import contextlib
from dataclasses import dataclass, field
from pathlib import Path

import torch

from ..camera.frames import Frames
from ..run_manifest import sha256_file
from ..voxsplat import VoxSplat
from .frames import context_record
from .merge import CompletionGrid

__all__ = ["Conversion", "checkpoint_hashes", "context_metadata", "one_torch_thread", "torch_threads"]


@dataclass
class Conversion:
    """One conversion: the `scene` (VoxSplat, chunk frame), `timings` (seconds per stage under the
    route's own keys, and peak_mb), and what an evaluator reads besides: the evidence route's scene
    before the completion (`uncompleted`) and the completion's coarse grid."""

    scene: VoxSplat
    timings: dict[str, float] = field(default_factory=dict)
    uncompleted: VoxSplat | None = None
    completion_grid: CompletionGrid | None = None


_HASHES: dict[tuple[str, int, int], str] = {}


def checkpoint_hashes(paths: dict[str, Path]) -> dict[str, str]:
    """sha256 of each named checkpoint file (provenance), computed once per file and version."""
    out = {}
    for name, path in paths.items():
        st = Path(path).stat()
        key = (str(Path(path).resolve()), st.st_size, st.st_mtime_ns)
        if key not in _HASHES:
            _HASHES[key] = sha256_file(path)
        out[name] = _HASHES[key]
    return out


def context_metadata(frames: Frames, used: str) -> dict:
    """The scene's record of the instants it was given (none for a single instant: its output stays
    as it was), with how the route used them."""
    return {"instants": context_record(frames), "instants_used": used} if frames.context else {}


@contextlib.contextmanager
def torch_threads(threads: int):
    """torch on `threads` intra-op threads for the block, restored afterwards."""
    before = torch.get_num_threads()
    torch.set_num_threads(int(threads))
    try:
        yield
    finally:
        torch.set_num_threads(before)


def one_torch_thread():
    """torch on one intra-op thread for the block (`torch_threads(1)`). The networks' convolutions
    and matrix products split their sums by thread count, so their float results (1e-6 apart) and
    the file's bytes would depend on it; `convert` and a batch worker must write the same file.
    It costs a single conversion its second core; a batch runs samples side by side instead."""
    return torch_threads(1)
