"""The voxel-semantics stage end to end on a tiny worlds dataset: data -> sparse U-Net -> trainer
-> checkpoint -> `scube-sim eval`; its metrics against a hand-made confusion matrix."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
import yaml
from typer.testing import CliRunner

from scube_sim.cli import app
from scube_sim.datasets import open_dataset
from scube_sim.labels import LABEL_NAMES, NUM_LABELS, label_id
from scube_sim.model.config import load_config
from scube_sim.model.evaluate import evaluate
from scube_sim.model.nn.label_metrics import semantic_metrics
from scube_sim.model.semantics.data import collate_grids
from scube_sim.model.stages import get_stage
from scube_sim.model.trainer import train
from scube_sim.worlds.dataset import DatasetConfig, generate_dataset

TINY = DatasetConfig(image_scale=0.04, visibility_scale=0.04, fine_voxel_m=0.4, coarse_factor=2, frame_offsets=[0],
                     lidar="vlp16", styles=["suburban"])


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    out = tmp_path_factory.mktemp("voxsem")
    for split in ("train", "val", "test"):
        generate_dataset(out, split, 1 if split != "train" else 2, TINY, progress=False)
    return out


def write_run(path, steps=6):
    path.write_text(yaml.safe_dump({
        "stage": "voxel-semantics",
        "train": {"seed": 0, "steps": steps, "batch_size": 2, "lr": 3e-3, "threads": 1},
        "model": {"widths": [8, 16], "blocks": 1, "norm": "group"},
        "data": {"level": "coarse", "region": [-10.24, -25.6, -3.23, 30.0, 25.6, 20.0]},
    }))
    return path


def test_metrics_from_a_confusion_matrix():
    road, car = label_id("road"), label_id("car")
    conf = torch.zeros(NUM_LABELS, NUM_LABELS, dtype=torch.int64)
    conf[road, road], conf[road, car], conf[car, car], conf[car, road] = 6, 2, 3, 1
    m = semantic_metrics(conf)
    # IoU(road) = 6 / (6 + 2 + 1), IoU(car) = 3 / (3 + 1 + 2); only the two labels that occur count
    assert m["iou_road"] == pytest.approx(6 / 9) and m["iou_car"] == pytest.approx(3 / 6)
    assert m["miou"] == pytest.approx((6 / 9 + 3 / 6) / 2) and m["accuracy"] == pytest.approx(9 / 12)
    assert sum(k.startswith("iou_") for k in m) == 2


def test_items_hold_the_ground_truth_grid_of_the_region(data):
    stage = get_stage("voxel-semantics")
    cfg = stage.data_config(level="coarse", region=(-10.24, -25.6, -3.23, 30.0, 25.6, 20.0))
    item = stage.dataset(data, cfg, "train", 0)[0]
    gt = open_dataset("worlds", data, split="train")[0].ground_truth.coarse
    centres = gt.centers()
    inside = np.all((centres >= [-10.24, -25.6, -3.23]) & (centres < [30.0, 25.6, 20.0]), axis=1)
    assert 0 < len(item["ijk"]) == int(inside.sum()) < len(gt)
    np.testing.assert_array_equal(item["ijk"].numpy(), gt.ijk[inside])
    np.testing.assert_array_equal(item["labels"].numpy(), gt.labels[inside])
    np.testing.assert_allclose(item["z"].numpy(), centres[inside, 2], rtol=1e-6)
    batch = collate_grids([item, item])
    assert batch["coords"].shape == (2 * len(item["ijk"]), 4) and batch["batch_size"] == 2
    # sorted in grid order, and each site keeps its own label
    first = batch["coords"][:, 0] == 0
    key = {tuple(c): int(lab) for c, lab in zip(item["ijk"].tolist(), item["labels"])}
    assert all(key[tuple(c)] == int(lab) for c, lab in zip(batch["coords"][first, 1:].tolist(),
                                                             batch["labels"][first]))


def test_training_lowers_the_loss_and_eval_reads_the_checkpoint(data, tmp_path):
    run = load_config(write_run(tmp_path / "run.yaml", steps=8))
    res = train("voxel-semantics", run, data, tmp_path / "run", progress=False)
    hist = [json.loads(line) for line in (tmp_path / "run" / "metrics.jsonl").read_text().splitlines()]
    assert hist and 0.0 <= hist[-1]["val"]["miou"] <= 1.0
    losses = torch.load(res.last, weights_only=True, map_location="cpu")["history"]["train"]["loss"].tolist()
    assert len(losses) == 8 and np.mean(losses[-2:]) < losses[0]
    # the CLI's eval on the held-out split gives the library's numbers
    out = tmp_path / "m.json"
    r = CliRunner().invoke(app, ["eval", "stage", "voxel-semantics", "--data", str(data), "--checkpoint", str(res.last),
                                 "--split", "test", "-o", str(out)])
    assert r.exit_code == 0, r.output
    got = json.loads(out.read_text())["metrics"]
    want = evaluate("voxel-semantics", res.last, data, split="test")
    assert got == pytest.approx(want) and 0.0 <= got["miou"] <= 1.0
    assert {k for k in got if k.startswith("iou_")} <= {f"iou_{n}" for n in LABEL_NAMES}
