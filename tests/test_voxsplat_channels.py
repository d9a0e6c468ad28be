"""The VoxSplat format policy: named optional channels (version 2), version 1 files still load.

Files are checked with plain `numpy.load` / `numpy.savez` as the independent reader and writer."""

import json
import zipfile

import numpy as np
import pytest

from scube_sim.errors import InputError, NotFoundError
from scube_sim.voxsplat import FORMAT_NAME, KNOWN_CHANNELS, VoxSplat


def _scene(v=5, m=3, seed=0):
    rng = np.random.default_rng(seed)
    ijk = rng.integers(-50, 50, (v, 3))
    params = rng.normal(0, 1, (v, m, 14)).astype(np.float32)
    return VoxSplat(ijk, params, 0.25, origin=[1e6, -2e5, 30.0], labels=rng.integers(0, 20, v))


def test_scene_without_channels_is_written_as_version_1(tmp_path):
    path = _scene().save(tmp_path / "a.npz")
    with np.load(path) as z:
        assert int(z["version"]) == 1
        assert "channels" not in z.files and not any(f.startswith("channel.") for f in z.files)


def test_channels_round_trip_and_read_back_with_numpy(tmp_path):
    vs = _scene()
    rng = np.random.default_rng(1)
    observed = rng.random(vs.num_voxels) > 0.5
    refl = rng.random(vs.valid.shape).astype(np.float32)
    sky = rng.random((8, 16, 3)).astype(np.float32)
    vs.set_channel("observed", observed)
    vs.set_channel("reflectance", refl)
    vs.set_channel("sky_panorama", sky)
    vs.set_channel("lidar_hits", np.arange(vs.num_voxels * 2).reshape(-1, 2), per="voxel")  # a user's own
    path = vs.save(tmp_path / "b.npz")
    with np.load(path) as z:  # the independent reader
        assert str(z["format"]) == FORMAT_NAME and int(z["version"]) == 2
        assert json.loads(str(z["channels"])) == {"lidar_hits": "voxel", "observed": "voxel",
                                                   "reflectance": "gaussian", "sky_panorama": "scene"}
        np.testing.assert_array_equal(z["channel.observed"], observed)
        np.testing.assert_array_equal(z["channel.sky_panorama"], sky)
    back = VoxSplat.load(path)
    assert sorted(back.channels) == ["lidar_hits", "observed", "reflectance", "sky_panorama"]
    np.testing.assert_array_equal(back.channel("reflectance"), refl)
    assert back.channel("observed").dtype == bool
    np.testing.assert_array_equal(back.channel("lidar_hits"), np.arange(vs.num_voxels * 2).reshape(-1, 2))
    assert back.channels["sky_panorama"].per == "scene"
    np.testing.assert_array_equal(back.origin, [1e6, -2e5, 30.0])


def test_version_1_file_written_by_hand_still_loads(tmp_path):
    """A version 1 file as the first release wrote it (its keys, no channels)."""
    rng = np.random.default_rng(2)
    ijk = np.array([[0, 0, 0], [1, 2, 3]], np.int32)
    params = rng.normal(0, 1, (2, 4, 14)).astype(np.float32)
    path = tmp_path / "v1.npz"
    np.savez_compressed(path, format=np.array(FORMAT_NAME), version=np.array(1, np.int32), ijk=ijk, params=params,
                        valid=np.ones((2, 4), bool), labels=np.array([3, 4], np.int16), voxel_size=np.array(0.1),
                        origin=np.array([5.0, 6.0, 7.0]), offset_range=np.array(3.0),
                        metadata=np.array(json.dumps({"source": "hand"})))
    vs = VoxSplat.load(path)
    np.testing.assert_array_equal(vs.params, params)
    assert vs.channels == {} and vs.metadata == {"source": "hand"} and vs.voxel_size == 0.1


def test_newer_version_is_refused_with_the_file_named(tmp_path):
    path = _scene().save(tmp_path / "c.npz")
    with np.load(path) as z:
        arrays = {k: z[k] for k in z.files}
    arrays["version"] = np.array(99, np.int32)
    np.savez(tmp_path / "future.npz", **arrays)
    with pytest.raises(InputError, match=r"future\.npz: VoxSplat format version 99 is newer"):
        VoxSplat.load(tmp_path / "future.npz")


