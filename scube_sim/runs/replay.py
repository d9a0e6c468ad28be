"""One scenario replay into an output folder, under its run manifest (`scube_sim.run_manifest`):
what `scube-sim replay` runs, and each task of a `replay` batch (`scube_sim.batch`)."""

from __future__ import annotations

import contextlib
import time
from dataclasses import dataclass
from pathlib import Path

from ..config import ConfigError
from ..run_manifest import finish_run, prepare_output
from .scenario import CACHE_FOLDERS, EditSpec, build_run, load_scenario, run_manifest


@dataclass
class ReplayResult:
    """What one replay did. state: "new" | "redo" | "complete" (already there, nothing run)."""

    name: str
    state: str
    ticks: int = 0
    sweeps: int = 0
    points: int = 0
    simulated_s: float = 0.0
    setup_s: float = 0.0
    run_s: float = 0.0
    outputs: int = 0


def replay(scenario: str | Path, output: str | Path, *, duration: float | None = None, seed: int | None = None,
           edit: dict | None = None, overwrite: bool = False, resume: bool = False, cache: Path | None = None,
           progress: bool = True, echo=None) -> ReplayResult:
    """Run `scenario` (a YAML path) into the folder `output`.

    duration, seed: override the scenario's (seconds > 0; an integer >= 0). edit: a
    `trajectory.edit` mapping that replaces the scenario's own (a counterfactual). overwrite /
    resume: as `prepare_output`. cache: the VoxSplat chunk cache (default output/scene_chunks).
    The run manifest is finished as "complete", "failed" or "interrupted" (Ctrl-C) before an
    exception propagates. echo: a callable for set-up messages, or None."""
    sc, base, manifest = replay_manifest(scenario, duration=duration, seed=seed, edit=edit)
    state = prepare_output(output, manifest, overwrite=overwrite, resume=resume, keep=CACHE_FOLDERS)
    result = ReplayResult(sc.name, state)
    if state == "complete":
        result.outputs = len(manifest.outputs)
        return result
    try:
        t0 = time.perf_counter()
        sim, source, t_start, t_end = build_run(sc, base, Path(output), progress=echo, cache=cache)
        t1 = time.perf_counter()
        for frame in sim.run(source, t_start=t_start, t_end=t_end, dt=1.0 / sc.tick_hz, progress=progress):
            result.ticks += 1
            for s in frame.sweeps():
                result.sweeps += 1
                result.points += len(s.points)
        t2 = time.perf_counter()
    except BaseException as exc:
        status = "interrupted" if isinstance(exc, KeyboardInterrupt) else "failed"
        with contextlib.suppress(OSError):  # a full disk: the manifest stays "running", not complete
            finish_run(output, manifest, status, " ".join(str(exc).split()) or type(exc).__name__,
                       keep=CACHE_FOLDERS)
        raise
    finish_run(output, manifest, "complete", keep=CACHE_FOLDERS)
    result.simulated_s, result.setup_s, result.run_s = t_end - t_start, t1 - t0, t2 - t1
    result.outputs = len(manifest.outputs)
    return result


def replay_manifest(scenario: str | Path, *, duration: float | None = None, seed: int | None = None,
                    edit: dict | None = None):
    """The scenario with the overrides applied (`replay`'s arguments), its folder, and the run
    manifest a complete replay of it carries: (Scenario, base folder, RunManifest)."""
    sc, base = load_scenario(scenario)
    if duration is not None:
        if not duration > 0:
            raise ConfigError(f"--duration: expected > 0 seconds, got {duration}")
        sc.duration_s = duration
    if seed is not None:
        if seed < 0:
            raise ConfigError(f"--seed: expected a non-negative integer, got {seed}")
        sc.seed = seed
    if edit is not None:
        sc.trajectory.edit = EditSpec.model_validate(edit)
    return sc, base, run_manifest(sc, base, scenario)
