"""The jobs of `scube-sim batch`: what one task of each does, what identifies it, where it writes.

    worlds   SPLIT:INDEX | SPLIT:FIRST-LAST   -> OUT/<split>/<index:06d>/ (a worlds dataset folder)
    build    a dataset folder (one log)       -> OUT/<folder name>/scene.npz   (`scube-sim build`)
    replay   a scenario YAML                  -> OUT/<stem>[/seed-<S>][/<edit>]/  (`scube-sim replay`),
                                                 × `seeds` × `edits` (a counterfactual sweep)
    convert  a worlds sample folder, or a     -> OUT/<split>/<sample>/scene.npz, or
             dataset folder (`dataset`)          OUT/<folder name>/<index:06d>/scene.npz (`scube-sim convert`)

Settings (one YAML mapping for the whole batch, validated here) are those of the single commands.
A task is identified by its settings and a fingerprint of its input folder (every file's path,
size and modification time: reading a log's gigabytes to checksum it would cost more than the
build); a changed input or setting reruns the task.
"""

from __future__ import annotations

import hashlib
from dataclasses import asdict, fields
from pathlib import Path

from pydantic import Field, ValidationError, field_validator

from .._version import __version__
from ..config import (
    BOUND_ERRORS,
    CONFIDENCE_SAMPLES,
    CONTEXT_INSTANTS,
    DDIM_STEPS,
    MAX_RANGE_M,
    SAMPLE_INDEX,
    SEED,
    StrictModel,
    field_range,
    unique_names,
)
from ..converter.profile import DEFAULT_PROFILE, load_profile
from ..datasets import open_dataset
from ..errors import InputError
from ..parallel.tasks import BatchError, Job, Task
from ..realdata.build import BuildOptions, build_from_dataset, check_build_lists
from ..run_manifest import RunManifest, read_manifest, sha256_file
from ..worlds.dataset import DatasetConfig, WorldsJob
from .replay import replay, replay_manifest
from .scenario import CACHE_FOLDERS, EditSpec

SCENE_FILE = "scene.npz"


def folder_fingerprint(path: Path) -> dict:
    """{files, bytes, digest}: a SHA-256 over every file's relative path, size and mtime (ns)."""
    path = Path(path)
    if not path.exists():
        raise BatchError(f"{path}: no such input")
    files = [path] if path.is_file() else sorted(p for p in path.rglob("*") if p.is_file())
    h = hashlib.sha256()
    total = 0
    for p in files:
        st = p.stat()
        total += st.st_size
        h.update(f"{p.relative_to(path).as_posix() if p != path else p.name}\0{st.st_size}\0{st.st_mtime_ns}\n".encode())
    return {"files": len(files), "bytes": total, "digest": h.hexdigest()}


def _validate(model, data: dict, job: str):
    try:
        return model.model_validate(data or {})
    except ValidationError as exc:
        err = exc.errors()[0]
        where = ".".join(str(p) for p in err["loc"]) or "(settings)"
        rng = field_range(model, err["loc"]) if err["type"] in BOUND_ERRORS else None  # the whole range
        msg = (f"expected {rng.describe()}, got {err['input']!r}" if rng is not None
               else err["msg"].removeprefix("Value error, "))  # our validators' own words
        raise BatchError(f"batch {job} settings: {where}: {msg}") from None


def _unique_names(paths: list[Path], job: str) -> list[str]:
    names = [p.name for p in paths]
    for n in set(names):
        if names.count(n) > 1:
            clash = [str(p) for p in paths if p.name == n]
            raise BatchError(f"batch {job}: inputs {clash[0]} and {clash[1]} share the name {n!r}, and so the output "
                             f"folder; run them as two batches")
    return names


class BuildSettings(StrictModel):
    dataset: str
    options: dict = Field(default_factory=dict)  # BuildOptions fields (samples, voxel_size, remove, ...)


