"""A scenario's cached conversion (`runs.scenario.build._cached_conversion`) is keyed by every checkpoint
its profile names: a completion checkpoint retrained under the same file name misses the cache, so a
stale converted scene is never reused."""

from __future__ import annotations

import json
import shutil

import torch

from scube_sim.converter.merge import CompletionConfig
from scube_sim.converter.profile import load_profile
from scube_sim.model.checkpoint import resolve_checkpoint
from scube_sim.run_manifest import sha256_file
from scube_sim.runs.scenario import FramesSpec, conversion_key
from scube_sim.runs.scenario.build import _cache_entry_valid


def _cache_entry(stem, key):
    """What `_cached_conversion` leaves behind for `key`: the scene and its key with the scene's checksum."""
    npz, meta = stem.with_suffix(".npz"), stem.with_suffix(".json")
    npz.write_bytes(b"a converted scene")
    meta.write_text(json.dumps({"key": key, "sha256": sha256_file(npz)}))
    return npz, meta


def test_a_completion_checkpoint_retrained_under_the_same_name_misses_the_cache(tmp_path):
    ck = tmp_path / "completion.pt"
    shutil.copy(resolve_checkpoint("completion-v3-cpu"), ck)
    base = load_profile("evidence-complete")
    profile = base.model_copy(update={"completion": CompletionConfig(**{**base.completion.model_dump(),
                                                                        "checkpoint": str(ck)})})
    spec = FramesSpec(path="frames")
    key = conversion_key(spec, profile, seed=0)
    assert set(key["checkpoints"]) == {"completion"}
    npz, meta = _cache_entry(tmp_path / "converted", json.loads(json.dumps(key)))
    assert _cache_entry_valid(npz, meta, conversion_key(spec, profile, seed=0))

    # retrained: the same path now holds other weights
    state = torch.load(ck, weights_only=True)
    name = next(iter(state["model"]))
    state["model"][name] = state["model"][name] + 1e-3
    torch.save(state, ck)
    assert not _cache_entry_valid(npz, meta, conversion_key(spec, profile, seed=0))


def test_the_paper_routes_checkpoints_are_in_the_key_too():
    key = conversion_key(FramesSpec(path="frames"), load_profile("cpu"), seed=0)
    assert key["checkpoints"] == {"geometry": sha256_file(resolve_checkpoint("geometry-coarse-cpu")),
                                  "appearance": sha256_file(resolve_checkpoint("appearance-cpu"))}
