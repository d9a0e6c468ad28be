"""The one trainer both converter stages use: Adam, deterministic data order, checkpoints that
resume bit for bit, and data-parallel training over CPU processes (torch.distributed, gloo).

A run folder holds::

    config.yaml     the resolved config (every default filled in)
    last.pt         the latest checkpoint (see `checkpoint`), written before the first step, every
                    `checkpoint_every` steps, at each epoch end and at the last step
    best.pt         the checkpoint with the best validation primary metric (train.keep_best)
    metrics.jsonl   one validation record per line: {"step", "epoch", "train": {means since the
                    previous record}, "val": {the stage's metrics}}
    loss.png        the training loss per step and the validation metric, written at the end

Why a resumed run reaches the same weights bit for bit: everything the next step depends on is in
the checkpoint (weights, Adam's moments, every rank's torch/numpy/random generator state, the
epoch and the batch position within it), the data order is a pure function of (seed, epoch), the
DataLoader draws its worker seed from its own generator instead of torch's global one, and
validation restores the generator states it may have consumed. Files are replaced by rename, and
best.pt is written before last.pt, so a kill at any moment leaves a last.pt that describes a
consistent earlier point from which the rest of the run replays identically.
"""

from __future__ import annotations

import json
import math
import tempfile
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
import torch.distributed as dist
import torch.multiprocessing as mp
import yaml
from rich.progress import Progress
from torch import nn
from torch.utils.data import DataLoader, Dataset

from ..atomic import atomic_path
from ..config import ConfigError, normalize_name
from ..errors import InputError, ScubeSimError
from .checkpoint import (
    CheckpointError,
    load_checkpoint,
    model_from_checkpoint,
    rng_state,
    save_checkpoint,
    seed_everything,
    set_rng_state,
    stage_checkpoint,
)
from .config import RunConfig, TrainConfig, config_from_dict, resolved_config, stage_configs, torch_settings
from .evaluate import bar_columns, evaluate_model
from .stages import Stage, StageError, get_stage

LAST, BEST, METRICS, CURVE, CONFIG = "last.pt", "best.pt", "metrics.jsonl", "loss.png", "config.yaml"



# `train` keys a resumed run may change: they set how long the run goes on and how it is executed,
# not the sequence of updates up to a given step.
RESUMABLE_KEYS = ("train.epochs", "train.steps", "train.checkpoint_every", "train.num_workers")


class TrainingError(ScubeSimError):
    """Training that cannot go on (a non-finite loss, a failed rank)."""


def learning_rate(tc: TrainConfig, step: int, total_steps: int) -> float:
    """The learning rate of update `step` (0-based) of a run of `total_steps` updates."""
    if step < tc.warmup_steps:
        return tc.lr * (step + 1) / tc.warmup_steps
    if tc.lr_schedule == "constant":
        return tc.lr
    span = max(1, total_steps - tc.warmup_steps - 1)
    p = min(1.0, (step - tc.warmup_steps) / span)
    return tc.lr * (tc.lr_final_ratio + (1.0 - tc.lr_final_ratio) * 0.5 * (1.0 + math.cos(math.pi * p)))


def _derive_seed(*parts: int) -> int:
    """A 63-bit seed that is a function of the integers `parts` (numpy's SeedSequence mixing)."""
    return int(np.random.SeedSequence([int(p) for p in parts]).generate_state(1, dtype=np.uint64)[0] >> np.uint64(1))


def epoch_order(n: int, seed: int, epoch: int) -> np.ndarray:
    """(n,) int64 permutation of range(n) for one epoch: a function of (seed, epoch) only."""
    return np.random.default_rng([seed, epoch]).permutation(n)


