"""The geometry stages on a tiny worlds dataset: the structure VAE reconstructs a grid it overfits,
the conditional latent model's loss falls 10x with t and noise fixed, the trainer and `eval` run
both stages, and bad inputs give one clear error."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch
import yaml
from typer.testing import CliRunner

from scube_sim.cli import app
from scube_sim.errors import InputError
from scube_sim.labels import label_id
from scube_sim.model.config import config_from_dict
from scube_sim.model.geometry.data import GeometryDataConfig
from scube_sim.model.geometry.dense_nets import VAEConfig, prune_decode
from scube_sim.model.geometry.net import GeometryModelConfig, GeometryNet
from scube_sim.model.geometry.stage import grid_metrics
from scube_sim.model.nn.lifting import LiftGrid, grid_in_box
from scube_sim.model.stages import get_stage
from scube_sim.model.trainer import train
from scube_sim.worlds.dataset import DatasetConfig, generate_dataset

TINY = DatasetConfig(image_scale=0.04, visibility_scale=0.04, fine_voxel_m=0.4, coarse_factor=2, frame_offsets=[0],
                     lidar="vlp16", styles=["suburban"])
# 3.2 m voxels over the default 102.4 x 102.4 x 25.6 m box: 32 x 32 x 8
DATA = {"voxel_size": 3.2, "image_scale": 1.0}
VAE = {"widths": [16], "blocks": 1, "latent_channels": 4, "groups": 4}
MODEL = {"vae": VAE, "encoder": {"kind": "cnn", "channels": 8, "stride": 4}, "feature_channels": 4, "depth_bins": 8,
         "cond_channels": 8, "widths": [8, 16], "blocks": 1, "groups": 4, "sample_steps": 2}


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    out = tmp_path_factory.mktemp("geometry")
    for split in ("train", "val", "test"):
        generate_dataset(out, split, 1, TINY, progress=False)
    return out


def test_grid_in_box_coarsens_by_majority_and_any_visibility():
    grid = LiftGrid((-10.24 + 1.6, -51.2, -3.23), 1.6, (4, 4, 4))  # the box starts one 1.6 m voxel in x
    ijk = torch.tensor([[2, 0, 0], [3, 0, 0], [3, 1, 1], [2, 1, 0], [0, 0, 0], [20, 0, 0]])
    road, car = label_id("road"), label_id("car")
    labels = torch.tensor([road, car, car, car, road, road])
    visible = torch.tensor([False, False, True, False, True, True])
    out, lab, vis = grid_in_box(ijk, labels, visible, 2, 0.8, grid)
    # 0.8 m voxels (2..3, 0..1, 0..1) fall in 1.6 m voxel (1, 0, 0) = box voxel (0, 0, 0); (0, 0, 0) is
    # left of the box and (20, 0, 0) -> 1.6 m voxel 10, past its 4 voxels
    assert out.tolist() == [[0, 0, 0]] and lab.tolist() == [car] and vis.tolist() == [True]


def test_grid_metrics_by_hand():
    road, car = label_id("road"), label_id("car")
    gt = {"gt_ijk": torch.tensor([[0, 0, 0], [1, 0, 0], [2, 0, 0]]), "gt_labels": torch.tensor([road, road, car])}
    pred = (torch.tensor([[1, 0, 0], [2, 0, 0], [3, 0, 0]]), torch.tensor([road, road, car]))
    m = grid_metrics([pred], [gt], split=False)
    assert m["iou"] == pytest.approx(2 / 4)
    # road: TP 1 (voxel 1), FP 1 (voxel 2 predicted road), FN 1 (voxel 0) -> 1/3; car: TP 0 -> 0
    assert m["label_iou_road"] == pytest.approx(1 / 3) and m["label_iou_car"] == 0.0
    assert m["miou"] == pytest.approx(1 / 6)
    # voxels 1, 2 match; 0 and 3 are one voxel from the other grid: Chamfer 0.5 (1/3 + 1/3) = 1/3
    assert m["chamfer_q50"] == pytest.approx(1 / 3)


def test_prune_decode_keeps_children_of_occupied_parents_only():
    final = torch.full((1, 4, 4, 4), -5.0)
    final[0, 0, 0, 0] = final[0, 3, 3, 3] = 5.0
    parent = torch.full((1, 2, 2, 2), -5.0)
    parent[0, 0, 0, 0] = 5.0  # (3, 3, 3)'s parent (1, 1, 1) is empty: pruned
    labels = torch.zeros(1, 26, 4, 4, 4)
    labels[0, 7] = 1.0
    ijks, labs = prune_decode([parent], final, labels)
    assert ijks[0].tolist() == [[0, 0, 0]] and labs[0].tolist() == [7]


def _vae_batch(data):
    stage = get_stage("geometry-vae")
    ds = stage.dataset(data, GeometryDataConfig(**DATA), "train", 0)
    return stage, [ds[0]]


@pytest.mark.parametrize("child_kernel", [None, 3])
def test_structure_vae_overfits_one_grid(data, child_kernel):
    torch.manual_seed(0)
    stage, batch = _vae_batch(data)
    model = stage.build_model(stage.model_config(vae=VAEConfig(**VAE, child_kernel=child_kernel)))
    assert len(batch[0]["gt_ijk"]) > 50
    opt = torch.optim.Adam(model.parameters(), 1e-2)
    model.eval()
    iou0 = stage.evaluate(model, [batch])["iou"]
    model.train()
    for _ in range(200):
        loss, _ = stage.loss(model, batch)
        opt.zero_grad()
        loss.backward()
        opt.step()
    model.eval()
    with torch.no_grad():
        m = stage.evaluate(model, [batch])
    assert iou0 < 0.3 and m["iou"] > 0.9, (iou0, m)
    assert float(model.vae.latent_std) > 0


def _geometry_item(data):
    stage = get_stage("geometry")
    ds = stage.dataset(data, GeometryDataConfig(**DATA), "val", 0)
    return stage, ds[0]


@pytest.mark.parametrize("mode", ["diffusion", "predictor"])
def test_conditional_model_overfits_one_sample_with_t_and_noise_fixed(data, mode):
    stage, item = _geometry_item(data)
    torch.manual_seed(0)
    model = GeometryNet(GeometryModelConfig(**MODEL, mode=mode, depth_weight=0.0))
    model.vae_loaded = True  # a random frozen VAE is still a fixed encoding of the grid
    opt = torch.optim.Adam([p for p in model.parameters() if p.requires_grad], 3e-3)
    model.train()
    losses = []
    for _ in range(60):
        torch.manual_seed(1)  # the same t and noise every step
        loss, _ = model.loss(item)
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(float(loss.detach()))
    assert losses[-1] < losses[0] / 10, losses[::10]
    model.eval()
    with torch.no_grad():
        _, probs, _ = model.conditioner(item, item["lift_grid"])
        ijk, labs = model.predict(item, seed=3)
        ijk2, labs2 = model.predict(item, seed=3)
    assert torch.equal(ijk, ijk2) and torch.equal(labs, labs2)  # the same input and seed: the same grid
    assert ijk.shape[1] == 3 and len(ijk) == len(labs)
    torch.testing.assert_close(probs.sum(1), torch.ones_like(probs.sum(1)))


def test_depth_loss_targets_come_from_the_depth_maps(data):
    _, item = _geometry_item(data)
    model = GeometryNet(GeometryModelConfig(**MODEL))
    _, probs, target = model.conditioner(item, item["lift_grid"])
    n, d, h, w = probs.shape
    assert target.shape == (n, h, w)
    # sky pixels (inf depth) have no target; ground pixels near the cameras do
    # feature pixel (r, c) of stride 4 reads the image pixel at (4 r + 2, 4 c + 2), clamped to the image
    rows = torch.clamp(torch.arange(h) * 4 + 2, max=item["images"].shape[2] - 1)
    cols = torch.clamp(torch.arange(w) * 4 + 2, max=item["images"].shape[3] - 1)
    sky = item["sky"][:, rows][:, :, cols]
    valid = item["valid"][:, rows][:, :, cols]
    depth = item["depth"][:, rows][:, :, cols]
    in_range = valid & ~sky & (depth >= 0.1) & (depth < 90.0)
    assert bool((target[~in_range] == -1).all()) and bool((target[in_range] >= 0).all())
    assert float(in_range.float().mean()) > 0.3
    centres = model.conditioner.bin_centres.float()
    # the target bin is the one whose edges hold the depth
    edges = model.conditioner.bin_edges
    ok = target >= 0
    assert bool(((edges[target[ok]] <= depth[ok].double()) & (depth[ok].double() < edges[target[ok] + 1])).all())
    assert len(centres) == d


def test_bad_inputs_give_clear_errors(data):
    _, item = _geometry_item(data)
    model = GeometryNet(GeometryModelConfig(**MODEL))
    grid = item["lift_grid"]
    with pytest.raises(InputError, match=r"images: expected \(N >= 1, 3, H, W\)"):
        model.conditioner({**item, "images": item["images"][:0]}, grid)
    k = item["intrinsics"].clone()
    k[0, :2] *= 4  # K of an image four times larger
    with pytest.raises(InputError, match=r"camera FRONT: intrinsics .* principal point"):
        model.conditioner({**item, "intrinsics": k}, grid)
    pose = item["cam_to_chunk"].clone()
    pose[1, 0, 3] = math.nan
    with pytest.raises(InputError, match=r"camera FRONT_LEFT: cam_to_chunk must be a finite rigid"):
        model.conditioner({**item, "cam_to_chunk": pose}, grid)
    with pytest.raises(InputError, match="vae_checkpoint"):
        model.loss(item)


def test_a_camera_that_sees_only_sky_gives_a_defined_output(data):
    _, item = _geometry_item(data)
    torch.manual_seed(0)
    model = GeometryNet(GeometryModelConfig(**MODEL))
    model.vae_loaded = True
    sky = {**item, "depth": torch.full_like(item["depth"], math.inf), "sky": torch.ones_like(item["sky"])}
    loss, logs = model.loss(sky)
    assert math.isfinite(float(loss.detach())) and logs["depth"] == 0.0


def _write(path, stage, steps, model, data=DATA):
    path.write_text(yaml.safe_dump({"stage": stage, "train": {"seed": 0, "steps": steps, "batch_size": 1,
                                                              "lr": 1e-3, "threads": 1},
                                    "model": model, "data": data}))
    return path


def test_both_stages_train_resume_and_evaluate(data, tmp_path):
    vae_run = tmp_path / "vae"
    train("geometry-vae", config_from_dict(yaml.safe_load(_write(tmp_path / "v.yaml", "geometry-vae", 2,
                                                                       {"vae": VAE}).read_text())),
                data, vae_run, progress=False)
    assert (vae_run / "last.pt").is_file()
    cfg = yaml.safe_load(_write(tmp_path / "g.yaml", "geometry", 2,
                                {**MODEL, "vae_checkpoint": str(vae_run / "last.pt")}).read_text())
    run = tmp_path / "geo"
    train("geometry", config_from_dict(cfg), data, run, progress=False)
    out = tmp_path / "m.json"
    r = CliRunner().invoke(app, ["eval", "stage", "geometry", "--data", str(data), "--checkpoint", str(run / "last.pt"),
                                 "--split", "test", "-o", str(out)])
    assert r.exit_code == 0, r.output
    m = json.loads(out.read_text())["metrics"]
    assert 0.0 <= m["iou"] <= 1.0 and "miou" in m and "iou_visible" in m and "chamfer_invisible_q90" in m
    # the VAE's weights travel inside the conditional model's checkpoint
    (vae_run / "last.pt").unlink()
    r = CliRunner().invoke(app, ["eval", "stage", "geometry", "--data", str(data), "--checkpoint", str(run / "last.pt"),
                                 "--split", "test", "-o", str(tmp_path / "m2.json")])
    assert r.exit_code == 0, r.output
    assert json.loads((tmp_path / "m2.json").read_text())["metrics"]["iou"] == m["iou"]


# --- the fine level: sparse, its latent on the coarse sites ------------------------------------------
FINE_DATA = {"level": "fine", "voxel_size": 1.6, "coarse_voxel_size": 3.2, "image_scale": 1.0}


def test_fine_items_hold_both_grids_and_crops_stay_inside(data):
    stage = get_stage("geometry")
    item = stage.dataset(data, GeometryDataConfig(**FINE_DATA), "val", 0)[0]
    fine, coarse = item["gt_ijk"], item["coarse_gt_ijk"]
    # every coarse voxel is the parent of some fine voxel and the other way round
    assert torch.equal(torch.unique(fine // 2, dim=0), torch.unique(coarse, dim=0))
    assert item["gt_grid"].voxel_size == 1.6 and item["lift_grid"].voxel_size == 3.2
    crop = stage.dataset(data, GeometryDataConfig(**FINE_DATA, crop=32.0), "train", 0)
    it = crop[0]
    assert it["lift_grid"].dims[:2] == (10, 10) and bool((it["gt_ijk"][:, :2] < 20).all())
    lo = np.array(it["lift_grid"].origin)
    # the same window of the chunk, cut from the whole box's voxels of the same sample
    whole = stage.dataset(data, GeometryDataConfig(**FINE_DATA), "train", 0)[0]
    full = whole["gt_ijk"].numpy() * 1.6 + np.array(whole["gt_grid"].origin)
    inside = np.all((full[:, :2] >= lo[:2]) & (full[:, :2] < lo[:2] + 32.0), axis=1)
    assert inside.sum() == len(it["gt_ijk"]) > 0


def test_fine_structure_vae_overfits_one_grid(data):
    torch.manual_seed(0)
    stage = get_stage("geometry-vae")
    batch = [stage.dataset(data, GeometryDataConfig(**FINE_DATA), "train", 0)[0]]
    model = stage.build_model(stage.model_config(level="fine", vae=VAEConfig(**VAE)))
    opt = torch.optim.Adam(model.parameters(), 1e-2)
    for _ in range(60):
        model.train()
        loss, _ = stage.loss(model, batch)
        opt.zero_grad()
        loss.backward()
        opt.step()
    model.eval()
    with torch.no_grad():
        m = stage.evaluate(model, [batch])
    assert m["iou"] > 0.9, m


@pytest.mark.parametrize("mode", ["diffusion", "predictor"])
def test_fine_conditional_model_overfits_one_sample(data, mode):
    stage = get_stage("geometry")
    item = stage.dataset(data, GeometryDataConfig(**FINE_DATA, crop=19.2), "train", 0)[0]  # a 6 x 6 site window
    assert 10 < len(item["coarse_gt_ijk"]) < 300
    torch.manual_seed(0)
    # one wide level: every site's latent is its own regression target here
    model = GeometryNet(GeometryModelConfig(**{**MODEL, "widths": [32], "cond_channels": 16}, level="fine",
                                            mode=mode, depth_weight=0.0))
    model.vae_loaded = True
    # a trained VAE's running RMS makes the scaled latent unit-sized: do the same for this random one
    model.vae.latent_std.copy_(model.latent_target(item).feats.pow(2).mean().sqrt())
    opt = torch.optim.Adam([p for p in model.parameters() if p.requires_grad], 3e-3)
    model.train()
    losses = []
    for _ in range(40):
        torch.manual_seed(1)
        loss, _ = model.loss(item)
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(float(loss.detach()))
    assert losses[-1] < losses[0] / 10, losses[::10]
    model.eval()
    with torch.no_grad():
        ijk, labs = model.predict(item, seed=0)
        again = model.predict(item, seed=0)
    assert torch.equal(ijk, again[0]) and ijk.shape[1] == 3
    # predicted fine voxels lie inside the coarse grid they were decoded from
    parents = torch.unique(ijk // 2, dim=0)
    assert bool(torch.isin(parents[:, 0] * 10000 + parents[:, 1] * 100 + parents[:, 2],
                           item["coarse_gt_ijk"][:, 0] * 10000 + item["coarse_gt_ijk"][:, 1] * 100
                           + item["coarse_gt_ijk"][:, 2]).all())


# --- extremes ---------------------------------------------------------------------------------------
def _shift_world(src, dst, offset):
    """A copy of a worlds dataset whose world frame is moved by `offset` metres: every pose and box
    of the samples' meta.json moves with it; images, depth and voxels (camera and chunk frames) stay."""
    import shutil

    shutil.copytree(src, dst)
    for meta in dst.glob("*/*/meta.json"):
        m = json.loads(meta.read_text())

        def move(pose):
            pose[0][3] += offset[0]
            pose[1][3] += offset[1]
            pose[2][3] += offset[2]

        move(m["chunk_to_world"])
        move(m["lidar"]["pose_start"])
        move(m["lidar"]["pose_end"])
        for f in m["frames"]:
            move(f["ego_pose"])
            for c in f["cameras"]:
                move(c["cam_to_world"])
            for b in f["boxes"]:
                b["center"] = [v + o for v, o in zip(b["center"], offset)]
        meta.write_text(json.dumps(m))


