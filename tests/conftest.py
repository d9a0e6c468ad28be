"""Shared fixtures. Third-party data stays in ../shared/data (override: SCUBE_SIM_SHARED_DATA)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, settings

REPO = Path(__file__).resolve().parents[1]

settings.register_profile(
    "ci", max_examples=60, deadline=None, derandomize=True,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)
settings.load_profile("ci")


def shared_data_dir() -> Path:
    env = os.environ.get("SCUBE_SIM_SHARED_DATA")
    return Path(env) if env else REPO.parent / "shared" / "data"


@pytest.fixture(scope="session", autouse=True)
def _private_cache(tmp_path_factory):
    """The user cache (estimated poses, `datasets.odometry`) in a folder of the test session, so a
    test run neither reads nor fills the user's own."""
    import os

    before = os.environ.get("SCUBE_SIM_CACHE")
    os.environ["SCUBE_SIM_CACHE"] = str(tmp_path_factory.mktemp("user-cache"))
    yield
    if before is None:
        os.environ.pop("SCUBE_SIM_CACHE", None)
    else:
        os.environ["SCUBE_SIM_CACHE"] = before


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """../shared/data, or skip the test with the reason."""
    d = shared_data_dir()
    if not d.is_dir():
        pytest.skip(f"third-party data folder {d} is absent (set SCUBE_SIM_SHARED_DATA)")
    return d


def require(path: Path) -> Path:
    """Skip the calling test if a third-party file is absent."""
    if not path.exists():
        pytest.skip(f"third-party file {path} is absent")
    return path


@pytest.fixture(scope="session")
def tiny_converter(tmp_path_factory) -> dict:
    """A tiny worlds dataset and a converter profile of two few-step stages, built once per session
    (tests/converter/tiny_converter.py): {"data", "profile", "geo", "app", "sample"}."""
    from .converter.tiny_converter import build

    return build(tmp_path_factory.mktemp("converter"))


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(1234)


def look_at(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """OpenCV camera (x right, y down, z forward) -> world pose looking from eye at target."""
    eye, target = np.asarray(eye, float), np.asarray(target, float)
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    t = np.eye(4)
    t[:3, :3] = np.column_stack([x, y, z])
    t[:3, 3] = eye
    return t


def one_line_error(res, *needles) -> str:
    """The line of a CLI result that failed with exit code 2 and printed one `error: ...` line (no
    traceback) containing `needles`."""
    assert res.exit_code == 2, res.output
    lines = [ln for ln in res.output.strip().splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: "), res.output
    for n in needles:
        assert n in lines[0], lines[0]
    return lines[0]