class ShardSampler:
    """The index lists one rank loads in one epoch, from global batch `start` on.

    Global batch b of the epoch is order[b * B:(b + 1) * B] with order = epoch_order(n, seed,
    epoch) and B the global batch size; n // B batches make an epoch. Rank r of `world` takes the
    r-th contiguous slice of B / world indices, so the shards are disjoint and equal in size and,
    in rank order, make up the global batch.
    """

    def __init__(self, n: int, batch_size: int, seed: int, epoch: int, start: int = 0, rank: int = 0, world: int = 1):
        if batch_size % world:
            raise ValueError(f"batch_size {batch_size} does not split over {world} ranks")
        self.n, self.batch_size, self.seed, self.epoch = n, batch_size, seed, epoch
        self.start, self.rank, self.world = start, rank, world

    @property
    def batches_per_epoch(self) -> int:
        return self.n // self.batch_size

    def __len__(self) -> int:
        return max(0, self.batches_per_epoch - self.start)

    def __iter__(self):
        order = epoch_order(self.n, self.seed, self.epoch)
        shard = self.batch_size // self.world
        for b in range(self.start, self.batches_per_epoch):
            lo = b * self.batch_size + self.rank * shard
            yield order[lo:lo + shard].tolist()


@dataclass
class TrainResult:
    """What a finished `train` call leaves: paths, counters, the last and best validation."""

    run_dir: Path
    last: Path
    best: Path | None
    step: int
    epoch: int  # epochs completed
    metrics: dict[str, float]  # the last validation
    best_metric: float | None
    best_step: int | None
    model: nn.Module  # the final weights (from last.pt), in eval mode


@dataclass
class _Job:
    """Everything a rank needs; pickled to spawned ranks (without the parent's datasets)."""

    stage: Stage
    resolved: dict
    data_dir: Path
    out_dir: Path
    resume: bool
    world: int
    steps_per_epoch: int
    total_steps: int
    train_samples: int
    datasets: tuple[Dataset, Dataset] | None = None

    def __getstate__(self):
        return {**self.__dict__, "datasets": None}  # each spawned rank opens its own


@dataclass
class _State:
    """The loop's counters and history (all of it goes into the checkpoint)."""

    step: int = 0  # optimiser steps done
    epoch: int = 0  # epochs completed (= index of the current epoch)
    batch: int = 0  # batches done in the current epoch: where its sampler resumes
    train_log: dict[str, list[float]] = field(default_factory=dict)  # "loss" and extra terms, one value a step
    records: list[dict] = field(default_factory=list)  # per validation, as in metrics.jsonl
    best_value: float | None = None
    best_step: int | None = None


def train(stage: Stage | str, run_cfg: RunConfig, data_dir: str | Path, out_dir: str | Path, resume: bool = False,
          progress: bool = True, ranks: int | None = None,
          on_step: Callable[[int, dict[str, float]], None] | None = None) -> TrainResult:
    """Train `stage` as `run_cfg` says on the data folder `data_dir`, into the run folder `out_dir`.

    resume: continue from out_dir/last.pt (the config may differ only in RESUMABLE_KEYS).
    ranks: processes (default train.ranks); more than one spawns them (gloo backend).
    on_step(step, logs): called on rank 0 after each step and its checkpoint, if any.
    Seeds torch, numpy and `random` of the calling process when ranks == 1.
    """
    job = _prepare(stage, run_cfg, data_dir, out_dir, resume, ranks)
    if job.world == 1:
        _run_rank(0, job, progress, on_step, None)
    else:
        with tempfile.TemporaryDirectory(prefix="scube-sim-rendezvous-") as tmp:
            try:
                mp.spawn(_run_rank, args=(job, progress, on_step, str(Path(tmp) / "init")), nprocs=job.world, join=True)
            except mp.ProcessRaisedException as exc:
                lines = [ln for ln in str(exc).splitlines() if ln.strip()]
                raise TrainingError(f"rank {exc.error_index} failed: {lines[-1] if lines else exc}") from None
            except mp.ProcessExitedException as exc:
                raise TrainingError(f"rank {exc.error_index} exited with code {exc.exit_code}") from None
    return _result(job)