def test_channel_shapes_and_names_are_checked():
    vs = _scene(v=4, m=2)
    with pytest.raises(InputError, match=r"channel 'observed' \(per voxel\): expected leading shape \(4,\)"):
        vs.set_channel("observed", np.ones(5, bool))
    with pytest.raises(InputError, match=r"channel 'reflectance' \(per gaussian\): expected leading shape \(4, 2\)"):
        vs.set_channel("reflectance", np.ones((4, 3)))
    with pytest.raises(InputError, match=r"channel 'confidence': expected shape \(4,\)"):
        vs.set_channel("confidence", np.ones((4, 2)))
    with pytest.raises(InputError, match="is per voxel, got per scene"):
        vs.set_channel("observed", np.ones(4, bool), per="scene")
    with pytest.raises(InputError, match="channel name 'Bad-Name'"):
        vs.set_channel("Bad-Name", np.ones(4), per="voxel")
    with pytest.raises(InputError, match="per must be one of"):
        vs.set_channel("mine", np.ones(4))  # an unknown name needs its kind
    with pytest.raises(NotFoundError, match="has no channel 'confidence'; it has: none"):
        vs.channel("confidence")
    assert set(KNOWN_CHANNELS) >= {"observed", "confidence", "reflectance", "sky_panorama"}


def test_a_missing_channel_array_names_the_key(tmp_path):
    vs = _scene()
    vs.set_channel("confidence", np.linspace(0, 1, vs.num_voxels))
    path = vs.save(tmp_path / "d.npz")
    with zipfile.ZipFile(path) as zin, zipfile.ZipFile(tmp_path / "cut.npz", "w") as zout:
        for item in zin.infolist():
            if item.filename != "channel.confidence.npy":
                zout.writestr(item, zin.read(item.filename))
    with pytest.raises(InputError, match=r"cut\.npz: missing key 'channel\.confidence'"):
        VoxSplat.load(tmp_path / "cut.npz")


def test_keep_slots_keeps_the_most_opaque_valid_gaussians_with_their_channels():
    from scube_sim.splat_params import opacities_to_raw

    vs = _scene(v=3, m=4)
    alpha = np.array([[0.2, 0.9, 0.5, 0.7], [0.3, 0.3, 0.8, 0.1], [0.6, 0.95, 0.4, 0.99]])
    vs.params[..., 3] = opacities_to_raw(alpha)
    vs.valid[2, 3] = False  # the most opaque slot of voxel 2 is empty: never kept
    vs.set_channel("reflectance", np.arange(12, dtype=np.float32).reshape(3, 4) / 12)
    vs.set_channel("confidence", np.array([0.1, 0.5, 0.9], np.float32))
    two = vs.keep_slots(2)
    assert two.gaussians_per_voxel == 2 and two.num_voxels == 3
    want = [[1, 3], [2, 0], [1, 0]]  # by opacity, ties (voxel 1: 0.3, 0.3) to the lower slot
    np.testing.assert_allclose(two.opacities(), np.take_along_axis(alpha, np.array(want), 1), rtol=1e-5)
    np.testing.assert_array_equal(two.channel("reflectance"),
                                  np.take_along_axis(vs.channel("reflectance"), np.array(want), 1))
    np.testing.assert_array_equal(two.channel("confidence"), vs.channel("confidence"))
    assert two.valid.all() and vs.keep_slots(4) is vs
    with pytest.raises(InputError, match="keep_slots"):
        vs.keep_slots(0)
    # select_voxels: the voxels asked for, in order, with per-voxel and per-Gaussian channels
    sub = vs.select_voxels(np.array([False, True, True]))
    np.testing.assert_array_equal(sub.ijk, vs.ijk[1:])
    np.testing.assert_array_equal(sub.channel("reflectance"), vs.channel("reflectance")[1:])
    np.testing.assert_array_equal(sub.channel("confidence"), vs.channel("confidence")[1:])
    with pytest.raises(InputError, match="select_voxels"):
        vs.select_voxels(np.array([True]))
