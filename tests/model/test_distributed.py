"""Data-parallel training: each rank loads its own shard of every global batch, gradients are
averaged over the ranks, and two ranks reach the weights of one rank on the whole batch."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from scube_sim.model.checkpoint import load_checkpoint
from scube_sim.model.config import load_config
from scube_sim.model.trainer import ShardSampler, epoch_order, train
from tests.model.test_trainer import TOY, write_config


def test_the_ranks_shards_are_disjoint_equal_and_make_up_each_global_batch():
    n, batch, seed = 22, 6, 5  # 3 batches an epoch; 4 samples are left out of each epoch
    for epoch in (0, 1):
        order = epoch_order(n, seed, epoch)
        assert sorted(order.tolist()) == list(range(n))
        shards = [list(ShardSampler(n, batch, seed, epoch, rank=r, world=3)) for r in range(3)]
        assert all(len(s) == 3 and all(len(b) == 2 for b in s) for s in shards)
        for b in range(3):
            union = shards[0][b] + shards[1][b] + shards[2][b]
            assert union == list(ShardSampler(n, batch, seed, epoch))[b] == order[6 * b:6 * b + 6].tolist()
        # Resuming at batch 2 gives exactly the rest of the epoch.
        assert list(ShardSampler(n, batch, seed, epoch, start=2, rank=1, world=3)) == shards[1][2:]
    assert not np.array_equal(epoch_order(n, seed, 0), epoch_order(n, seed, 1))
    assert np.array_equal(epoch_order(n, seed, 1), epoch_order(n, seed, 1))
    with pytest.raises(ValueError, match="does not split"):
        ShardSampler(n, 6, seed, 0, world=4)


def test_two_ranks_reach_the_weights_of_one_rank_on_the_union_of_their_shards(tmp_path):
    data = tmp_path / "data"
    data.mkdir()
    # Global batch 8: each of the two ranks takes 4 samples of every batch.
    cfg = load_config(write_config(tmp_path / "run.yaml", epochs=2, checkpoint_every=3))
    one = train(TOY, cfg, data, tmp_path / "one", progress=False, ranks=1)
    two = train(TOY, cfg, data, tmp_path / "two", progress=False, ranks=2)
    assert one.step == two.step == 8

    a, b = load_checkpoint(one.last), load_checkpoint(two.last)
    for k in a["model"]:
        assert torch.allclose(a["model"][k], b["model"][k], rtol=0, atol=1e-6), k
    # The logged loss is the mean over the ranks, i.e. the full batch's.
    assert torch.allclose(a["history"]["train"]["loss"], b["history"]["train"]["loss"], rtol=1e-5, atol=0)
    # Rank 0 saved every rank's generator state; the ranks draw from streams of their own.
    assert b["world_size"] == 2 and len(b["rng"]) == 2 and len(a["rng"]) == 1
    assert not torch.equal(b["rng"][0]["torch"], b["rng"][1]["torch"])
    assert torch.equal(a["rng"][0]["torch"], b["rng"][0]["torch"])
    assert b["config"]["train"]["ranks"] == 2
