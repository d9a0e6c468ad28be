"""Checkpoints: plain values and tensors only, atomic writes, weights_only loading with errors
that name the file, and generator states that continue the same random streams."""

from __future__ import annotations

import os
import random
from collections import OrderedDict

import numpy as np
import pytest
import torch

from scube_sim.errors import ScubeSimError
from scube_sim.model import checkpoint as ckpt
from scube_sim.model.checkpoint import (
    FORMAT,
    VERSION,
    CheckpointError,
    check_plain,
    load_checkpoint,
    rng_state,
    save_checkpoint,
    seed_everything,
    set_rng_state,
)


def test_a_checkpoint_round_trips_tensors_and_plain_values(tmp_path):
    model = torch.nn.Linear(3, 2)
    opt = torch.optim.Adam(model.parameters(), betas=(0.9, 0.999))
    model(torch.randn(4, 3)).sum().backward()
    opt.step()
    state = {"model": model.state_dict(), "optimizer": opt.state_dict(), "step": 7, "lr": 1e-4, "name": "toy",
             "best": None, "done": False, "pair": (1, 2.5),
             "history": {"loss": torch.tensor([0.5, 0.25], dtype=torch.float64)},
             "rng": [rng_state()]}
    path = save_checkpoint(tmp_path / "last.pt", state)
    back = load_checkpoint(path)
    assert (back["format"], back["version"]) == (FORMAT, VERSION)
    for k, v in model.state_dict().items():
        assert torch.equal(back["model"][k], v)
    assert back["optimizer"]["param_groups"][0]["betas"] == (0.9, 0.999)
    assert torch.equal(back["optimizer"]["state"][0]["exp_avg"], opt.state_dict()["state"][0]["exp_avg"])
    plain = ("step", "lr", "name", "best", "done", "pair")
    assert [back[k] for k in plain] == [7, 1e-4, "toy", None, False, (1, 2.5)]
    assert torch.equal(back["history"]["loss"], state["history"]["loss"])
    assert not list(tmp_path.glob(".*"))  # no temporary file left behind


def test_restored_generator_states_continue_the_same_streams():
    seed_everything(3)
    torch.rand(5), np.random.rand(5), random.random(), np.random.randn()  # leaves a cached Gaussian in numpy
    state = rng_state()
    first = (torch.rand(4), np.random.randn(3), [random.gauss(0, 1) for _ in range(3)])
    seed_everything(99)
    set_rng_state(state)
    again = (torch.rand(4), np.random.randn(3), [random.gauss(0, 1) for _ in range(3)])
    assert torch.equal(first[0], again[0]) and np.array_equal(first[1], again[1]) and first[2] == again[2]
    check_plain(state)  # storable as it is
    assert state["torch"].dtype == torch.uint8 and type(state["numpy"]["key"][0]) is int


def test_values_that_weights_only_would_refuse_are_rejected_before_writing(tmp_path):
    for bad, where in [({"x": np.float64(1.0)}, "checkpoint.x"), ({"a": [1, np.zeros(2)]}, r"checkpoint.a\[1\]"),
                       ({"p": tmp_path}, "checkpoint.p"), ({(1, 2): 3}, "key")]:
        with pytest.raises(TypeError, match=where):
            save_checkpoint(tmp_path / "x.pt", bad)
    assert not list(tmp_path.iterdir())
    check_plain(OrderedDict(w=torch.zeros(1)))


def test_a_failed_write_leaves_the_previous_checkpoint_in_place(tmp_path, monkeypatch):
    path = save_checkpoint(tmp_path / "last.pt", {"step": 1})

    def broken_save(obj, f, *args, **kwargs):
        with open(f, "wb") as fh:
            fh.write(b"PK\x03\x04 half a zip")
        raise OSError("disk full")

    monkeypatch.setattr(ckpt.torch, "save", broken_save)
    with pytest.raises(OSError, match="disk full"):
        save_checkpoint(path, {"step": 2})
    monkeypatch.undo()
    assert load_checkpoint(path)["step"] == 1
    assert not list(tmp_path.glob(".*"))


class _Exploit:
    """Pickles to a call of os.system: weights_only must refuse it without running it."""

    def __init__(self, marker):
        self.marker = marker

    def __reduce__(self):
        return (os.system, (f"touch {self.marker}",))


def test_files_that_are_not_our_checkpoints_give_an_error_naming_the_file(tmp_path):
    marker = tmp_path / "ran"
    evil = tmp_path / "evil.pt"
    torch.save({"format": FORMAT, "version": VERSION, "x": _Exploit(marker)}, evil)
    with pytest.raises(CheckpointError, match=r"evil\.pt: not a loadable checkpoint \(it holds a pickled Python "
                       r"object \((os|posix)\.system\)") as err:
        load_checkpoint(evil)
    assert not marker.exists() and "weights_only" not in str(err.value)

    other = tmp_path / "other.pt"
    torch.save({"format": FORMAT, "version": VERSION + 1}, other)
    with pytest.raises(CheckpointError, match=rf"other\.pt: format '{FORMAT}', version {VERSION + 1}; expected"):
        load_checkpoint(other)
    plain = tmp_path / "weights.pt"
    torch.save(torch.nn.Linear(2, 2).state_dict(), plain)
    with pytest.raises(CheckpointError, match=r"weights\.pt: format None, version None"):
        load_checkpoint(plain)
    tensor = tmp_path / "tensor.pt"
    torch.save(torch.zeros(2), tensor)
    with pytest.raises(CheckpointError, match=r"tensor\.pt: a Tensor; expected"):
        load_checkpoint(tensor)

    good = save_checkpoint(tmp_path / "good.pt", {"w": torch.arange(1000.0)})
    cut = tmp_path / "cut.pt"
    cut.write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    with pytest.raises(CheckpointError, match=r"cut\.pt: not a loadable checkpoint"):
        load_checkpoint(cut)
    with pytest.raises(CheckpointError, match=r"missing\.pt: no such checkpoint file"):
        load_checkpoint(tmp_path / "missing.pt")
    assert issubclass(CheckpointError, ScubeSimError)