def test_a_chunk_a_million_metres_out_converts_to_the_same_grid(data, tmp_path):
    far = tmp_path / "far"
    _shift_world(data, far, (1.0e6, -1.0e6, 50.0))
    stage = get_stage("geometry")
    near_item = stage.dataset(data, GeometryDataConfig(**DATA), "test", 0)[0]
    far_item = stage.dataset(far, GeometryDataConfig(**DATA), "test", 0)[0]
    assert float(far_item["chunk_to_world"][0, 3]) - float(near_item["chunk_to_world"][0, 3]) == 1.0e6
    torch.testing.assert_close(far_item["cam_to_chunk"], near_item["cam_to_chunk"], rtol=0, atol=1e-6)
    torch.manual_seed(0)
    model = GeometryNet(GeometryModelConfig(**MODEL)).eval()
    with torch.no_grad():
        a, la = model.predict(near_item, seed=5)
        b, lb = model.predict(far_item, seed=5)
    assert torch.equal(a, b) and torch.equal(la, lb)


class _NanAtStep3:
    """The VAE stage whose third loss is NaN (a diverged step)."""

    def __init__(self, stage):
        self.stage, self.calls = stage, 0

    def __getattr__(self, name):
        return getattr(self.stage, name)

    def loss(self, model, batch):
        loss, logs = self.stage.loss(model, batch)
        self.calls += 1
        return (loss * float("nan") if self.calls == 3 else loss), logs


