"""Restricted unpickling of third-party info files."""

from __future__ import annotations

import collections
import pickle

import numpy as np
import pytest

from scube_sim.io.safe_pickle import UnsafePickleError, load_pickle
from tests.conftest import require


def test_real_info_files_load(shared_data):
    nus = load_pickle(require(shared_data / "nuscenes-mmdet3d-demo" / "n015-2018-07-24-11-22-45+0800.pkl"))
    lidar2ego = np.asarray(nus["data_list"][0]["lidar_points"]["lidar2ego"])
    assert lidar2ego.shape == (4, 4)
    kitti = load_pickle(require(shared_data / "kitti-object-000008" / "000008.pkl"))
    assert isinstance(kitti, dict)


def test_numpy_and_containers_round_trip(tmp_path):
    obj = {"a": np.arange(6, dtype=np.float32).reshape(2, 3), "b": [1, 2.5, "x", (3, None)],
           "c": collections.OrderedDict(k=np.int64(4)), "d": np.array([b"ab"])}
    for proto in (2, 4, 5):
        p = tmp_path / f"ok{proto}.pkl"
        p.write_bytes(pickle.dumps(obj, protocol=proto))
        back = load_pickle(p)
        np.testing.assert_array_equal(back["a"], obj["a"])
        assert back["b"] == obj["b"] and back["c"]["k"] == 4


class Evil:
    def __reduce__(self):
        import os

        return (os.system, ("echo pwned",))


def test_foreign_class_is_refused(tmp_path):
    p = tmp_path / "evil.pkl"
    p.write_bytes(pickle.dumps({"x": Evil()}))
    with pytest.raises(UnsafePickleError, match=r"evil.pkl: refusing to load class (posix|os)\.system"):
        load_pickle(p)
    q = tmp_path / "junk.pkl"
    q.write_bytes(b"not a pickle")
    with pytest.raises(ValueError, match="junk.pkl: not a readable pickle"):
        load_pickle(q)
