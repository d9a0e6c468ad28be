"""One converter, two pipelines: the profile's route picks the pipeline, each takes only its own
options (any other refused with one line naming the route), and the CLI offers the paper route's
options only where the profile is that route."""

from __future__ import annotations

import pytest
from typer.testing import CliRunner

from scube_sim.cli import app
from scube_sim.converter.evidence import EvidencePipeline
from scube_sim.converter.pipeline import Converter
from scube_sim.converter.scube import PaperPipeline
from scube_sim.errors import InputError


def test_the_route_picks_the_pipeline_and_its_checkpoints():
    assert isinstance(Converter("evidence").pipeline, EvidencePipeline)
    assert Converter("evidence").checkpoint_hashes() == {}
    complete = Converter("evidence-complete")
    assert isinstance(complete.pipeline, EvidencePipeline) and set(complete.checkpoint_hashes()) == {"completion"}
    paper = Converter("cpu-lidar")
    assert isinstance(paper.pipeline, PaperPipeline)
    assert set(paper.checkpoint_hashes()) == {"geometry", "appearance"}


@pytest.mark.parametrize("option", ["sky", "steps", "fit_steps", "confidence"])
def test_the_evidence_route_refuses_the_paper_routes_options(option):
    with pytest.raises(InputError, match=rf"^{option}: profile 'evidence' \(route evidence\) does not use it; it takes "
                                         r"seed, max_range, evidence$"):
        Converter("evidence").convert(None, **{option: 1})


def test_the_paper_route_refuses_a_measured_evidence():
    with pytest.raises(InputError, match=r"^evidence: profile 'cpu' \(route scube\) does not use it"):
        Converter("cpu").convert(None, evidence=object())


@pytest.mark.parametrize("args", [["--no-sky"], ["--steps", "3"], ["--confidence", "4"], ["--fit-steps", "2"],
                                  ["--seed", "7"]])
def test_convert_refuses_a_paper_route_option_on_an_evidence_profile(tmp_path, args):
    out = tmp_path / "s.npz"
    r = CliRunner().invoke(app, ["convert", str(tmp_path / "no-such-sample"), "-o", str(out), "--profile", "evidence",
                                 *args])
    assert r.exit_code == 2, r.output
    lines = r.output.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"error: {args[0]}: profile 'evidence' is route evidence"), r.output
    assert not out.exists()