def test_a_non_finite_loss_stops_training_and_a_resume_continues(data, tmp_path):
    from scube_sim.model.checkpoint import load_checkpoint
    from scube_sim.model.trainer import TrainingError

    cfg = yaml.safe_load(_write(tmp_path / "v.yaml", "geometry-vae", 4, {"vae": VAE}).read_text())
    cfg["train"]["checkpoint_every"] = 1
    stage = get_stage("geometry-vae")
    flaky = _NanAtStep3(stage)
    with pytest.raises(TrainingError, match=r"step 3: the loss is nan; the last good checkpoint is .*last\.pt"):
        train(flaky, config_from_dict(cfg), data, tmp_path / "run", progress=False)
    assert load_checkpoint(tmp_path / "run" / "last.pt")["step"] == 2
    train(stage, config_from_dict(cfg), data, tmp_path / "run", resume=True, progress=False)
    ck = load_checkpoint(tmp_path / "run" / "last.pt")
    assert ck["step"] == 4 and all(torch.isfinite(t).all() for t in ck["model"].values() if t.is_floating_point())


def test_the_depth_prior_baseline_puts_voxels_where_its_depth_says(data):
    """With the depth head forced to the ground-truth bins, the unprojected voxels are the visible
    surface: nearly all of them are ground-truth voxels or next to one."""
    _, item = _geometry_item(data)
    model = GeometryNet(GeometryModelConfig(**MODEL)).eval()
    cond = model.conditioner
    # the ground-truth bins at the feature pixels, as the depth loss sees them
    with torch.no_grad():
        _, probs, target = cond(item, item["lift_grid"])
    logits = torch.full_like(probs, -30.0)
    ok = target >= 0
    logits.permute(0, 2, 3, 1)[ok] = torch.where(
        torch.nn.functional.one_hot(target[ok], probs.shape[1]).bool(), 30.0, -30.0)
    c = cond.cfg.feature_channels
    orig = cond.head.forward
    cond.head.forward = lambda x: torch.cat([orig(x)[:, :c], logits], 1)
    with torch.no_grad():
        ijk, labels = model.predict_from_depth(item)
    cond.head.forward = orig
    assert len(ijk) > 20 and bool((labels == 0).all())
    gt = item["gt_ijk"]
    d = torch.cdist(ijk.double(), gt.double()).min(1).values
    assert float((d <= 1.0).double().mean()) > 0.9


