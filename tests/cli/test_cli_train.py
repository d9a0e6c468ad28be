"""`scube-sim train` and `scube-sim eval` on the toy stage, and their one-line errors."""

from __future__ import annotations

import json

import pytest
import yaml
from typer.testing import CliRunner

from scube_sim.cli import app
from scube_sim.model.checkpoint import load_checkpoint
from scube_sim.model.evaluate import evaluate
from tests.conftest import one_line_error
from tests.model.test_trainer import TOY, write_config

runner = CliRunner()


def run(*args):
    return runner.invoke(app, [str(a) for a in args])


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """A finished toy run: (data folder, config path, run folder, the train command's result)."""
    tmp = tmp_path_factory.mktemp("cli-train")
    data = tmp / "data"
    data.mkdir()
    cfg = write_config(tmp / "toy.yaml", epochs=2)
    res = run("train", "toy", "--data", data, "--config", cfg, "-o", tmp / "run", "--no-progress")
    return data, cfg, tmp / "run", res


def test_train_writes_a_run_folder_and_eval_reports_its_metrics(trained, tmp_path):
    data, _, run_dir, res = trained
    assert res.exit_code == 0, res.output
    assert f"-> {run_dir / 'last.pt'}" in res.output and "step 8, epoch 2" in res.output
    assert {p.name for p in run_dir.iterdir()} >= {"last.pt", "best.pt", "metrics.jsonl", "loss.png", "config.yaml"}

    out = tmp_path / "m" / "metrics.json"
    res = run("eval", "stage", "toy", "--data", data, "--checkpoint", run_dir / "last.pt", "--split", "test", "-o", out)
    assert res.exit_code == 0, res.output
    report = json.loads(out.read_text())
    assert report["split"] == "test" and report["stage"] == "toy"
    assert report["metrics"]["mse"] == evaluate(TOY, run_dir / "last.pt", data, split="test")["mse"]
    assert "(primary, lower is better)" in res.output
    # The test split is another sample of the line than the val split.
    assert report["metrics"]["mse"] != load_checkpoint(run_dir / "last.pt")["history"]["val"][-1]["val"]["mse"]


def test_resume_without_config_continues_with_the_runs_own(trained):
    data, _, run_dir, _ = trained
    res = run("train", "toy", "--data", data, "-o", run_dir, "--resume", "--no-progress")
    assert res.exit_code == 0, res.output
    assert "step 8, epoch 2" in res.output


def test_train_errors_are_one_line(trained, tmp_path):
    data, cfg, run_dir, _ = trained
    one_line_error(run("train", "nosuch", "--data", data, "--config", cfg, "-o", tmp_path / "r"),
                   "unknown stage 'nosuch'; known stages:", "toy")
    one_line_error(run("train", "toy", "--data", tmp_path / "absent", "--config", cfg, "-o", tmp_path / "r"),
                   "absent: no such data folder")
    bad = tmp_path / "bad.yaml"
    bad.write_text(yaml.safe_dump({"stage": "toy", "train": {"epochs": 1, "lrate": 0.1}}))
    one_line_error(run("train", "toy", "--data", data, "--config", bad, "-o", tmp_path / "r"),
                   "bad.yaml: train.lrate: unknown key")
    one_line_error(run("train", "toy", "--data", data, "--config", "no-such-config", "-o", tmp_path / "r"),
                   "unknown training config 'no-such-config'")
    one_line_error(run("train", "toy", "--data", data, "--config", cfg, "-o", run_dir),
                   "the run folder exists and is not empty")
    one_line_error(run("train", "toy", "--data", data, "--config", cfg, "-o", tmp_path / "empty", "--resume"),
                   "last.pt: no checkpoint to resume from")
    one_line_error(run("train", "toy", "--data", data, "-o", tmp_path / "new"), "--config: required for a new run")
    one_line_error(run("train", "toy", "--data", data, "--config", cfg, "-o", tmp_path / "r", "--ranks", "3"),
                   "train.batch_size: 8 does not split evenly over 3 ranks")
    assert not (tmp_path / "r").exists()


def test_eval_errors_are_one_line(trained, tmp_path):
    data, _, run_dir, _ = trained
    one_line_error(run("eval", "stage", "toy", "--data", data, "--checkpoint", tmp_path / "none.pt"),
                   "none.pt: no such checkpoint file")
    junk = tmp_path / "junk.pt"
    junk.write_bytes(b"not a checkpoint")
    one_line_error(run("eval", "stage", "toy", "--data", data, "--checkpoint", junk), "junk.pt: not a loadable checkpoint")
    one_line_error(run("eval", "stage", "toy", "--data", data, "--checkpoint", run_dir / "last.pt", "--split", "dev"),
                   "split: 'dev' is not a split of stage 'toy' (train, val, test)")
    one_line_error(run("eval", "stage", "toy", "--data", tmp_path / "absent", "--checkpoint", run_dir / "last.pt"),
                   "absent: no such data folder")