class BuildJob(Job):
    """Real LiDAR -> VoxSplat per log (`reconstruct.build_from_dataset`)."""

    name = "build"

    def __init__(self, settings: dict):
        self.settings = _validate(BuildSettings, settings, self.name)
        names = {f.name for f in fields(BuildOptions)}
        bad = sorted(set(self.settings.options) - names)
        if bad:
            raise BatchError(f"batch build settings: options.{bad[0]}: not a build option (expected: "
                             f"{', '.join(sorted(names))})")
        try:
            self.options = BuildOptions(**{"samples": [0], **self.settings.options})
            check_build_lists(self.options)  # a sample or sensor listed twice
        except InputError as exc:  # a number out of its range: `realdata.options.BUILD_RANGES`
            raise BatchError(f"batch build settings: options.{exc}") from None

    def tasks(self, inputs, out):
        paths = [Path(p) for p in inputs]
        for p in paths:
            if not p.is_dir():
                raise BatchError(f"batch build: --inputs {p}: not a dataset folder")
        return [Task(n, str(p), {"path": str(p.absolute())}) for n, p in zip(_unique_names(paths, self.name), paths)]

    def manifest(self, task, out):
        return RunManifest("build", {}, {"input": folder_fingerprint(Path(task.params["path"])),
                                         "dataset": self.settings.dataset, "options": asdict(self.options),
                                         "scube_sim": __version__})

    def run(self, task, folder, out):
        vs, rep, _ = build_from_dataset(open_dataset(self.settings.dataset, task.params["path"]), self.options)
        vs.save(folder / SCENE_FILE)
        return {"points": rep.points, "voxels": rep.voxels, "gaussians": rep.gaussians}

    def describe(self):
        return {"dataset": self.settings.dataset, "options": asdict(self.options)}


class ReplaySettings(StrictModel):
    duration_s: float | None = Field(default=None, gt=0, le=86_400)
    seeds: list[SEED.annotated()] | None = None  # one replay per seed (default: the scenario's own)
    edits: dict[str, EditSpec] | None = None  # one replay per named trajectory edit, replacing the scenario's

    _seeds_once = field_validator("seeds")(classmethod(lambda cls, v: unique_names(v)))  # one run folder each


class ReplayJob(Job):
    """Scenario replays (`sim.replay`), optionally × seeds × edits. Runs of one scenario file share
    one VoxSplat chunk cache (OUT/.cache/<stem>-<hash>/), so a sweep fits its world once."""

    name = "replay"
    own_manifest = True
    keep = CACHE_FOLDERS

    def __init__(self, settings: dict):
        self.settings = _validate(ReplaySettings, settings, self.name)  # seeds: each in SEED's range

    def tasks(self, inputs, out):
        paths = [Path(p) for p in inputs]
        for p in paths:
            if not p.is_file():
                raise BatchError(f"batch replay: --inputs {p}: no such scenario file")
        stems = _unique_names([p.with_suffix("") for p in paths], self.name)
        seeds = self.settings.seeds or [None]
        edits = list(self.settings.edits or {}) or [None]
        tasks = []
        for stem, p in zip(stems, paths):
            for seed in seeds:
                for edit in edits:
                    key = "/".join([stem] + ([f"seed-{seed}"] if seed is not None else []) + ([edit] if edit else []))
                    tasks.append(Task(key, str(p), {"path": str(p.absolute()), "seed": seed, "edit": edit}))
        return tasks

    def _args(self, task):
        edit = task.params["edit"]
        return {"duration": self.settings.duration_s, "seed": task.params["seed"],
                "edit": self.settings.edits[edit].model_dump() if edit else None}

    def manifest(self, task, out):
        return replay_manifest(task.params["path"], **self._args(task))[2]

    def run(self, task, folder, out):
        path = Path(task.params["path"])
        cache = Path(out) / ".cache" / f"{path.stem}-{hashlib.sha256(str(path).encode()).hexdigest()[:8]}"
        r = replay(path, folder, **self._args(task), resume=read_manifest(folder) is not None if folder.is_dir() else False,
                   cache=cache, progress=False)
        return {"state": r.state, "ticks": r.ticks, "sweeps": r.sweeps, "points": r.points}

    def describe(self):
        return self.settings.model_dump(mode="json")


class ConvertSettings(StrictModel):
    dataset: str | None = None  # None: each input is a worlds sample folder
    samples: list[SAMPLE_INDEX.annotated()] = Field(default_factory=lambda: [0])  # with `dataset`: each folder's
    profile: str = DEFAULT_PROFILE
    steps: int | None = DDIM_STEPS.field(None)
    seed: int = SEED.field(0)
    confidence: int = CONFIDENCE_SAMPLES.field(0)  # K geometry samples for per-voxel confidence (0: off)
    sky: bool = True
    max_range: float | None = MAX_RANGE_M.field(None)
    # instants before and after in the same log (convert --context); None: the profile's own
    context: int | None = CONTEXT_INSTANTS.field(None)

    _samples_once = field_validator("samples")(classmethod(lambda cls, v: unique_names(v)))  # one task each