@pytest.mark.parametrize("level", ["coarse", "fine"])
def test_calibrated_latents_have_unit_rms(data, level):
    from scube_sim.model.geometry.stage import calibrate_latent_std

    torch.manual_seed(0)
    stage = get_stage("geometry-vae")
    cfg = GeometryDataConfig(**(DATA if level == "coarse" else FINE_DATA))
    ds = stage.dataset(data, cfg, "train", 0)
    model = stage.build_model(stage.model_config(level=level, vae=VAEConfig(**VAE)))
    std = calibrate_latent_std(model, ds)
    batch = [ds[0]]
    from scube_sim.model.geometry.stage import _dense_batch, _sparse_batch

    with torch.no_grad():
        if level == "fine":
            mu = model.vae.encode(*_sparse_batch(batch), 1)[0].feats
        else:
            mu = model.vae.encode(*_dense_batch(batch))[0]
    # one train item: its RMS over the calibrated scale is 1
    assert float((mu / std).pow(2).mean().sqrt()) == pytest.approx(1.0, rel=1e-5)


def test_oracle_lifting_puts_features_on_the_visible_surface_only(data):
    """lifting: oracle: each pixel's features land in its depth map's bin alone, so the voxels that
    receive features are the visible surface (at or next to a ground-truth voxel), where Eq. 1 with
    an untrained depth head smears them along every ray."""
    _, item = _geometry_item(data)
    filled = {}
    for lifting in ("oracle", "depth"):
        model = GeometryNet(GeometryModelConfig(**{**MODEL, "lifting": lifting})).eval()
        model.conditioner.down = torch.nn.Identity()  # the lifted volume itself
        with torch.no_grad():
            x, _, target = model.conditioner(item, item["lift_grid"])
        c = model.cfg.feature_channels
        filled[lifting] = torch.nonzero(x[0, :c].abs().sum(0) > 0)
    ijk = filled["oracle"]
    assert len(ijk) > 20 and len(filled["depth"]) > 3 * len(ijk)
    d = torch.cdist(ijk.double(), item["gt_ijk"].double()).min(1).values
    assert float((d <= 1.0).double().mean()) > 0.9


