"""Profiles inherit (`base:`): a file's keys laid over its base's section by section, the result the
same profile as writing every key out; circles and bad bases refused with one line naming the file."""

from __future__ import annotations

import sys

import pytest
import yaml

from scube_sim.converter.profile import ConverterProfile, load_profile, shipped_profiles
from scube_sim.errors import InputError
from scube_sim.reconstruct.config import EvidenceConfig


def test_a_profile_based_on_evidence_changes_only_its_own_keys(tmp_path):
    p = tmp_path / "mine.yaml"
    p.write_text("base: evidence\nevidence:\n  stereo:\n    fill_gap_deg: 10\n  ground_snap_m: null\n")
    mine, ev = load_profile(p), load_profile("evidence")
    assert mine.name == "mine" and mine.description == ""
    assert mine.evidence.stereo.fill_gap_deg == 10 and mine.evidence.ground_snap_m is None
    # every other key is the base's, down to the nested sections
    expect = ev.evidence.model_dump()
    expect["stereo"]["fill_gap_deg"], expect["ground_snap_m"] = 10, None
    assert mine.evidence.model_dump() == expect
    assert mine.route == ev.route and mine.context == ev.context


def test_the_shipped_profiles_that_inherit_equal_their_keys_written_out(tmp_path):
    """Each shipped profile read through its `base:` chain equals the profile built from its keys
    written out in full (pydantic from a plain mapping, no inheritance)."""
    for name in shipped_profiles():
        prof = load_profile(name)
        flat = tmp_path / f"{name}.yaml"
        flat.write_text(yaml.safe_dump(prof.model_dump(mode="json", exclude={"name"})))
        assert load_profile(flat).model_dump() == {**prof.model_dump(), "name": name}
    assert load_profile("evidence-complete").evidence == load_profile("evidence").evidence
    assert load_profile("evidence-fast").evidence.references == [0]
    assert load_profile("cpu-lidar").appearance.gaussians_per_voxel == 1
    assert load_profile("cpu-lidar").geometry == load_profile("cpu").geometry


def test_a_base_relative_to_the_file_and_a_circle(tmp_path):
    (tmp_path / "a.yaml").write_text("base: b.yaml\n")
    (tmp_path / "b.yaml").write_text("base: a.yaml\nroute: evidence\n")
    with pytest.raises(InputError, match=r"a.yaml: base: the profiles base each other in a circle"):
        load_profile(tmp_path / "a.yaml")
    (tmp_path / "c.yaml").write_text("base: d.yaml\ncontext: 2\n")
    (tmp_path / "d.yaml").write_text("route: evidence\ncontext: 4\n")
    c = load_profile(tmp_path / "c.yaml")
    assert c.route == "evidence" and c.context == 2 and c.evidence == EvidenceConfig()


def test_a_bad_base_is_one_line_naming_the_file(tmp_path):
    p = tmp_path / "bad.yaml"
    p.write_text("base: no-such-profile\n")
    with pytest.raises(InputError, match="profile 'no-such-profile': no such file, nor a shipped profile"):
        load_profile(p)
    p.write_text("base: [evidence]\n")
    with pytest.raises(InputError, match=r"bad.yaml: base: expected a shipped profile's name"):
        load_profile(p)


def test_a_profile_validates_without_torch():
    """The profile module imports no torch: a profile is checked before any network loads."""
    import subprocess

    code = ("import sys; from scube_sim.converter.profile import load_profile, DEFAULT_PROFILE; "
            "load_profile(DEFAULT_PROFILE); print('torch' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"
    assert isinstance(load_profile(), ConverterProfile)
