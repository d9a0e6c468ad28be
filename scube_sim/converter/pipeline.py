"""The converter: a profile's pipeline loaded once (`Converter`), and `convert` for one call.

A profile's `route` picks the pipeline, and each takes only the options that mean something to
it: `evidence.EvidencePipeline` (measured geometry, then the learned completion) and
`scube.PaperPipeline` (the paper's two networks). Both return a `Conversion`.
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable, Protocol

import numpy as np

from ..camera.frames import Frames
from ..cpus import resolve_threads
from ..errors import InputError
from ..voxsplat import VoxSplat
from .conversion import Conversion, checkpoint_hashes, torch_threads
from .evidence import EvidencePipeline
from .profile import DEFAULT_PROFILE, ConverterProfile, load_profile
from .scube import TRACE_MODE, PaperPipeline

__all__ = ["TRACE_MODE", "Conversion", "Converter", "Pipeline", "convert", "is_loaded"]


class Pipeline(Protocol):
    """A route's conversion: its networks loaded from the profile, `paths` the checkpoint files
    they came from, `OPTIONS` the keyword options `convert` takes besides seed, max_range and
    status (called with one line as each stage starts)."""

    OPTIONS: tuple[str, ...]
    paths: dict[str, Path]

    def convert(self, frames: Frames, *, seed: int = 0, max_range: float | None = None,
                status: Callable[[str], None] | None = None, **options) -> Conversion:
        ...


PIPELINES: dict[str, type] = {"scube": PaperPipeline, "evidence": EvidencePipeline}


class Converter:
    """A profile's pipeline, loaded once; `convert` turns frames into a `Conversion`."""

    def __init__(self, profile: str | Path | ConverterProfile = DEFAULT_PROFILE):
        self.profile = load_profile(profile)
        self.pipeline: Pipeline = PIPELINES[self.profile.route](self.profile)

    def checkpoint_hashes(self) -> dict[str, str]:
        """sha256 of every checkpoint the profile's pipeline loaded (provenance)."""
        return checkpoint_hashes(self.pipeline.paths)

    def convert(self, frames: Frames, *, seed: int = 0, max_range: float | None = None,
                status: Callable[[str], None] | None = None, **options) -> Conversion:
        """Frames -> `Conversion` (the scene in the chunk frame, timings, intermediates). seed: the
        paper route's sampler (an integer >= 0); max_range: metres (horizontal) from the ego a voxel's
        centre may lie; status: called with one line as each stage starts (a command's progress);
        `options`: the pipeline's own (`PaperPipeline.convert`, `EvidencePipeline.convert`),
        any other refused with one line naming the profile's route and what it takes."""
        unknown = sorted(set(options) - set(self.pipeline.OPTIONS))
        if unknown:
            takes = ", ".join(self.pipeline.OPTIONS)
            raise InputError(f"{', '.join(unknown)}: profile {self.profile.name!r} (route {self.profile.route}) "
                             f"does not use {'it' if len(unknown) == 1 else 'them'}; it takes seed, max_range, {takes}")
        if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
            raise InputError(f"seed: expected an integer >= 0, got {seed!r}")
        if max_range is not None and not (np.isfinite(max_range) and max_range > 0):
            raise InputError(f"max_range: expected a positive number of metres, got {max_range}")
        # the CPUs this process may use (`cpus.resolve_threads`), not torch's count of the machine's cores
        with torch_threads(resolve_threads(None)):
            return self.pipeline.convert(frames, seed=int(seed), max_range=max_range, status=status, **options)


_CACHE: dict[str, Converter] = {}


def is_loaded(profile: str | Path | ConverterProfile) -> bool:
    """Whether `convert` already holds this profile's converter in this process."""
    return _cache_key(profile) in _CACHE


def _cache_key(profile: str | Path | ConverterProfile) -> str:
    return profile.model_dump_json() if isinstance(profile, ConverterProfile) else str(profile)


def convert(frames: Frames, *, profile: str | Path | ConverterProfile = DEFAULT_PROFILE, seed: int = 0,
            max_range: float | None = None, **options) -> VoxSplat:
    """`Converter(profile).convert(frames, ...).scene`, with the loaded converter kept per profile
    name or path for the next call."""
    key = _cache_key(profile)
    if key not in _CACHE:
        _CACHE[key] = Converter(profile)
    return _CACHE[key].convert(frames, seed=seed, max_range=max_range, **options).scene