def test_mean_lifting_holds_the_weighted_mean_feature_and_the_summed_weight(data):
    """lift_norm mean: with every pixel's features the same vector c, each voxel holds c however
    many frustum points land in it (the sum holds c times their weight, which spans orders of
    magnitude), and the next channel holds log(1 + the summed weight)."""
    _, item = _geometry_item(data)
    c_vec = torch.tensor([0.5, -1.0, 2.0, 0.25])
    vols = {}
    for norm in ("mean", "sum"):
        torch.manual_seed(0)
        model = GeometryNet(GeometryModelConfig(**{**MODEL, "lifting": "oracle", "lift_norm": norm})).eval()
        model.conditioner.down = torch.nn.Identity()
        last = model.conditioner.head[-1]
        with torch.no_grad():
            last.weight.zero_()
            last.bias.zero_()
            last.bias[:4] = c_vec
            vols[norm], _, _ = model.conditioner(item, item["lift_grid"])
    mean, summed = vols["mean"][0], vols["sum"][0]
    assert mean.shape[0] == 4 + 2 and summed.shape[0] == 4 + 1
    mass = torch.expm1(mean[4])
    reached = mass >= 1.0  # oracle: the number of pixels whose depth falls in the voxel
    assert int(reached.sum()) > 20
    torch.testing.assert_close(mean[:4][:, reached], c_vec[:, None].expand(4, int(reached.sum())), rtol=0.011, atol=0)
    torch.testing.assert_close(summed[:4][:, reached], c_vec[:, None] * mass[reached][None], rtol=1e-4, atol=1e-5)
    assert float(mass[reached].max()) > 10 * float(mass[reached].min())
    torch.testing.assert_close(mean[5], summed[4])  # log(1 + frustum points) in both