def _prepare(stage, run_cfg: RunConfig, data_dir, out_dir, resume: bool, ranks: int | None) -> _Job:
    """Check everything a user can get wrong before any rank starts, so errors are one line."""
    stage = get_stage(stage) if isinstance(stage, str) else stage
    if normalize_name(run_cfg.stage) != normalize_name(stage.name):
        raise ConfigError(f"{run_cfg.source}: stage: the config is for {run_cfg.stage!r}, not {stage.name!r}")
    model_cfg, data_cfg = stage_configs(run_cfg, stage.model_config, stage.data_config)
    resolved = resolved_config(run_cfg, model_cfg, data_cfg)
    world = run_cfg.train.ranks if ranks is None else ranks
    if world < 1:
        raise InputError(f"ranks: expected at least 1, got {world}")
    resolved["train"]["ranks"] = world
    tc = run_cfg.train
    if tc.batch_size % world:
        raise ConfigError(f"{run_cfg.source}: train.batch_size: {tc.batch_size} does not split evenly "
                          f"over {world} ranks")

    data_dir, out_dir = Path(data_dir), Path(out_dir)
    if not data_dir.is_dir():
        raise InputError(f"{data_dir}: no such data folder")
    last = out_dir / LAST
    # Temporary files of a write that a kill interrupted: not part of the run.
    leftovers = set(out_dir.glob(".*.tmp-*")) if out_dir.is_dir() else set()
    ck = None
    if resume:
        if not last.is_file():
            raise InputError(f"{last}: no checkpoint to resume from")
        ck = load_checkpoint(last)
        _check_resumable(ck, stage, resolved, last)
    elif out_dir.exists() and (not out_dir.is_dir() or set(out_dir.iterdir()) - leftovers):
        raise InputError(f"{out_dir}: the run folder exists and is not empty (resume it, or choose a new folder)")

    train_ds, val_ds = stage.datasets(data_dir, data_cfg, tc.seed)
    n = len(train_ds)
    if n < tc.batch_size:
        raise InputError(f"{data_dir}: the train split has {n} samples, fewer than train.batch_size = {tc.batch_size}")
    if len(val_ds) == 0:
        raise InputError(f"{data_dir}: the val split has no samples")
    if ck is not None and ck["train_samples"] != n:
        raise InputError(f"{data_dir}: the train split has {n} samples; the run in {last} had {ck['train_samples']}")
    spe = n // tc.batch_size
    total = tc.steps if tc.steps is not None else tc.epochs * spe
    if ck is not None and ck["step"] > total:
        raise ConfigError(f"{run_cfg.source}: train: the run in {last} is at step {ck['step']}, "
                          f"past this config's {total} steps")

    out_dir.mkdir(parents=True, exist_ok=True)
    for stale in leftovers:
        stale.unlink()
    return _Job(stage, resolved, data_dir, out_dir, resume, world, spe, total, n, (train_ds, val_ds))


def _flatten(d: dict, prefix: str = "") -> dict:
    out = {}
    for k, v in d.items():
        if isinstance(v, dict):
            out.update(_flatten(v, f"{prefix}{k}."))
        else:
            out[f"{prefix}{k}"] = v
    return out


def _with_todays_defaults(config: dict, stage: Stage, path: Path) -> dict:
    """A checkpoint's stored config resolved again by today's classes: a setting added since the
    run began takes its default, which is what the run did, so it does not count as a change."""
    try:
        run = config_from_dict(config, f"{path} (config)")
        model_cfg, data_cfg = stage_configs(run, stage.model_config, stage.data_config)
    except ConfigError:  # a config today's classes refuse: compare it as stored, key by key
        return config
    out = resolved_config(run, model_cfg, data_cfg)
    out["train"]["ranks"] = config.get("train", {}).get("ranks", out["train"].get("ranks"))
    return out


def _check_resumable(ck: dict, stage: Stage, resolved: dict, path: Path) -> None:
    if normalize_name(str(ck.get("stage"))) != normalize_name(stage.name):
        raise CheckpointError(f"{path}: a checkpoint of stage {ck.get('stage')!r}, not {stage.name!r}")
    old, new = _flatten(_with_todays_defaults(ck["config"], stage, path)), _flatten(resolved)
    for key in sorted(set(old) | set(new)):
        if key not in RESUMABLE_KEYS and old.get(key) != new.get(key):
            raise ConfigError(f"{path}: the run was started with {key} = {old.get(key)!r}, this config has "
                              f"{new.get(key)!r}; a resumed run may change only {', '.join(RESUMABLE_KEYS)}")


