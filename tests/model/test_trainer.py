"""The trainer on a toy stage (linear regression with dropout): it reaches the least-squares
optimum, is deterministic in its seed, writes metrics.jsonl and loss.png, and a run killed by
SIGKILL (between steps, or in the middle of a checkpoint write) resumes to the same weights, bit
for bit, as an uninterrupted run.

The toy stage lives here; the other model tests import it from this module.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest
import torch
import yaml
from pydantic import Field
from torch import nn
from torch.utils.data import Dataset

from scube_sim.config import ConfigError, StrictModel
from scube_sim.errors import NotFoundError
from scube_sim.model.checkpoint import load_checkpoint, save_checkpoint, seed_everything
from scube_sim.model.config import load_config
from scube_sim.model.stages import Stage, StageError, get_stage, register_stage, stage_names
from scube_sim.model.trainer import TrainingError, train

REPO = Path(__file__).resolve().parents[2]
SPLIT_SEEDS = {"train": 0, "val": 1, "test": 2}


class ToyModelConfig(StrictModel):
    in_dim: int = Field(default=3, ge=1)
    dropout: float = Field(default=0.0, ge=0, lt=1)


class ToyDataConfig(StrictModel):
    samples: int = Field(default=32, ge=1)  # per split
    noise: float = Field(default=0.01, ge=0)


def true_weights(in_dim: int) -> tuple[torch.Tensor, float]:
    """(in_dim,) weights and the bias of the line the toy data follows."""
    return torch.tensor([(-1) ** i * 0.5 * (i + 1) for i in range(in_dim)]), 0.3


class ToyDataset(Dataset):
    """x ~ N(0, I) (n, in_dim), y = x . w + b + noise (n, 1); a function of the split only."""

    def __init__(self, n: int, in_dim: int, noise: float, split_seed: int):
        g = torch.Generator().manual_seed(split_seed)
        w, b = true_weights(in_dim)
        self.x = torch.randn(n, in_dim, generator=g)
        self.y = (self.x @ w + b + noise * torch.randn(n, generator=g))[:, None]

    def __len__(self) -> int:
        return len(self.x)

    def __getitem__(self, i):
        return self.x[i], self.y[i]


class ToyStage(Stage):
    """Linear regression; dropout on the input makes training draw from torch's generator."""

    name = "toy"
    model_config = ToyModelConfig
    data_config = ToyDataConfig
    primary_metric = "mse"
    higher_is_better = False

    def build_model(self, model_cfg):
        return nn.Sequential(nn.Dropout(model_cfg.dropout), nn.Linear(model_cfg.in_dim, 1))

    def dataset(self, data_dir, data_cfg, split, seed):
        return ToyDataset(data_cfg.samples, 3, data_cfg.noise, SPLIT_SEEDS[split])

    def loss(self, model, batch):
        x, y = batch
        err = model(x) - y
        return (err ** 2).mean(), {"mae": float(err.detach().abs().mean())}

    def evaluate(self, model, batches):
        sq, n = 0.0, 0
        for x, y in batches:
            sq += float(((model(x) - y) ** 2).sum())
            n += len(x)
        # Draws from the global generator, like a stage that evaluates on random ray subsets:
        # the trainer must not let this shift the training stream.
        return {"mse": sq / n, "probe": float(torch.rand(()))}


TOY = register_stage(ToyStage())


def write_config(path: Path, model: dict | None = None, data: dict | None = None, **train) -> Path:
    """A toy run config: 32 samples in batches of 8 (4 steps an epoch), one thread."""
    cfg = {"stage": "toy",
           "train": {"seed": 0, "epochs": 3, "batch_size": 8, "lr": 0.05, "threads": 1, **train},
           "model": {"in_dim": 3, **(model or {})}, "data": {**(data or {})}}
    path.write_text(yaml.safe_dump(cfg), encoding="utf-8")
    return path


def weights(run_dir: Path) -> dict[str, torch.Tensor]:
    return load_checkpoint(run_dir / "last.pt")["model"]


def assert_same_weights(a: dict, b: dict) -> None:
    assert a.keys() == b.keys()
    for k, v in a.items():
        assert torch.equal(v, b[k]), k


@pytest.fixture
def data_dir(tmp_path) -> Path:
    d = tmp_path / "data"
    d.mkdir()
    return d