def _fit_decoded_predictor(model, item, steps: int = 40, lr: float = 1e-2):
    """Trains `model` on `item` alone -> (voxel IoU of its prediction before, after, the decoded
    losses per step)."""
    opt = torch.optim.Adam([p for p in model.parameters() if p.requires_grad], lr)
    truth = {tuple(v) for v in item["gt_ijk"].tolist()}

    def iou():
        model.eval()
        with torch.no_grad():
            ijk, _ = model.predict(item)
        model.train()
        a = {tuple(v) for v in ijk.tolist()}
        return len(a & truth) / max(len(a | truth), 1)

    iou0 = iou()
    losses = []
    for _ in range(steps):
        loss, logs = model.loss(item)
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(logs["latent"])
    return iou0, iou(), losses


def test_decoded_predictor_learns_one_grid_through_the_frozen_decoder(data):
    """predictor_loss decoded: the loss is the frozen VAE's structure BCE + label CE of the
    decoded prediction, so training on one sample moves the decoded grid towards it."""
    stage, item = _geometry_item(data)
    torch.manual_seed(0)
    model = GeometryNet(GeometryModelConfig(**MODEL, mode="predictor", predictor_loss="decoded", depth_weight=0.0))
    model.vae_loaded = True
    iou0, iou1, losses = _fit_decoded_predictor(model, item)
    # a random frozen decoder cannot draw every grid (the loss has a floor), but its best match
    # to this one is found: IoU from ~0.02 to ~0.35
    assert losses[-1] < 0.9 * losses[0], losses[::8]
    assert iou1 > iou0 + 0.2, (iou0, iou1)
    with pytest.raises(ValueError, match="predictor_loss 'decoded'"):
        GeometryModelConfig(**MODEL, mode="diffusion", predictor_loss="decoded")


