"""Source-view selection (`reconstruct.stereo.views`): candidates over cameras and instants, refusals (no
baseline, looking away, fisheye, no overlap), the parallax-per-hypothesis score, deterministic order."""

from __future__ import annotations

import numpy as np

from scube_sim.camera import Intrinsics
from scube_sim.camera.frames import CameraImage, Frames
from scube_sim.reconstruct.stereo import candidates, select_sources

W, H, F = 128, 96, 120.0
INTR = Intrinsics(W, H, F, F, W / 2, H / 2)
STEP = 1.0 / (120.0 * 1.0)  # 1/m per hypothesis: a 1 m sideways baseline moves one pixel per step


def _im(name: str, centre=(0.0, 0.0, 0.0), yaw_deg: float = 0.0, intr: Intrinsics = INTR) -> CameraImage:
    t = np.eye(4)
    a = np.deg2rad(yaw_deg)
    t[:3, :3] = [[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]]
    t[:3, 3] = centre
    return CameraImage(name, np.zeros((intr.height, intr.width, 3), np.uint8), intr, t, 0.0)


def test_candidates_are_the_other_cameras_and_every_context_camera():
    ref, side = _im("FRONT"), _im("LEFT", (-0.5, 0, 0))
    ctx = [Frames([_im("FRONT", (0, 0, -1.0)), _im("LEFT", (-0.5, 0, -1.0))], np.eye(4), -0.1, offset=-1)]
    frames = Frames([ref, side], np.eye(4), 0.0, context=ctx)
    assert [(o, im.name) for o, im in candidates(frames, 0)] == [(0, "LEFT"), (-1, "FRONT"), (-1, "LEFT")]


def test_refusals_and_the_preferred_baseline():
    ref = _im("ref")
    cands = [(1, _im("same")), (2, _im("tiny", (0.01, 0, 0))), (3, _im("away", (1.0, 0, 0), 180.0)),
             (4, _im("fish", (1.0, 0, 0), intr=Intrinsics(W, H, F, F, W / 2, H / 2, "fisheye"))),
             (5, _im("far_off", (500.0, 0, 0))), (6, _im("good", (1.0, 0, 0))), (7, _im("long", (8.0, 0, 0))),
             (8, _im("short", (0.15, 0, 0)))]
    views = select_sources(ref, cands, 10, STEP)
    names = [v.image.name for v in views]
    assert names[0] == "good"  # one pixel per hypothesis step
    assert set(names) == {"good", "long", "short"}  # no baseline, looking away, fisheye, no overlap: refused
    v = views[0]
    np.testing.assert_allclose(v.ref_to_src[:3, 3], [-1.0, 0, 0])
    assert v.baseline_m == 1.0 and 0 < v.score <= 1 and v.overlap > 0.5


def test_the_preferred_step_picks_the_baseline():
    # pixels per hypothesis step scale with the baseline: 1 m gives 1 px, 2 m 2 px, 0.5 m 0.5 px
    ref = _im("ref")
    cands = [(1, _im("half", (0.5, 0, 0))), (2, _im("one", (1.0, 0, 0))), (3, _im("two", (2.0, 0, 0)))]
    for step_px, best in ((0.5, "half"), (1.0, "one"), (2.0, "two")):
        assert select_sources(ref, cands, 1, STEP, good_step_px=step_px)[0].image.name == best


def test_ties_are_broken_by_offset_then_name():
    ref = _im("ref")
    cands = [(2, _im("b", (1.0, 0, 0))), (-2, _im("b", (1.0, 0, 0))), (2, _im("a", (1.0, 0, 0))),
             (1, _im("c", (-1.0, 0, 0)))]
    views = select_sources(ref, cands, 3, STEP)
    assert [(v.offset, v.image.name) for v in views] == [(1, "c"), (-2, "b"), (2, "a")]