def test_stages_are_found_by_normalised_name_and_names_are_not_taken_twice():
    assert get_stage("TOY") is TOY and "toy" in stage_names()
    assert register_stage(ToyStage()) is get_stage("toy")  # the same class again (a re-import) replaces it
    register_stage(TOY)

    class Impostor(ToyStage):
        pass

    with pytest.raises(StageError, match=r"stage 'toy' is already registered by tests\.model\.test_trainer\.ToyStage"):
        register_stage(Impostor())
    with pytest.raises(NotFoundError, match=r"unknown stage 'nosuch'; known stages: .*toy"):
        get_stage("nosuch")
    with pytest.raises(TypeError, match="expected a Stage instance"):
        register_stage(object())


def test_trainer_reaches_the_least_squares_optimum_and_writes_its_outputs(tmp_path, data_dir):
    cfg = load_config(write_config(tmp_path / "run.yaml", epochs=30))
    res = train(TOY, cfg, data_dir, tmp_path / "run", progress=False)

    ds = TOY.dataset(data_dir, ToyDataConfig(), "train", 0)
    a = torch.cat([ds.x, torch.ones(len(ds), 1)], dim=1)
    optimum = torch.linalg.lstsq(a, ds.y).solution.ravel()  # (w_0, w_1, w_2, b)
    lin = res.model[1]
    got = torch.cat([lin.weight.detach().ravel(), lin.bias.detach()])
    assert torch.allclose(got, optimum, atol=0.02), (got, optimum)
    assert res.step == 120 and res.epoch == 30

    lines = (tmp_path / "run" / "metrics.jsonl").read_text().splitlines()
    records = [json.loads(ln) for ln in lines]
    assert [r["step"] for r in records] == [4 * (i + 1) for i in range(30)]
    assert [r["epoch"] for r in records] == [float(i + 1) for i in range(30)]
    assert set(records[0]["train"]) == {"loss", "mae"} and set(records[0]["val"]) == {"mse", "probe"}
    assert records[-1]["val"]["mse"] < 0.01 * records[0]["val"]["mse"]
    # The first record's training loss is the mean of the first epoch's four step losses.
    loss = load_checkpoint(res.last)["history"]["train"]["loss"]
    assert loss.shape == (120,) and loss.dtype == torch.float64
    assert records[0]["train"]["loss"] == pytest.approx(float(loss[:4].mean()), rel=1e-12)

    best = min(records, key=lambda r: r["val"]["mse"])
    assert (res.best_step, res.best_metric) == (best["step"], best["val"]["mse"])
    assert load_checkpoint(res.best)["step"] == best["step"]

    png = (tmp_path / "run" / "loss.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n"
    from PIL import Image

    with Image.open(tmp_path / "run" / "loss.png") as im:
        im.verify()
    assert yaml.safe_load((tmp_path / "run" / "config.yaml").read_text())["train"]["betas"] == [0.9, 0.999]


def test_same_seed_gives_the_same_weights_however_often_it_validates_and_another_seed_others(tmp_path, data_dir):
    """Dropout draws from torch's generator in training, the toy's evaluation draws too: the
    weights depend on the seed only, not on how often validation runs."""
    runs = {}
    for name, seed, every in [("a", 0, 1), ("b", 0, 3), ("c", 1, 1)]:
        cfg = load_config(write_config(tmp_path / f"{name}.yaml", model={"dropout": 0.3}, seed=seed,
                                       validate_every=every))
        train(TOY, cfg, data_dir, tmp_path / name, progress=False)
        runs[name] = weights(tmp_path / name)
    assert_same_weights(runs["a"], runs["b"])
    assert len((tmp_path / "b" / "metrics.jsonl").read_text().splitlines()) == 1  # the last step only
    assert not torch.equal(runs["a"]["1.weight"], runs["c"]["1.weight"])


def test_resume_may_extend_the_run_but_not_change_it(tmp_path, data_dir):
    short = load_config(write_config(tmp_path / "short.yaml", model={"dropout": 0.2}, epochs=1))
    long = load_config(write_config(tmp_path / "long.yaml", model={"dropout": 0.2}, epochs=2))
    train(TOY, short, data_dir, tmp_path / "run", progress=False)
    # The extension loads with a worker process: the batches, hence the weights, are the same.
    more = load_config(write_config(tmp_path / "more.yaml", model={"dropout": 0.2}, epochs=2, num_workers=1))
    res = train(TOY, more, data_dir, tmp_path / "run", resume=True, progress=False)
    train(TOY, long, data_dir, tmp_path / "ref", progress=False)
    assert res.step == 8
    assert_same_weights(weights(tmp_path / "run"), weights(tmp_path / "ref"))
    assert (tmp_path / "run" / "metrics.jsonl").read_text() == (tmp_path / "ref" / "metrics.jsonl").read_text()

    other = load_config(write_config(tmp_path / "other.yaml", model={"dropout": 0.2}, epochs=2, lr=0.01))
    with pytest.raises(ConfigError, match=r"last\.pt: the run was started with train\.lr = 0\.05"):
        train(TOY, other, data_dir, tmp_path / "run", resume=True, progress=False)


def test_a_run_may_start_from_another_runs_weights(tmp_path, data_dir):
    """train.init: the weights of a checkpoint at step 0 with a fresh optimiser (a fine-tune);
    another stage's checkpoint or a missing file is named."""
    from scube_sim.model.checkpoint import CheckpointError

    first = train(TOY, load_config(write_config(tmp_path / "a.yaml", epochs=1)), data_dir, tmp_path / "a",
                  progress=False)
    # At a learning rate too small to move a float32 weight, the fine-tune keeps the init exactly.
    still = load_config(write_config(tmp_path / "b.yaml", epochs=1, lr=1e-30, init=str(first.last)))
    res = train(TOY, still, data_dir, tmp_path / "b", progress=False)
    assert res.step == 4
    assert_same_weights(weights(tmp_path / "b"), weights(tmp_path / "a"))
    assert yaml.safe_load((tmp_path / "b" / "config.yaml").read_text())["train"]["init"] == str(first.last)
    fresh = train(TOY, load_config(write_config(tmp_path / "c.yaml", epochs=1, lr=1e-30)), data_dir, tmp_path / "c",
                  progress=False)
    assert not torch.equal(weights(tmp_path / "c")["1.weight"], weights(tmp_path / "a")["1.weight"])
    del fresh
    ck = load_checkpoint(first.last)
    ck["stage"] = "geometry-vae"
    save_checkpoint(tmp_path / "other.pt", {k: v for k, v in ck.items() if k not in ("format", "version")})
    for bad, match in ((tmp_path / "other.pt", "stage 'geometry-vae', not 'toy'"),
                       (tmp_path / "none.pt", "none.pt: no such checkpoint file")):
        cfg = load_config(write_config(tmp_path / "d.yaml", epochs=1, init=str(bad)))
        with pytest.raises(CheckpointError, match=match):
            train(TOY, cfg, data_dir, tmp_path / f"d-{bad.stem}", progress=False)


def test_a_run_from_before_a_setting_existed_resumes_at_its_default(tmp_path, data_dir):
    """A checkpoint whose stored config lacks a setting added since (here: dropout, at its
    default) is the same run as today's config with that default; another value is a change."""
    short = load_config(write_config(tmp_path / "short.yaml", epochs=1))
    res = train(TOY, short, data_dir, tmp_path / "run", progress=False)
    ck = load_checkpoint(res.last)
    default = ck["config"]["model"].pop("dropout")
    save_checkpoint(res.last, {k: v for k, v in ck.items() if k not in ("format", "version")})
    more = load_config(write_config(tmp_path / "more.yaml", epochs=2))
    assert train(TOY, more, data_dir, tmp_path / "run", resume=True, progress=False).step == 8
    ck = load_checkpoint(res.last)
    ck["config"]["model"].pop("dropout")
    save_checkpoint(res.last, {k: v for k, v in ck.items() if k not in ("format", "version")})
    other = load_config(write_config(tmp_path / "other.yaml", model={"dropout": default + 0.25}, epochs=3))
    with pytest.raises(ConfigError, match=r"model\.dropout"):
        train(TOY, other, data_dir, tmp_path / "run", resume=True, progress=False)


def test_a_run_of_steps_ends_mid_epoch_with_a_validation_and_clipping_acts(tmp_path, data_dir):
    cfg = load_config(write_config(tmp_path / "run.yaml", epochs=None, steps=6))
    res = train(TOY, cfg, data_dir, tmp_path / "run", progress=False)
    records = [json.loads(ln) for ln in (tmp_path / "run" / "metrics.jsonl").read_text().splitlines()]
    assert [(r["step"], r["epoch"]) for r in records] == [(4, 1.0), (6, 1.5)]
    ck = load_checkpoint(res.last)
    assert (ck["step"], ck["epoch"], ck["batch"]) == (6, 1, 2) and res.epoch == 1

    # Stopped after step 1, before any periodic checkpoint: the step-0 checkpoint resumes it.
    class Stop(Exception):
        pass

    def stop(step, logs):
        assert load_checkpoint(tmp_path / "early" / "last.pt")["step"] == 0
        raise Stop

    with pytest.raises(Stop):
        train(TOY, cfg, data_dir, tmp_path / "early", progress=False, on_step=stop)
    train(TOY, cfg, data_dir, tmp_path / "early", resume=True, progress=False)
    assert_same_weights(weights(tmp_path / "early"), weights(tmp_path / "run"))
    # A gradient norm clipped far below Adam's eps (1e-8) shrinks every update about tenfold.
    clipped = load_config(write_config(tmp_path / "clip.yaml", epochs=None, steps=6, grad_clip=1e-9))
    train(TOY, clipped, data_dir, tmp_path / "clip", progress=False)
    seed_everything(0)  # as train does before building the model
    start = TOY.build_model(ToyModelConfig()).state_dict()
    moved = {name: (weights(tmp_path / d)["1.weight"] - start["1.weight"]).abs().max() for name, d in
             [("plain", "run"), ("clipped", "clip")]}
    assert moved["clipped"] < 0.2 * moved["plain"]


class NanAfterTwoSteps(ToyStage):
    def __init__(self):
        self.calls = 0

    def loss(self, model, batch):
        loss, extras = super().loss(model, batch)
        self.calls += 1
        return (loss * float("nan") if self.calls > 2 else loss), extras


def test_a_non_finite_loss_stops_the_run_at_the_last_good_checkpoint(tmp_path, data_dir):
    cfg = load_config(write_config(tmp_path / "run.yaml", checkpoint_every=1))
    # What a kill in the first checkpoint's write leaves: the folder still counts as empty.
    (tmp_path / "run").mkdir()
    (tmp_path / "run" / ".last.pt.tmp-12345").write_bytes(b"PK")
    with pytest.raises(TrainingError, match=r"step 3: the loss is nan; the last good checkpoint is .*last\.pt"):
        train(NanAfterTwoSteps(), cfg, data_dir, tmp_path / "run", progress=False)
    ck = load_checkpoint(tmp_path / "run" / "last.pt")
    assert ck["step"] == 2 and all(torch.isfinite(t).all() for t in ck["model"].values())
    assert not (tmp_path / "run" / ".last.pt.tmp-12345").exists()


# --- killed and resumed ------------------------------------------------------------------------

# Runs a toy training in a fresh interpreter and SIGKILLs it: after step K ("step"), or in the
# middle of writing the checkpoint of step K ("write": half the file is on disk, not yet renamed).
KILL_SCRIPT = r"""
import os, signal, sys
import torch
torch.set_num_threads(1)
from tests.model.test_trainer import TOY
from scube_sim.model.config import load_config
from scube_sim.model import checkpoint, trainer

cfg_path, data_dir, run_dir, mode, kill_at, resume = sys.argv[1:7]
kill_at = int(kill_at)

def die():
    os.kill(os.getpid(), signal.SIGKILL)

def on_step(step, logs):
    if mode == "step" and step == kill_at:
        die()

real_save = torch.save
def half_save(obj, f, *args, **kwargs):
    real_save(obj, f, *args, **kwargs)
    if mode == "write" and isinstance(obj, dict) and obj.get("step") == kill_at:
        size = os.path.getsize(f)
        with open(f, "r+b") as fh:
            fh.truncate(size // 2)
        die()
checkpoint.torch.save = half_save

trainer.train(TOY, load_config(cfg_path), data_dir, run_dir, resume=resume == "1", progress=False, on_step=on_step)
"""


def _killed_run(cfg: Path, data_dir: Path, run_dir: Path, mode: str, kill_at: int, resume: bool) -> None:
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(REPO)}
    args = [str(cfg), str(data_dir), str(run_dir), mode, str(kill_at), "1" if resume else "0"]
    proc = subprocess.run([sys.executable, "-c", KILL_SCRIPT, *args], check=False, cwd=REPO, env=env,
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == -signal.SIGKILL, proc.stderr


def test_a_run_killed_at_any_moment_resumes_to_the_same_weights_bit_for_bit(tmp_path, data_dir):
    # 4 steps an epoch, 3 epochs; checkpoints at steps 3, 4 (epoch end), 6, 8 (epoch end), 9, 12.
    cfg = write_config(tmp_path / "run.yaml", model={"dropout": 0.3}, checkpoint_every=3)
    ref = train(TOY, load_config(cfg), data_dir, tmp_path / "ref", progress=False)

    run = tmp_path / "run"
    _killed_run(cfg, data_dir, run, "step", 7, resume=False)  # mid-epoch, one step after a checkpoint
    assert load_checkpoint(run / "last.pt")["step"] == 6
    _killed_run(cfg, data_dir, run, "write", 9, resume=True)  # while writing step 9's last.pt
    assert load_checkpoint(run / "last.pt")["step"] == 8
    assert list(run.glob(".last.pt.tmp-*")), "the interrupted write should have left its temporary file"

    res = train(TOY, load_config(cfg), data_dir, run, resume=True, progress=False)
    assert res.step == ref.step == 12
    assert not list(run.glob(".*.tmp-*"))
    a, b = load_checkpoint(run / "last.pt"), load_checkpoint(tmp_path / "ref" / "last.pt")
    assert_same_weights(a["model"], b["model"])
    for pa, pb in zip(a["optimizer"]["state"].values(), b["optimizer"]["state"].values()):
        assert_same_weights(pa, pb)
    assert a["history"]["val"] == b["history"]["val"]
    assert_same_weights(a["history"]["train"], b["history"]["train"])
    assert (run / "metrics.jsonl").read_text() == (tmp_path / "ref" / "metrics.jsonl").read_text()
    assert_same_weights(load_checkpoint(run / "best.pt")["model"], load_checkpoint(ref.best)["model"])


def test_the_cosine_schedule_warms_up_linearly_and_ends_at_its_final_ratio():
    from scube_sim.model.config import TrainConfig
    from scube_sim.model.trainer import learning_rate

    tc = TrainConfig(steps=11, lr=1.0, lr_schedule="cosine", warmup_steps=2, lr_final_ratio=0.1)
    got = [learning_rate(tc, k, 11) for k in range(11)]
    assert got[:2] == pytest.approx([0.5, 1.0])  # warm-up: (k + 1) / 2
    assert got[2] == pytest.approx(1.0)  # the decay starts at the full rate ...
    assert got[-1] == pytest.approx(0.1)  # ... and ends at lr * lr_final_ratio
    assert got[2 + 4] == pytest.approx(0.55)  # half-way down the cosine: the mean of the two
    assert all(a >= b for a, b in zip(got[1:], got[2:]))
    constant = TrainConfig(steps=11, lr=0.3)
    assert {learning_rate(constant, k, 11) for k in range(11)} == {0.3}


def test_a_scheduled_run_takes_the_scheduled_steps_and_resumes_bit_for_bit(tmp_path, data_dir):
    """With a gradient clipped far below Adam's eps every Adam update is about lr * sign(grad):
    the first update of a 4-step warm-up moves the weights a quarter as far as a constant run's."""
    sched = dict(epochs=None, steps=6, lr_schedule="cosine", warmup_steps=1, lr_final_ratio=0.0)
    moved = {}
    seed_everything(0)
    start = TOY.build_model(ToyModelConfig()).state_dict()["1.weight"]
    for name, extra in [("const", {}), ("warm", {"lr_schedule": "cosine", "warmup_steps": 4})]:
        cfg = load_config(write_config(tmp_path / f"{name}.yaml", epochs=None, steps=1, grad_clip=1e-12, **extra))
        train(TOY, cfg, data_dir, tmp_path / name, progress=False)
        moved[name] = (weights(tmp_path / name)["1.weight"] - start).abs()
    assert torch.allclose(moved["warm"], 0.25 * moved["const"], rtol=1e-3)

    full = load_config(write_config(tmp_path / "full.yaml", **sched))
    train(TOY, full, data_dir, tmp_path / "full", progress=False)
    half = load_config(write_config(tmp_path / "half.yaml", **{**sched, "steps": 3}))
    train(TOY, half, data_dir, tmp_path / "split", progress=False)
    # Stopped at step 3 of a 3-step run then extended to 6: the rest of the curve is the 6-step one,
    # but the first 3 steps followed a 3-step curve, so the weights differ from `full` ...
    train(TOY, full, data_dir, tmp_path / "split", resume=True, progress=False)
    assert not torch.equal(weights(tmp_path / "split")["1.weight"], weights(tmp_path / "full")["1.weight"])
    # ... while a run interrupted and resumed with the same length reaches the same weights.
    class Stop(Exception):
        pass

    def stop(step, logs):
        if step == 3:
            raise Stop

    with pytest.raises(Stop):
        train(TOY, full, data_dir, tmp_path / "cut", progress=False, on_step=stop)
    train(TOY, full, data_dir, tmp_path / "cut", resume=True, progress=False)
    assert_same_weights(weights(tmp_path / "cut"), weights(tmp_path / "full"))