def _run_rank(rank: int, job: _Job, progress: bool, on_step, init_file: str | None) -> None:
    """One rank's whole run (`mp.spawn` calls it with the rank first)."""
    tc = TrainConfig.model_validate(job.resolved["train"])
    with torch_settings(tc, job.world):
        if job.world > 1:
            dist.init_process_group("gloo", init_method=f"file://{init_file}", rank=rank, world_size=job.world)
        try:
            _Loop(rank, job, tc, progress and rank == 0, on_step).run()
            if job.world > 1:
                dist.barrier()  # rank 0 may still be writing its last outputs
        finally:
            if job.world > 1:
                dist.destroy_process_group()


class _Loop:
    """The training loop of one rank."""

    def __init__(self, rank: int, job: _Job, tc: TrainConfig, progress: bool, on_step):
        self.rank, self.job, self.tc, self.progress, self.on_step = rank, job, tc, progress, on_step
        self.stage, self.world = job.stage, job.world
        run = config_from_dict(job.resolved, str(job.out_dir / CONFIG))
        self.model_cfg, self.data_cfg = stage_configs(run, self.stage.model_config, self.stage.data_config)
        self.train_ds, self.val_ds = job.datasets or self.stage.datasets(job.data_dir, self.data_cfg, tc.seed)

        seed_everything(tc.seed)  # the same initial weights on every rank
        self.model = self.stage.build_model(self.model_cfg)
        self.params = [p for p in self.model.parameters() if p.requires_grad]
        self.opt = torch.optim.Adam(self.params, lr=tc.lr, betas=tc.betas, eps=tc.eps, weight_decay=tc.weight_decay)
        self.state = _State()
        if job.resume:
            self._load(load_checkpoint(job.out_dir / LAST))
        else:
            if tc.init is not None:
                self._init_from(tc.init)
            if self.world > 1:  # identical start even if build_model is not reproducible
                for t in self.model.state_dict().values():
                    dist.broadcast(t, 0)
            # Each rank's own stream for training-time randomness (dropout, noise).
            seed_everything(_derive_seed(tc.seed, rank))

    def _init_from(self, name_or_path: str) -> None:
        path, ck = stage_checkpoint(self.stage, name_or_path)
        # a model may name parameters a warm start need not hold (a head the checkpoint's model had not)
        optional = tuple(getattr(self.model, "init_optional_prefixes", ()))
        try:
            missing, unexpected = self.model.load_state_dict(ck["model"], strict=False)
            bad = [k for k in missing if not k.startswith(optional)] if optional else list(missing)
            if bad or unexpected:
                raise RuntimeError(f"missing {bad[:3]}, unexpected {list(unexpected)[:3]}")
        except (RuntimeError, KeyError) as exc:
            first = (str(exc).strip().splitlines() or [type(exc).__name__])[0]
            raise CheckpointError(f"train.init: {path} does not fit this run's model: {first}") from None

    def _load(self, ck: dict) -> None:
        try:
            self.model.load_state_dict(ck["model"])
            self.opt.load_state_dict(ck["optimizer"])
        except (RuntimeError, ValueError, KeyError) as exc:
            first = (str(exc).strip().splitlines() or [type(exc).__name__])[0]
            raise CheckpointError(f"{self.job.out_dir / LAST}: does not fit the model: {first}") from None
        s = self.state
        s.step, s.epoch, s.batch = ck["step"], ck["epoch"], ck["batch"]
        s.train_log = {k: v.tolist() for k, v in ck["history"]["train"].items()}
        s.records = list(ck["history"]["val"])
        s.best_value, s.best_step = ck["best"]["value"], ck["best"]["step"]
        set_rng_state(ck["rng"][self.rank])

    def run(self) -> None:
        s, job = self.state, self.job
        if not job.resume:
            self._save(False)  # step 0: from the first moment on, the run folder can be resumed
        if self.rank == 0:
            self._write_metrics()  # after a resume: drop records newer than the checkpoint
            with atomic_path(job.out_dir / CONFIG) as tmp:
                tmp.write_text(yaml.safe_dump(job.resolved, sort_keys=False), encoding="utf-8")
        with Progress(*bar_columns(), disable=not self.progress) as bar:
            task = bar.add_task(f"{self.stage.name}", total=job.total_steps, completed=s.step)
            while s.step < job.total_steps:
                sampler = ShardSampler(job.train_samples, self.tc.batch_size, self.tc.seed, s.epoch, s.batch,
                                       self.rank, self.world)
                # Its own generator: otherwise the DataLoader draws its worker seed from torch's global
                # generator, and a resumed run (which opens the loader at another moment) diverges.
                gen = torch.Generator().manual_seed(_derive_seed(self.tc.seed, s.epoch, self.rank))
                if self.stage.epoch_aware:
                    self.train_ds.set_epoch(s.epoch)
                loader = DataLoader(self.train_ds, batch_sampler=sampler, collate_fn=self.stage.collate,
                                    num_workers=self.tc.num_workers, generator=gen)
                for batch in loader:
                    logs = self._step(batch)
                    s.step += 1
                    s.batch += 1
                    self._log(logs)
                    epoch_done = s.batch == job.steps_per_epoch
                    if epoch_done:
                        s.epoch, s.batch = s.epoch + 1, 0
                    last = s.step == job.total_steps
                    new_best = False
                    if last or (epoch_done and s.epoch % self.tc.validate_every == 0):
                        new_best = self._validate()
                    if last or epoch_done or (self.tc.checkpoint_every and s.step % self.tc.checkpoint_every == 0):
                        self._save(new_best)
                    bar.update(task, completed=s.step,
                               description=f"{self.stage.name} epoch {s.epoch + (s.batch > 0)} loss {logs['loss']:.4g}")
                    if self.on_step is not None and self.rank == 0:
                        self.on_step(s.step, logs)
                    if last:
                        break
        if self.rank == 0:
            self._write_metrics()
            plot_loss_curve(s.train_log, s.records, self.stage.primary_metric, job.out_dir / CURVE)

    def _step(self, batch) -> dict[str, float]:
        """One optimiser step on this rank's shard; returns the logs averaged over the ranks."""
        self.model.train()
        self.opt.zero_grad(set_to_none=True)
        loss, extras = self.stage.loss(self.model, batch)
        if not isinstance(loss, torch.Tensor) or loss.ndim != 0:
            raise StageError(f"stage {self.stage.name!r}: loss must return a scalar tensor first")
        loss.backward()
        if self.world > 1:
            self._average_gradients()
        logs = self._mean_over_ranks({**extras, "loss": loss.detach()})
        if not math.isfinite(logs["loss"]):
            raise TrainingError(f"step {self.state.step + 1}: the loss is {logs['loss']}; the last good "
                                f"checkpoint is {self.job.out_dir / LAST}")
        if self.tc.grad_clip is not None:
            nn.utils.clip_grad_norm_(self.params, self.tc.grad_clip)
        lr = learning_rate(self.tc, self.state.step, self.job.total_steps)
        for group in self.opt.param_groups:
            group["lr"] = lr
        self.opt.step()
        if self.world > 1:  # e.g. batch-norm statistics: keep rank 0's everywhere, as DDP does
            for b in self.model.buffers():
                dist.broadcast(b, 0)
        return logs

    def _log(self, logs: dict[str, float]) -> None:
        log = self.state.train_log
        if log and set(log) != set(logs):
            raise StageError(f"stage {self.stage.name!r}: loss logged {', '.join(sorted(logs))} at step "
                             f"{self.state.step}, {', '.join(sorted(log))} before")
        for k, v in logs.items():
            log.setdefault(k, []).append(v)

    def _average_gradients(self) -> None:
        """All-reduce (mean) the gradients. A parameter without a gradient on every rank keeps none
        (Adam skips it, as in a one-rank run); one missing only somewhere counts as zero there."""
        has = torch.tensor([p.grad is not None for p in self.params], dtype=torch.int32)
        dist.all_reduce(has)
        for p, h in zip(self.params, has.tolist()):
            if h == 0:
                continue
            if p.grad is None:
                p.grad = torch.zeros_like(p)
            dist.all_reduce(p.grad)
            p.grad.div_(self.world)

    def _mean_over_ranks(self, logs: dict) -> dict[str, float]:
        keys = ["loss"] + sorted(k for k in logs if k != "loss")
        vals = torch.tensor([float(logs[k]) for k in keys], dtype=torch.float64)
        if self.world > 1:
            dist.all_reduce(vals)
            vals /= self.world
        return dict(zip(keys, vals.tolist()))

    def _validate(self) -> bool:
        """Evaluate on the val split (rank 0), append a record; True for a new best."""
        s = self.state
        if self.rank != 0:
            return False
        saved = rng_state()  # evaluation must not shift the training streams
        metrics = evaluate_model(self.stage, self.model, self.val_ds, self.tc.batch_size, self.tc.num_workers)
        set_rng_state(saved)
        since = s.records[-1]["step"] if s.records else 0
        means = {k: sum(v[since:]) / len(v[since:]) for k, v in s.train_log.items()} if s.step > since else {}
        s.records.append({"step": s.step, "epoch": s.step / self.job.steps_per_epoch, "train": means, "val": metrics})
        value = metrics[self.stage.primary_metric]
        better = not math.isnan(value) and (
            s.best_value is None or (value > s.best_value if self.stage.higher_is_better else value < s.best_value))
        if better:
            s.best_value, s.best_step = value, s.step
        return better

    def _save(self, new_best: bool) -> None:
        rngs = [rng_state()]
        if self.world > 1:
            rngs = [None] * self.world
            dist.all_gather_object(rngs, rng_state())
        if self.rank != 0:
            return
        s = self.state
        ck = {"stage": self.stage.name, "config": self.job.resolved, "world_size": self.world,
              "train_samples": self.job.train_samples, "steps_per_epoch": self.job.steps_per_epoch,
              "model": self.model.state_dict(), "optimizer": self.opt.state_dict(),
              "step": s.step, "epoch": s.epoch, "batch": s.batch, "rng": rngs,
              # Per-step values as float64 tensors: exact for Python floats, and fast to pickle.
              "history": {"train": {k: torch.tensor(v, dtype=torch.float64) for k, v in s.train_log.items()},
                          "val": s.records},
              "best": {"metric": self.stage.primary_metric, "higher_is_better": self.stage.higher_is_better,
                       "value": s.best_value, "step": s.best_step}}
        # best.pt first: a kill between the two leaves last.pt behind, and the replay rewrites best.pt.
        if new_best and self.tc.keep_best:
            save_checkpoint(self.job.out_dir / BEST, ck)
        save_checkpoint(self.job.out_dir / LAST, ck)
        self._write_metrics()

    def _write_metrics(self) -> None:
        with atomic_path(self.job.out_dir / METRICS) as tmp:
            tmp.write_text("".join(json.dumps(r) + "\n" for r in self.state.records), encoding="utf-8")