class ConvertJob(Job):
    """Camera frames -> VoxSplat (`scube_sim.convert`). The converter loads once per worker process
    (`converter.pipeline.convert` keeps it), not once per task."""

    name = "convert"

    def __init__(self, settings: dict):
        self.settings = _validate(ConvertSettings, settings, self.name)
        if self.settings.confidence == 1:
            raise BatchError("batch convert settings: confidence: expected 0 (off) or K >= 2 samples, got 1")
        self._weights: dict | None = None

    def prepare(self, out):
        from ..model.checkpoint import resolve_checkpoint

        s = self.settings
        profile = load_profile(s.profile)
        unset = {"steps": s.steps is None, "confidence": s.confidence == 0, "sky": s.sky}
        paper = [k for k, off in unset.items() if not off]
        if paper and profile.route != "scube":
            raise BatchError(f"batch convert settings: {', '.join(paper)}: profile {profile.name!r} is route "
                             f"{profile.route}, which does not use {'it' if len(paper) == 1 else 'them'}")
        # every checkpoint the profile names: a retrained one under the same name converts again
        self._weights = {"profile": profile.model_dump(mode="json"),
                         "checkpoints": {stage: sha256_file(resolve_checkpoint(name))
                                         for stage, name in profile.checkpoints().items()}}

    def tasks(self, inputs, out):
        paths = [Path(p) for p in inputs]
        tasks = []
        if self.settings.dataset is None:
            for p in paths:
                if not (p / "meta.json").is_file():
                    raise BatchError(f"batch convert: --inputs {p}: not a worlds sample folder (DIR/<split>/NNNNNN); "
                                     f"set `dataset` for other folders")
            keys = [f"{p.absolute().parent.name}/{p.name}" for p in paths]
            for k in keys:
                if keys.count(k) > 1:
                    raise BatchError(f"batch convert: two inputs are both {k}; run them as two batches")
            return [Task(k, str(p), {"path": str(p.absolute()), "sample": 0}) for k, p in zip(keys, paths)]
        for p in paths:
            if not p.exists():
                raise BatchError(f"batch convert: --inputs {p}: no such dataset folder")
        for name, p in zip(_unique_names(paths, self.name), paths):
            tasks += [Task(f"{name}/{i:06d}", f"{p}#{i}", {"path": str(p.absolute()), "sample": i})
                      for i in self.settings.samples]
        return tasks

    def manifest(self, task, out):
        s = self.settings
        return RunManifest("convert", {}, {"input": folder_fingerprint(Path(task.params["path"])),
                                           "sample": task.params["sample"],
                                           # the profile's context left out: batches run before the option resume
                                           "settings": s.model_dump(mode="json", exclude={"context"} if s.context is None
                                                                    else None),
                                           **self._weights, "scube_sim": __version__})

    def run(self, task, folder, out):
        from ..converter.frames import open_frames
        from ..converter.pipeline import convert, is_loaded

        s = self.settings
        context = load_profile(s.profile).context if s.context is None else s.context
        frames = open_frames(task.params["path"], s.dataset, task.params["sample"], context=context)
        loaded = not is_loaded(s.profile)
        options = {} if load_profile(s.profile).route != "scube" else {
            "steps": s.steps, "confidence": s.confidence > 1, "confidence_samples": s.confidence or None, "sky": s.sky}
        vs = convert(frames, profile=s.profile, seed=s.seed, max_range=s.max_range, **options)
        vs.save(folder / SCENE_FILE)
        return {"model_loaded": loaded, "voxels": vs.num_voxels, "gaussians": vs.num_gaussians}

    def describe(self):
        return {**self.settings.model_dump(mode="json"), **(self._weights or {})}


def make_job(name: str, settings: dict | None = None) -> Job:
    """The job called `name` with its settings (a mapping; for worlds: DatasetConfig fields, or
    none to use the dataset folder's own)."""
    settings = settings or {}
    if name == "worlds":
        return WorldsJob(_validate(DatasetConfig, settings, name) if settings else None)
    if name in JOBS:
        return JOBS[name](settings)
    raise BatchError(f"batch: unknown job {name!r}; expected one of worlds, {', '.join(JOBS)}")


JOBS = {"build": BuildJob, "replay": ReplayJob, "convert": ConvertJob}
JOB_NAMES = ("worlds", *JOBS)
