"""The converter's label -> reflectance defaults: one entry per label with a named source, the
lookup, and the measured entries against a fresh measurement on the real logs."""

from __future__ import annotations

import importlib.util

import numpy as np
import pytest

from scube_sim.errors import InputError
from scube_sim.labels import (
    LABEL_IDS,
    LABEL_NAMES,
    REFLECTANCE_DEFAULTS,
    REFLECTANCE_SOURCES,
    label_id,
    reflectance_from_labels,
)
from scube_sim.voxsplat import KNOWN_CHANNELS
from tests.conftest import REPO, require


def test_every_label_has_a_default_with_a_known_source():
    assert [d.label for d in REFLECTANCE_DEFAULTS] == list(LABEL_NAMES)
    lo, hi = KNOWN_CHANNELS["reflectance"].bounds
    for d in REFLECTANCE_DEFAULTS:
        assert lo <= d.reflectance <= hi
        if d.source.startswith("as "):  # borrowed from a measured class
            other = REFLECTANCE_DEFAULTS[label_id(d.source[3:])]
            assert other.source in REFLECTANCE_SOURCES and not other.source.startswith("as ")
        else:
            assert d.source in REFLECTANCE_SOURCES, d.label


def test_lookup_keeps_the_shape_and_refuses_unknown_ids():
    labels = np.array([[LABEL_IDS["car"], LABEL_IDS["road"]], [LABEL_IDS["sign"], LABEL_IDS["sky"]]], np.int16)
    out = reflectance_from_labels(labels)
    assert out.shape == (2, 2) and out.dtype == np.float32
    np.testing.assert_array_equal(out, np.float32([[0.13, 0.14], [1.0, 0.0]]))
    assert reflectance_from_labels(np.zeros(0, np.int64)).shape == (0,)
    with pytest.raises(InputError, match=r"labels hold ids -1\.\.3, expected 0\.\.25"):
        reflectance_from_labels(np.array([-1, 3]))
    with pytest.raises(InputError, match="labels must be integer label ids"):
        reflectance_from_labels(np.array([1.5]))


def test_measured_entries_match_the_real_logs(shared_data):
    """Re-measure with the tool: every entry taken from the nuScenes boxes, and the ground
    entries (mean of the nuScenes and Argoverse 2 ground medians), within the table's rounding."""
    from scube_sim.datasets import open_dataset

    spec = importlib.util.spec_from_file_location("measure", REPO / "tools" / "measure_class_reflectance.py")
    tool = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(tool)
    nus = tool.measure(open_dataset("nuscenes", require(shared_data / "nuscenes-mmdet3d-demo")), [0])
    av2 = tool.measure(open_dataset("argoverse2", require(shared_data / "argoverse2-sensor-log-7fab2350")), [0])
    for d in REFLECTANCE_DEFAULTS:
        if d.source == "nuscenes":
            assert abs(nus[d.label]["median"] - d.reflectance) <= 0.006, d.label
    ground = (nus["ground (unlabelled)"]["median"] + av2["ground (unlabelled)"]["median"]) / 2
    assert abs(reflectance_from_labels(LABEL_IDS["road"]) - ground) <= 0.006
    above = (nus["above ground, unlabelled"]["median"] + av2["above ground, unlabelled"]["median"]) / 2
    assert abs(reflectance_from_labels(LABEL_IDS["building"]) - above) <= 0.006