def _result(job: _Job) -> TrainResult:
    ck = load_checkpoint(job.out_dir / LAST)
    run = config_from_dict(ck["config"], str(job.out_dir / LAST))
    model = model_from_checkpoint(job.stage, run, ck, job.out_dir / LAST)
    best = job.out_dir / BEST
    records = ck["history"]["val"]
    return TrainResult(run_dir=job.out_dir, last=job.out_dir / LAST, best=best if best.is_file() else None,
                       step=ck["step"], epoch=ck["epoch"], metrics=records[-1]["val"] if records else {},
                       best_metric=ck["best"]["value"], best_step=ck["best"]["step"], model=model)


def plot_loss_curve(train_log: dict[str, list[float]], records: list[dict], metric: str, path: str | Path) -> Path:
    """PNG: training loss per step (train_log["loss"][i] is step i + 1's; left, log scale when
    positive) and the validation `metric` of each record (right)."""
    from matplotlib.figure import Figure  # no pyplot: no global figure state, no GUI backend

    fig = Figure(figsize=(9, 3.5), dpi=100)
    ax_loss, ax_val = fig.subplots(1, 2)
    loss = train_log.get("loss", [])
    steps = range(1, len(loss) + 1)
    ax_loss.plot(steps, loss, lw=1)
    if loss and min(loss) > 0:
        ax_loss.set_yscale("log")
    ax_loss.set(xlabel="step", ylabel="training loss", title="training loss")
    ax_val.plot([r["step"] for r in records], [r["val"][metric] for r in records], marker="o")
    ax_val.set(xlabel="step", ylabel=metric, title=f"validation {metric}")
    for ax in (ax_loss, ax_val):
        ax.grid(alpha=0.3)
    fig.subplots_adjust(left=0.08, right=0.98, bottom=0.14, top=0.9, wspace=0.3)  # tight_layout draws twice
    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    return path
