"""The completion stage's data: the evidence of worlds samples, measured by the real stereo
pipeline and cached (`cache_evidence`, `scube-sim worlds evidence`), with the ground truth.

Cache: DATA/evidence/<split>/<sample>.npz, one per sample, written atomically:
``features`` (len(FEATURES), X, Y, Z) float16 (`features.completion_input`), ``key`` (JSON: the
evidence settings, the profile's context, the grid's voxel size and the features' version; a
sample whose key differs is measured again), ``seconds`` (the measurement's time). The cache is
rebuilt by the same command, never edited; `-j N` measures in N worker processes
(`EvidenceJob`, the batch runner: its batch.json and .batch/ beside the files), the same features
and keys whatever N.

Items (`CompletionDataset`): ``features`` (C, X, Y, Z) float32, ``occupancy`` (X, Y, Z) float32
and ``labels`` (X, Y, Z) int64 (-1 where empty): the ground truth's coarse voxels coarsened to
the grid (a cell is occupied if any child is; the most frequent label); ``fine_occupancy`` (fX,
fY, fZ) bool: the stored coarse voxels themselves (f = the grid's voxel size over theirs: 2 for
0.8 m cells over the worlds' 0.4 m), for the sub-cell head. Training items keep a
random `crop` x `crop` metre window in x, y and are mirrored left-right with probability one
half (seeded by seed, epoch and index); validation items are the whole chunk.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import torch
from pydantic import Field
from torch.utils.data import Dataset

from ...atomic import atomic_path
from ...camera.frames import chunk_to_world
from ...config import StrictModel, json_loads
from ...datasets import open_dataset
from ...datasets.base import frames_with_context
from ...errors import InputError
from ...parallel.runner import run_batch
from ...parallel.tasks import Job, Task
from ...reconstruct.evidence import measure_evidence
from ...transforms import invert_pose
from ...worlds.groundtruth import CHUNK_CORNER
from ..data.worlds import item_generator
from ..nn.lifting import LiftGrid, grid_in_box
from .features import FEATURES, coarse_dims, completion_input

__all__ = ["CompletionData", "CompletionDataset", "cache_evidence", "cache_path"]

FEATURES_VERSION = 2  # 2: the `looked` channel
CACHE_DIR = "evidence"


class CompletionData(StrictModel):
    """voxel_size: the grid's (metres; the stored coarse ground truth's size times a whole
    number); crop: training windows (metres, a multiple of 8 cells; None: the whole chunk);
    flip: mirror training items left-right (y) with probability one half."""

    voxel_size: float = Field(default=0.8, gt=0, le=10)
    crop: float | None = Field(default=51.2, gt=0)
    flip: bool = True


def cache_path(data_dir: Path, split: str, sample: str) -> Path:
    return Path(data_dir) / CACHE_DIR / split / f"{sample}.npz"


def _key(profile, voxel_size: float) -> str:
    return json.dumps({"evidence": profile.evidence.model_dump(mode="json"), "context": profile.context,
                       "voxel_size": voxel_size, "features": list(FEATURES), "version": FEATURES_VERSION},
                      sort_keys=True)


def _cached_key(path: Path) -> str | None:
    try:
        with np.load(path, allow_pickle=False) as z:
            return str(z["key"])
    except (OSError, ValueError, KeyError):
        return None  # damaged or from an interrupted writer: measured again


class EvidenceJob(Job):
    """`cache_evidence`'s batch job (`scube_sim.parallel`): one task per sample, keyed by its name.
    The cache file carries its own key, so the job keeps no task folder (`own_manifest`): the
    driver hands it only samples not cached with this key."""

    name = "evidence"
    own_manifest = True

    def __init__(self, data_dir: Path, split: str, prof, voxel_size: float, key: str):
        self.data_dir, self.split, self.prof, self.voxel_size, self.key = str(data_dir), split, prof, voxel_size, key

    def tasks(self, inputs: list[str], out: Path) -> list[Task]:
        return [Task(name, name, {"index": int(i)}) for name, i in (item.split("@") for item in inputs)]

    def run(self, task: Task, folder: Path, out: Path) -> dict:
        ds = _open_split(self.data_dir, self.split)
        i, cfg = task.params["index"], self.prof.evidence
        t0 = time.perf_counter()
        frames = frames_with_context(ds, i, self.prof.context) if self.prof.context else ds[i].frames
        ev = measure_evidence(frames, invert_pose(chunk_to_world(frames)), cfg)
        feats = completion_input(ev, self.voxel_size, min_confidence=cfg.fusion.min_confidence,
                                 pixel_stride=cfg.fusion_at_stereo_scale().pixel_stride, max_depth_m=cfg.fusion.max_depth_m)
        seconds = time.perf_counter() - t0
        path = cache_path(Path(self.data_dir), self.split, task.key)
        with atomic_path(path) as tmp:
            with open(tmp, "wb") as f:
                np.savez_compressed(f, features=feats.astype(np.float16), key=np.array(self.key),
                                    seconds=np.array(seconds))
        return {"seconds": seconds}

    def describe(self) -> dict:
        return {"profile": self.prof.name, "voxel_size": self.voxel_size}


_SPLITS: dict = {}  # (folder, split) -> the opened worlds split, once per worker process


def _open_split(data_dir: str, split: str):
    if (data_dir, split) not in _SPLITS:
        _SPLITS[(data_dir, split)] = open_dataset("worlds", Path(data_dir), split=split, eval_frames=False)
    return _SPLITS[(data_dir, split)]


def cache_evidence(data_dir: Path, split: str, prof, *, count: int | None = None, start: int = 0,
                   voxel_size: float = 0.8, jobs: int = 1, progress: bool = True) -> dict:
    """Measure and cache the evidence features of samples [start, start + count) of a worlds
    split (all from `start` when count is None) with the evidence route of the converter profile
    `prof` (a `ConverterProfile`, e.g. `load_profile("evidence")`), in this process (jobs 1) or
    `jobs` worker processes of one thread each (the files do not depend on it); samples already
    cached with the same key are skipped (resumable). Returns {written, skipped,
    seconds_per_sample} (a sample's measurement, not the wall time)."""
    if prof.route != "evidence":
        raise InputError(f"--profile: {prof.name!r} is route {prof.route!r}; the completion's evidence needs "
                         f"an evidence-route profile")
    data_dir = Path(data_dir)
    ds = open_dataset("worlds", data_dir, split=split, eval_frames=False)
    names = [d.name for d in ds.sample_dirs]
    stop = len(names) if count is None else min(len(names), start + count)
    if start >= stop:
        raise InputError(f"{data_dir / split}: no samples from {start} ({len(names)} in the split)")
    key = _key(prof, voxel_size)
    todo = [f"{names[i]}@{i}" for i in range(start, stop)
            if _cached_key(cache_path(data_dir, split, names[i])) != key]
    out = data_dir / CACHE_DIR / split
    rep = run_batch(EvidenceJob(data_dir, split, prof, voxel_size, key), [",".join(todo)] if todo else [], out,
                    executor="local" if jobs > 1 else "inline", workers=jobs, retries=0, progress=progress)
    if rep.failed:
        first = next(r for r in rep.records.values() if r["status"] == "failed")
        raise RuntimeError(f"{out}: {rep.failed} of {rep.total} samples failed; {first['input']}: {first['error']}")
    spent = [r["stats"]["seconds"] for r in rep.records.values() if r.get("stats", {}).get("seconds") is not None]
    return {"written": rep.completed, "skipped": stop - start - len(todo),
            "seconds_per_sample": float(np.mean(spent)) if spent else 0.0}


class CompletionDataset(Dataset):
    """The cached samples of one split that have ground truth (module docstring)."""

    def __init__(self, root: Path, split: str, cfg: CompletionData, seed: int = 0, train: bool | None = None):
        self.root, self.split, self.cfg, self.seed = Path(root), split, cfg, seed
        self.train = split == "train" if train is None else train
        folder = self.root / CACHE_DIR / split
        self.files = sorted(folder.glob("*.npz")) if folder.is_dir() else []
        self.epoch = 0
        self.dims = coarse_dims(cfg.voxel_size)
        if cfg.crop is not None:
            c = cfg.crop / cfg.voxel_size
            if abs(c - round(c)) > 1e-6 or round(c) % 8 or round(c) > self.dims[0]:
                raise InputError(f"data.crop: {cfg.crop} m is not a multiple of 8 cells of {cfg.voxel_size} m "
                                 f"within the chunk")

    def __len__(self) -> int:
        return len(self.files)

    def set_epoch(self, epoch: int) -> None:
        self.epoch = epoch

    def _target(self, sample: str) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        path = self.root / self.split / sample / "voxels.npz"
        if not path.is_file():
            raise InputError(f"{path}: missing ground-truth voxels")
        with np.load(path, allow_pickle=False) as z:
            ijk, lab, vis, stored = z["coarse_ijk"], z["coarse_labels"], z["coarse_visible"], float(z["coarse_voxel_size"])
        factor = int(round(self.cfg.voxel_size / stored))
        if factor < 1 or abs(self.cfg.voxel_size / stored - factor) > 1e-6:
            raise InputError(f"{path}: voxel size {self.cfg.voxel_size} m is not a whole multiple of the stored "
                             f"{stored} m")
        grid = LiftGrid(tuple(float(v) for v in CHUNK_CORNER), self.cfg.voxel_size, self.dims)
        rel, labels, _ = grid_in_box(torch.from_numpy(ijk.astype(np.int64)), torch.from_numpy(lab.astype(np.int64)),
                                     torch.from_numpy(vis), factor, stored, grid)
        occ = torch.zeros(self.dims)
        tl = torch.full(self.dims, -1, dtype=torch.int64)
        occ[rel[:, 0], rel[:, 1], rel[:, 2]] = 1.0
        tl[rel[:, 0], rel[:, 1], rel[:, 2]] = labels
        # the stored voxels themselves (the grid's corner is the chunk's): where in a cell the truth lies
        fine_dims = tuple(d * factor for d in self.dims)
        f = torch.from_numpy(ijk.astype(np.int64))
        f = f[((f >= 0) & (f < torch.tensor(fine_dims))).all(1)]
        fine = torch.zeros(fine_dims, dtype=torch.bool)
        fine[f[:, 0], f[:, 1], f[:, 2]] = True
        return occ, tl, fine

    def __getitem__(self, index: int) -> dict:
        path = self.files[index]
        with np.load(path, allow_pickle=False) as z:
            feats = torch.from_numpy(z["features"].astype(np.float32))
            key = json_loads(str(z["key"]), str(path))
        if feats.shape[0] != len(FEATURES):
            raise InputError(f"{path}: {feats.shape[0]} feature channels, this version reads {len(FEATURES)} "
                             f"(rebuild: scube-sim worlds evidence)")
        if abs(key.get("voxel_size", -1) - self.cfg.voxel_size) > 1e-9:
            raise InputError(f"{path}: cached at {key.get('voxel_size')} m, data.voxel_size is {self.cfg.voxel_size} m "
                             f"(rebuild: scube-sim worlds evidence)")
        occ, labels, fine = self._target(path.stem)
        if self.train:
            gen = item_generator(self.seed + 11, self.epoch, index)
            if self.cfg.crop is not None:
                c = int(round(self.cfg.crop / self.cfg.voxel_size))
                x0, y0 = (int(torch.randint(0, (d - c) // 8 + 1, (1,), generator=gen)) * 8 for d in self.dims[:2])
                feats, occ, labels = (t[..., x0:x0 + c, y0:y0 + c, :] for t in (feats, occ, labels))
                f = fine.shape[0] // self.dims[0]
                fine = fine[x0 * f:(x0 + c) * f, y0 * f:(y0 + c) * f]
            if self.cfg.flip and bool(torch.randint(0, 2, (1,), generator=gen)):
                feats, occ, labels, fine = (t.flip(-2) for t in (feats, occ, labels, fine))
        return {"features": feats.contiguous(), "occupancy": occ.contiguous(), "labels": labels.contiguous(),
                "fine_occupancy": fine.contiguous(), "sample": path.stem}