def test_the_refiner_starts_as_the_decoder_and_places_voxels_the_frozen_decoder_cannot(data):
    """refine: an untrained refiner returns the decoder's logits (its head starts at zero); trained
    on one sample it reaches an IoU the decoded predictor alone cannot through the random frozen
    decoder, because it corrects each voxel from the lifted volume at the voxels' own size."""
    _, item = _geometry_item(data)
    cfg = {**MODEL, "mode": "predictor", "predictor_loss": "decoded", "depth_weight": 0.0}
    torch.manual_seed(0)
    plain = GeometryNet(GeometryModelConfig(**cfg))
    torch.manual_seed(0)
    refined = GeometryNet(GeometryModelConfig(**cfg, refine=True, refine_width=8))
    refined.load_state_dict(plain.state_dict(), strict=False)  # the same VAE, conditioner and denoiser
    plain.vae_loaded = refined.vae_loaded = True
    with torch.no_grad():
        vol, lifted, _, _ = refined._condition(item, item["lift_grid"])
        assert lifted.shape[2:] == tuple(item["gt_grid"].dims)
        z = refined.sample_latent(vol, (1, refined.cfg.vae.latent_channels, *vol.shape[2:]))
        want = refined.vae.decode(z * refined.vae.latent_std)
        got = refined._decode(z, lifted)
    assert torch.equal(got[1], want[1]) and torch.equal(got[2], want[2])
    _, iou_plain, _ = _fit_decoded_predictor(plain, item)
    _, iou_refined, losses = _fit_decoded_predictor(refined, item, steps=80)
    assert losses[-1] < 0.5 * losses[0], losses[::8]
    assert iou_refined > iou_plain + 0.2, (iou_plain, iou_refined)
    with pytest.raises(ValueError, match="refine"):
        GeometryModelConfig(**MODEL, mode="diffusion", refine=True)


def test_observed_voxels_are_the_first_surface_each_camera_sees():
    """A pinhole camera at the origin looking along +x at two walls, 10 m and 14 m out: the near
    wall's voxels inside the field of view are observed, the far wall (behind it) and the near
    wall's voxels outside the view are not."""
    from scube_sim.model.geometry.net import observed_voxels

    grid = LiftGrid(origin=(-8.0, -8.0, -8.0), voxel_size=1.0, dims=(32, 16, 16))
    near = torch.tensor([[18, j, k] for j in range(16) for k in range(16)])  # x in [10, 11) m
    far = near + torch.tensor([4, 0, 0])
    ijk = torch.cat([near, far])
    # camera axes: x right, y down, z forward -> chunk: forward +x, right -y, down -z
    cam_to_chunk = torch.eye(4, dtype=torch.float64)
    cam_to_chunk[:3, :3] = torch.tensor([[0.0, 0, 1], [-1, 0, 0], [0, -1, 0]], dtype=torch.float64)
    f = 40.0  # 80 x 80 pixels: half-angle atan(40 / 40) = 45 deg -> |y|, |z| < 10 m at x = 10 m
    item = {"intrinsics": torch.tensor([[[f, 0, 40.0], [0, f, 40.0], [0, 0, 1]]], dtype=torch.float64),
            "distortion": torch.zeros(1, 5), "cam_to_chunk": cam_to_chunk[None], "image_size": torch.tensor([[80, 80]])}
    seen = observed_voxels(ijk, grid, item, stride=1)
    assert not seen[len(near):].any()
    # every near-wall voxel within the view's cone at its near face (|y|, |z| < 10 m) is seen
    centres = torch.tensor(grid.origin) + (near.double() + 0.5) * grid.voxel_size
    assert bool(seen[: len(near)].all())  # the 16 m wall spans +-8 m, all inside +-10 m
    narrow = dict(item, intrinsics=item["intrinsics"].clone())
    narrow["intrinsics"][0, 0, 0] = narrow["intrinsics"][0, 1, 1] = 80.0  # half-angle 26.6 deg: +-5 m
    seen = observed_voxels(ijk, grid, narrow, stride=1)
    inside = (centres[:, 1].abs() < 4.5) & (centres[:, 2].abs() < 4.5)
    outside = (centres[:, 1].abs() > 5.5) | (centres[:, 2].abs() > 5.5)
    assert bool(seen[: len(near)][inside].all()) and not seen[: len(near)][outside].any()
    assert not seen[len(near):].any()


