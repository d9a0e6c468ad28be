"""Training configs: strict validation with errors naming the file and key, shipped configs by
name, and the stage's own sections validated by the stage's classes."""

from __future__ import annotations

import pytest
import yaml
from pydantic import Field

from scube_sim.config import ConfigError, StrictModel
from scube_sim.model import config as mc
from scube_sim.model.config import RunConfig, TrainConfig, config_names, load_config, resolved_config, stage_configs


def _write(path, data) -> str:
    path.write_text(yaml.safe_dump(data), encoding="utf-8")
    return str(path)


def test_defaults_follow_the_paper_and_a_file_loads_by_path(tmp_path):
    cfg = load_config(_write(tmp_path / "a.yaml", {"stage": "geometry", "train": {"epochs": 2}}))
    assert isinstance(cfg, RunConfig) and cfg.source.endswith("a.yaml")
    t = cfg.train
    assert t.betas == (0.9, 0.999) and t.lr == 1e-4 and t.eps == 1e-8 and t.weight_decay == 0.0
    assert (t.seed, t.batch_size, t.ranks, t.num_workers, t.deterministic, t.keep_best) == (0, 1, 1, 0, True, True)
    assert (t.epochs, t.steps, t.checkpoint_every, t.grad_clip, t.validate_every) == (2, None, None, None, 1)
    assert cfg.model == {} and cfg.data == {}


@pytest.mark.parametrize("train, needle", [
    ({"epochs": 2, "batchsize": 4}, "train.batchsize: unknown key"),
    ({"epochs": 2, "steps": 10}, "train: give exactly one of 'epochs' and 'steps'"),
    ({}, "train: give exactly one of 'epochs' and 'steps'"),
    ({"epochs": 2, "lr": 0}, "train.lr: expected a finite number > 0, got 0"),
    ({"epochs": 2, "betas": [0.9, 1.0]}, "train.betas: each beta must lie in [0, 1)"),
    ({"epochs": 2, "betas": [0.9]}, "train.betas"),
    ({"epochs": 0}, "train.epochs: expected an integer >= 1, got 0"),
])
def test_bad_train_settings_name_the_file_and_key(tmp_path, train, needle):
    path = _write(tmp_path / "bad.yaml", {"stage": "toy", "train": train})
    with pytest.raises(ConfigError) as exc:
        load_config(path)
    assert str(exc.value).startswith(f"{path}: ")
    assert needle in str(exc.value)


def test_other_bad_files(tmp_path):
    with pytest.raises(ConfigError, match=r"top\.yaml: seed: unknown key"):
        load_config(_write(tmp_path / "top.yaml", {"stage": "toy", "train": {"epochs": 1}, "seed": 1}))
    with pytest.raises(ConfigError, match=r"nostage\.yaml: stage: Field required"):
        load_config(_write(tmp_path / "nostage.yaml", {"train": {"epochs": 1}}))
    with pytest.raises(ConfigError, match=r"list\.yaml: expected a mapping of training settings, got list"):
        load_config(_write(tmp_path / "list.yaml", [1, 2]))
    (tmp_path / "syntax.yaml").write_text("train: [1, 2\n")
    with pytest.raises(ConfigError, match=r"syntax\.yaml: not valid YAML \(line"):
        load_config(tmp_path / "syntax.yaml")
    with pytest.raises(ConfigError, match=r"absent\.yaml: no such file"):
        load_config(tmp_path / "absent.yaml")


def test_shipped_configs_resolve_by_normalised_name(tmp_path, monkeypatch):
    monkeypatch.setattr(mc, "configs_dir", lambda: tmp_path)
    _write(tmp_path / "geometry-waymo.yaml", {"stage": "geometry", "train": {"epochs": 3}})
    _write(tmp_path / "appearance.yaml", {"stage": "appearance", "train": {"steps": 5}})
    assert config_names() == ["appearance", "geometry-waymo"]
    assert load_config("Geometry_Waymo").train.epochs == 3
    assert load_config("APPEARANCE").source == str(tmp_path / "appearance.yaml")
    with pytest.raises(ConfigError, match=r"unknown training config 'nope': not a file and not a shipped config; "
                                          r"shipped: appearance, geometry-waymo"):
        load_config("nope")


def test_the_shipped_folder_is_the_package_folder():
    assert mc.configs_dir().is_dir() and (mc.configs_dir() / "__init__.py").is_file()
    assert config_names() == sorted(p.stem for p in mc.configs_dir().glob("*.yaml"))


class _Model(StrictModel):
    width: int = Field(default=8, ge=1)


class _Data(StrictModel):
    root_split: str = "train"


def test_the_stage_sections_are_validated_by_the_stages_classes(tmp_path):
    path = _write(tmp_path / "run.yaml", {"stage": "toy", "train": {"epochs": 1}, "model": {"width": 4}})
    run = load_config(path)
    model_cfg, data_cfg = stage_configs(run, _Model, _Data)
    assert model_cfg.width == 4 and data_cfg.root_split == "train"
    resolved = resolved_config(run, model_cfg, data_cfg)
    assert resolved["model"] == {"width": 4} and resolved["data"] == {"root_split": "train"}
    assert resolved["train"]["betas"] == [0.9, 0.999]  # plain JSON values
    assert TrainConfig.model_validate(resolved["train"]) == run.train

    bad = load_config(_write(tmp_path / "bad.yaml", {"stage": "toy", "train": {"epochs": 1},
                                                     "model": {"width": 0, "depth": 2}}))
    with pytest.raises(ConfigError) as exc:
        stage_configs(bad, _Model, _Data)
    lines = str(exc.value).splitlines()
    assert f"{bad.source}: model.width: expected an integer >= 1, got 0" in lines
    assert f"{bad.source}: model.depth: unknown key" in lines


@pytest.mark.parametrize("name", config_names())
def test_every_shipped_config_validates_against_its_stage(name):
    from scube_sim.model.stages import get_stage

    run = load_config(name)
    stage = get_stage(run.stage)
    stage_configs(run, stage.model_config, stage.data_config)
