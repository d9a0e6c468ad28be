"""Dataset names as users type them: any case and punctuation of an adapter's name, a few common
aliases, and an unknown name answered with the known ones in one line."""

from __future__ import annotations

import pytest

from scube_sim.datasets import adapter_name, available, open_dataset


@pytest.mark.parametrize("typed, adapter", [("nuScenes", "nuscenes"), ("NUSCENES", "nuscenes"),
                                            ("kitti-360", "kitti360"), ("KITTI_360", "kitti360"),
                                            ("kitti-raw", "kitti_raw"), ("KittiObject", "kitti_object"),
                                            ("av2", "argoverse2"), ("Argoverse 2", "argoverse2"),
                                            ("tri-dgp", "tri_dgp"), ("DGP", "tri_dgp"), ("Worlds", "worlds")])
def test_spellings_name_their_adapter(typed, adapter):
    assert adapter_name(typed) == adapter


def test_an_unknown_name_lists_the_known_ones(tmp_path):
    with pytest.raises(ValueError) as err:
        open_dataset("lyft", tmp_path)
    msg = str(err.value)
    assert msg.startswith("dataset: unknown format 'lyft'; expected one of ") and "\n" not in msg
    assert all(name in msg for name in available())
    with pytest.raises(ValueError, match=r"unknown format 'kitti' \(kitti_raw or kitti_object\?\)"):
        adapter_name("kitti")