def test_confidence_is_the_share_of_samples_holding_each_voxel(data):
    from scube_sim.model.geometry.net import observed_voxels

    _, item = _geometry_item(data)
    torch.manual_seed(0)  # the weights: otherwise they depend on which tests ran before
    model = GeometryNet(GeometryModelConfig(**MODEL)).eval()
    with torch.no_grad():
        ijk, labels, conf, observed = model.predict_with_confidence(item, k=1, seed=5)
        first, first_labels = model.predict(item, seed=5)
        assert torch.equal(ijk, first) and torch.equal(labels, first_labels) and bool((conf == 1).all())
        ijk3, _, conf3, observed3 = model.predict_with_confidence(item, k=3, seed=5)
        samples = [set(map(tuple, model.predict(item, seed=s)[0].tolist())) for s in (5, 6, 7)]
    assert torch.equal(ijk3, first) and torch.equal(observed3, observed)
    want = torch.tensor([sum(tuple(v) in s for s in samples) / 3 for v in first.tolist()], dtype=torch.float32)
    assert len(first) > 0 and torch.equal(conf3, want)
    assert observed.dtype == torch.bool and torch.equal(observed, observed_voxels(first, item["gt_grid"], item))
    with pytest.raises(InputError, match="k: expected at least one sample"):
        model.predict_with_confidence(item, k=0)


def test_the_predictors_confidence_is_its_decoders_occupancy_probability(data):
    """mode predictor: no samples to count; the confidence of a voxel is the product of the
    decoder's occupancy probabilities of the voxel and of its ancestors (each > 0.5 where kept)."""
    _, item = _geometry_item(data)
    torch.manual_seed(0)
    model = GeometryNet(GeometryModelConfig(**MODEL, mode="predictor")).eval()
    with torch.no_grad():
        ijk, labels, conf, _ = model.predict_with_confidence(item, k=4)
        first, _ = model.predict(item)
        vol, _, _ = model.conditioner(item, item["lift_grid"])
        z = model.sample_latent(vol, (1, model.cfg.vae.latent_channels, *vol.shape[2:]))
        occ_levels, occ_final, _ = model.vae.decode(z * model.vae.latent_std)
    assert torch.equal(ijk, first) and len(ijk) > 0
    dense = torch.sigmoid(occ_final[0])
    for logits in occ_levels:  # every coarser level upsampled to the voxel grid, multiplied in
        s = occ_final.shape[-1] // logits.shape[-1]
        dense = dense * torch.sigmoid(logits[0]).repeat_interleave(s, 0).repeat_interleave(s, 1).repeat_interleave(s, 2)
    want = dense[ijk[:, 0], ijk[:, 1], ijk[:, 2]].float()
    torch.testing.assert_close(conf, want, rtol=1e-5, atol=1e-6)
    assert bool((conf > 0.5 ** (len(occ_levels) + 1)).all()) and bool((conf <= 1).all())


def test_fine_decoded_predictor_learns_one_sample_through_the_frozen_decoder(data):
    """The fine level's predictor_loss decoded: the predicted latent on the coarse sites, decoded
    by the frozen sparse VAE and scored against the fine voxels, so training on one window moves
    the decoded fine grid towards its ground truth."""
    stage = get_stage("geometry")
    item = stage.dataset(data, GeometryDataConfig(**FINE_DATA, crop=19.2), "train", 0)[0]
    torch.manual_seed(0)
    model = GeometryNet(GeometryModelConfig(**{**MODEL, "widths": [32], "cond_channels": 16}, level="fine",
                                            mode="predictor", predictor_loss="decoded", depth_weight=0.0))
    model.vae_loaded = True
    iou0, iou1, losses = _fit_decoded_predictor(model, item)
    # a random frozen decoder has a floor (the loss falls by ~10 %), but the decoded grid follows:
    # IoU ~0.31 -> ~0.55
    assert losses[-1] < 0.95 * losses[0], losses[::8]
    assert iou1 > iou0 + 0.15, (iou0, iou1)
