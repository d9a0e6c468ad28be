"""The evidence-first route (`reconstruct.evidence`): a synthetic corridor (two textured walls, the road
and a box) seen by a camera driving through it, measured by stereo, fused and fitted, converts to
surfaces within one voxel of the truth, traces in `entry` mode at the right ranges, fills the
ground nobody saw, and gives the same bytes twice."""

from __future__ import annotations

import hashlib
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import pytest

from scube_sim.boxes import Box, points_in_boxes
from scube_sim.camera import Intrinsics
from scube_sim.camera.frames import CameraImage, Frames
from scube_sim.errors import InputError
from scube_sim.labels import LABEL_IDS
from scube_sim.raytrace.tracer import Tracer
from scube_sim.reconstruct.config import GROUND_LABEL, EvidenceConfig, FusionConfig, StereoConfig
from scube_sim.reconstruct.evidence import fuse_evidence, measure_evidence
from scube_sim.reconstruct.fusion import DepthObservation
from scube_sim.reconstruct.surfels import scene_from_evidence
from scube_sim.worlds.groundtruth import CHUNK_CORNER
from tests.reconstruct.stereo.test_mvs import _shot, _texture
from tests.reconstruct.stereo.test_sweep import _pose

W, H, F = 128, 96, 120.0
INTR = Intrinsics(W, H, F, F, W / 2, H / 2)
CAM_HEIGHT = 1.5
# world: x forward, y left, z up; boxes (lo, hi), each face textured by its two in-plane coordinates
BOXES = [
    (np.array([-20.0, -3.0, -0.5]), np.array([80.0, 3.0, 0.0])),  # the road
    (np.array([-20.0, 3.0, 0.0]), np.array([80.0, 3.3, 4.0])),  # the left wall, face y = 3
    (np.array([-20.0, -3.3, 0.0]), np.array([80.0, -3.0, 4.0])),  # the right wall, face y = -3
    (np.array([10.0, -1.5, 0.0]), np.array([13.0, 0.5, 1.5])),  # a box on the road
]
# camera axes (x right, y down, z forward) in the world
CAM_R = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
STEREO = StereoConfig(hypotheses=64, near_m=2.0, far_m=40.0, sources=4, scale=1.0)
CFG = EvidenceConfig(stereo=STEREO, fusion=FusionConfig(voxel_size=0.2))


def _cast(o: np.ndarray, d: np.ndarray):
    """Rays (N, 3) from o (3,) -> nearest hit distance (N,) and the hit's texture (N, 3)."""
    best = np.full(len(d), np.inf)
    rgb = np.full((len(d), 3), 0.5)
    with np.errstate(divide="ignore", invalid="ignore"):
        for b, (lo, hi) in enumerate(BOXES):
            t1, t2 = (lo - o) / d, (hi - o) / d
            tmin, tmax = np.minimum(t1, t2), np.maximum(t1, t2)
            enter = np.nanmax(tmin, 1)
            axis = np.nanargmax(tmin, 1)
            hit = (enter <= np.nanmin(tmax, 1)) & (enter > 0) & (enter < best)
            p = o + enter[:, None] * d
            uv = np.where(axis[:, None] == 0, p[:, [1, 2]], np.where(axis[:, None] == 1, p[:, [0, 2]], p[:, [0, 1]]))
            tex = _texture(uv[:, 0], uv[:, 1], 20 + b)
            best = np.where(hit, enter, best)
            rgb = np.where(hit[:, None], tex, rgb)
    return best, rgb


def _truth_distance(points: np.ndarray) -> np.ndarray:
    """(N, 3) -> (N,) the distance to the nearest box surface."""
    out = np.full(len(points), np.inf)
    for lo, hi in BOXES:
        q = np.maximum(lo - points, 0) + np.maximum(points - hi, 0)
        outside = np.linalg.norm(q, axis=1)
        inside = np.minimum(points - lo, hi - points).min(1)
        out = np.minimum(out, np.where(outside > 0, outside, inside))
    return out


def _image(x: float, t: float) -> CameraImage:
    pose = np.eye(4)
    pose[:3, :3] = CAM_R
    pose[:3, 3] = [x, 0.0, CAM_HEIGHT]
    rays = INTR.pixel_rays().reshape(-1, 3) @ CAM_R.T
    _, rgb = _cast(pose[:3, 3], rays)
    img = np.clip(np.round(rgb * 255), 0, 255).astype(np.uint8).reshape(H, W, 3)
    return CameraImage("FRONT", img, INTR, pose, t)


def evidence_scene(frames: Frames, to_chunk: np.ndarray, cfg: EvidenceConfig):
    """The route's scene without the converter: the evidence measured, then its surfels."""
    return scene_from_evidence(measure_evidence(frames, to_chunk, cfg), cfg)


def _frames() -> Frames:
    ctx = [Frames([_image(0.8 * k, 0.1 * k)], np.eye(4), 0.1 * k, offset=k) for k in (-2, -1, 1, 2)]
    return Frames([_image(0.0, 0.0)], np.eye(4), 0.0, context=ctx)


def _to_chunk() -> np.ndarray:
    return np.eye(4)  # the ego at the world origin, its road at z = 0: the chunk frame is the world


def _convert(update: dict | None = None):
    """The corridor through the converter, as `scube-sim convert --profile` runs it (a 30 m range:
    the voxels kept), with `update` to the evidence config."""
    from scube_sim.converter.pipeline import Converter
    from scube_sim.converter.profile import ConverterProfile

    cfg = CFG.model_copy(update=update or {})
    return Converter(ConverterProfile(name="corridor", route="evidence", evidence=cfg)).convert(_frames(),
                                                                                              max_range=30.0).scene


@pytest.fixture(scope="module")
def scene():
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(max(2, threads))  # several threads here, one in the determinism test's process
    try:
        return _convert()
    finally:
        torch.set_num_threads(threads)


def test_the_corridor_converts_to_surfaces_within_one_voxel(scene):
    observed = scene.channels["observed"].data
    centres = CHUNK_CORNER + (scene.ijk[observed] + 0.5) * scene.voxel_size
    dist = _truth_distance(centres)
    # a voxel holding a surface point has its centre within half a diagonal (0.17 m) of it; measured
    # median 0.10, p90 0.13, p95 0.20, p99 0.5 m: the rest are stereo's errors where its window
    # straddles the walls' tops against the empty sky (no depth edge to keep away from)
    q50, q90 = np.quantile(dist, [0.5, 0.9])
    assert q50 < 0.12 and q90 < 0.2, (q50, q90)
    near_left = np.abs(centres[:, 1] - 3.0) < 0.2
    near_right = np.abs(centres[:, 1] + 3.0) < 0.2
    on_box = (centres[:, 0] > 9.8) & (centres[:, 0] < 10.2) & (centres[:, 2] > 0.2)
    assert near_left.sum() > 100 and near_right.sum() > 100 and on_box.sum() > 10


def test_labels_and_the_ground_nobody_saw(scene):
    observed = scene.channels["observed"].data
    centres = CHUNK_CORNER + (scene.ijk + 0.5) * scene.voxel_size
    road = scene.labels == LABEL_IDS["road"]
    # the road z = 0 lies in the voxel layer [-0.03, 0.17) (the chunk's corner sits at z -3.23):
    # observed road voxels are that layer or a neighbour (stereo's few centimetres cross the
    # boundary 3 cm under the road); walls and the box are not road
    layer = (centres[:, 2] > -0.03) & (centres[:, 2] < 0.17)
    assert np.all(np.abs(centres[observed & road, 2] - 0.07) < 0.21) and layer[observed & road].mean() > 0.7
    walls = observed & ((np.abs(centres[:, 1] - 3.0) < 0.2) | (np.abs(centres[:, 1] + 3.0) < 0.2)) & (centres[:, 2] > 1.0)
    assert walls.sum() > 50 and not road[walls].any()
    # behind the camera nobody looked: the filled ground is there, unobserved, at z ~ 0
    behind = ~observed & (centres[:, 0] < -3.0) & (np.abs(centres[:, 1]) < 2.0)  # (the chunk starts 10 m back)
    assert behind.sum() > 100 and np.all(road[behind]) and np.all(layer[behind])
    # and so it is beyond the walls, 50 m out, where the corridor's plane is extrapolated (its roll,
    # fitted over a 6 m wide road, puts it up to 5 cm low there: the layer below)
    assert np.all(np.abs(centres[~observed, 2] - 0.07) < 0.21)
    conf = scene.channels["confidence"].data
    assert np.all(conf[~observed] == CFG.ground_confidence) and np.all(conf[observed] > 0.5)


def test_the_converted_corridor_traces_in_entry_mode_at_the_walls(scene):
    assert scene.metadata["trace_mode"] == "entry"
    tracer = Tracer(scene, mode="entry")
    # level rays from the camera towards the left wall, 8-16 m ahead
    x = np.array([8.0, 10.5, 13.0, 16.0])
    d = np.column_stack([x, np.full_like(x, 3.0), np.zeros_like(x)])
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    o = np.tile([0.0, 0.0, CAM_HEIGHT], (len(x), 1)) - CHUNK_CORNER
    hits = tracer.trace(o, d)
    expected, _ = _cast(np.array([0.0, 0.0, CAM_HEIGHT]), d)
    assert hits.hit.all()
    # grazing at 11-21 degrees: where each ray meets the converted wall lies within one voxel of
    # the true wall across it (measured: range errors -0.17, 0.17, -0.28, -0.83 m, i.e. 0.06,
    # 0.05, 0.06, 0.15 m across)
    across = np.abs(hits.t - expected) * np.sin(np.arctan(3.0 / x))
    assert np.all(across < 0.2), across


def test_road_points_snapped_onto_the_height_field_lie_on_it_and_the_walls_keep_theirs():
    """`ground_snap_m`: the observed road's points within it of the height field move onto the
    field, so the observed road's Gaussians lie on it (stereo left them centimetres about it), the
    field's samples filling under the snapped road beside them; the walls' surfels are the same
    bytes."""
    from scube_sim.reconstruct.evidence import measure_evidence
    from scube_sim.reconstruct.surfels import scene_from_evidence

    ev = measure_evidence(_frames(), _to_chunk(), CFG)
    raw = scene_from_evidence(ev, CFG)
    snapped = scene_from_evidence(ev, CFG.model_copy(update={"ground_snap_m": 0.15}))

    def road_gaussians(s):
        g = s.gaussians()
        keep = s.channels["observed"].data[g.voxel] & (s.labels[g.voxel] == LABEL_IDS["road"])
        p = g.means[keep] + s.origin
        return p, p[:, 2] - ev.field.height_at(p[:, :2])

    p_raw, dz_raw = road_gaussians(raw)
    p_snap, dz_snap = road_gaussians(snapped)
    # measured: within 5 mm of the field, 31 % of the 1027 raw Gaussians, 91 % of the 1370 snapped
    # (the rest lie in voxels that also hold road points left where they were, over 0.15 m off it)
    on_raw, on_snap = (np.abs(dz_raw) < 0.005).mean(), (np.abs(dz_snap) < 0.005).mean()
    assert on_raw < 0.5 and on_snap > 0.85 and len(p_snap) > len(p_raw), (on_raw, on_snap, len(p_raw), len(p_snap))
    assert np.median(np.abs(dz_snap)) < 1e-4 < np.median(np.abs(dz_raw))
    # the walls (no road label, over a metre up) keep their surfels
    def walls(s):
        c = CHUNK_CORNER + (s.ijk + 0.5) * s.voxel_size
        on = s.channels["observed"].data & (np.abs(np.abs(c[:, 1]) - 3.0) < 0.2) & (c[:, 2] > 1.0)
        return s.ijk[on], s.params[on]
    (ijk_a, par_a), (ijk_b, par_b) = walls(raw), walls(snapped)
    assert len(ijk_a) > 50
    np.testing.assert_array_equal(ijk_a, ijk_b)
    np.testing.assert_array_equal(par_a, par_b)
    assert (snapped.labels == LABEL_IDS["road"]).sum() >= (raw.labels == LABEL_IDS["road"]).sum()


def _digest(scene) -> str:
    """The sha256 of the file `scene` saves to (metadata and channels included)."""
    with tempfile.TemporaryDirectory() as tmp:
        return hashlib.sha256(scene.save(Path(tmp) / "s.npz").read_bytes()).hexdigest()


def converted_digest(update: dict | None = None) -> str:
    """The file the `scene` fixture's conversion (with `update`) saves to, hashed (run in another
    process below)."""
    return _digest(_convert(update))


def test_the_same_frames_give_the_same_bytes_in_another_process_with_one_thread(scene):
    # the fixture converted with at least two threads; the other process uses one
    code = ("import torch; torch.set_num_threads(1); "
            "from tests.reconstruct.test_evidence import converted_digest; print(converted_digest())")
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env,
                         cwd=Path(__file__).resolve().parents[2], check=True)
    assert out.stdout.strip().splitlines()[-1] == _digest(scene)


def test_a_bad_chunk_pose_is_refused():
    with pytest.raises(InputError, match="to_chunk"):
        evidence_scene(_frames(), np.eye(3), CFG)


def test_the_evidence_profile_converts_without_checkpoints(scene, tmp_path):
    from scube_sim.converter.pipeline import Converter
    from scube_sim.converter.profile import ConverterProfile, load_profile

    shipped = load_profile("evidence")
    assert shipped.route == "evidence" and shipped.context == 4 and shipped.geometry is None
    # the defaults but for stereo's gap filling (off in StereoConfig, 14 degrees in the profiles) and,
    # the weak pixels (in `evidence` and `evidence-fast`), T+3 as a third reference, thinner
    # surfels and runs up to 28 degrees filled where in line (in `evidence` alone), the road snapped
    # onto the height field and the surfels off the road widened (in `evidence` and `evidence-fast`;
    # `evidence-complete` keeps the evidence its checkpoint was trained on, today's `evidence`, and
    # with it the moving objects swept in their own frames and the boxed objects no camera saw
    # filled, both measured with that checkpoint on top)
    weak = EvidenceConfig(stereo={"fill_gap_deg": 28, "fill_coplanar": 0.5, "weak_agreement": 0.25, "movers": True},
                          fusion={"weak_confidence": 0.1, "weak_fit_weight": 0.1},
                          references=[0, -3, 3], max_normal_share=0.03, ground_snap_m=0.15, min_width_share=0.144,
                          fill_boxes=True)
    assert shipped.evidence == weak and EvidenceConfig().references == [0, -3]
    fast = load_profile("evidence-fast")  # T alone as the reference
    assert fast.route == "evidence" and fast.context == 4
    assert fast.evidence == EvidenceConfig(stereo={"fill_gap_deg": 14, "weak_agreement": 0.25},
                                           fusion={"weak_confidence": 0.1, "weak_fit_weight": 0.1}, references=[0],
                                           ground_snap_m=0.15, min_width_share=0.144)
    assert load_profile("evidence-complete").evidence == shipped.evidence  # what its checkpoint learnt from
    conv = Converter(ConverterProfile(name="corridor", route="evidence", evidence=CFG))
    assert scene.metadata["route"] == "evidence" and scene.metadata["trace_mode"] == "entry"
    assert scene.metadata["instants_used"].startswith("all")
    centres = CHUNK_CORNER[:2] + (scene.ijk[:, :2] + 0.5) * scene.voxel_size
    assert np.linalg.norm(centres, axis=1).max() <= 30.0 and scene.channels["observed"].data.any()
    assert conv.checkpoint_hashes() == {}
    bad = tmp_path / "bad.yaml"
    bad.write_text("route: evidence\ngeometry: {checkpoint: geometry-coarse-cpu, focal_px: 300}\n")
    with pytest.raises(InputError, match="(?s)bad.yaml.*no checkpoints"):
        load_profile(bad)
    bad.write_text("route: scube\n")
    with pytest.raises(InputError, match="(?s)bad.yaml.*needs geometry and appearance"):
        load_profile(bad)
    for refs in ("[]", "[0.5]", "three"):
        bad.write_text(f"route: evidence\nevidence: {{references: {refs}}}\n")
        with pytest.raises(InputError, match="(?s)bad.yaml.*references"):
            load_profile(bad)


def test_a_measured_evidence_converts_to_the_same_bytes_as_the_frames(scene):
    """`convert(frames, evidence=ev)` builds from the given measurement the scene `convert` builds
    (several completions compared on one measurement); a paper-route profile refuses one."""
    from scube_sim.camera.frames import chunk_to_world
    from scube_sim.converter.pipeline import Converter
    from scube_sim.converter.profile import ConverterProfile, load_profile
    from scube_sim.reconstruct.evidence import measure_evidence
    from scube_sim.transforms import invert_pose

    frames = _frames()
    ev = measure_evidence(frames, invert_pose(chunk_to_world(frames)), CFG)
    conv = Converter(ConverterProfile(name="corridor", route="evidence", evidence=CFG))
    done = conv.convert(frames, max_range=30.0, evidence=ev)
    again = done.scene
    assert done.timings["stereo_s"] == 0.0
    assert np.array_equal(again.ijk, scene.ijk) and np.array_equal(again.params, scene.params)
    assert again.metadata == scene.metadata
    with pytest.raises(InputError, match=r"evidence: profile 'cpu' \(route scube\) does not use it"):
        Converter(load_profile("cpu")).convert(frames, evidence=ev).scene


def test_an_earlier_instant_as_a_second_reference_adds_what_only_it_saw(scene):
    """references [0, -2] (instants -4..2): the camera 1.6 m back sees the walls from 4.0 m ahead
    of T's camera on (T's own view starts at 5.6 m: a 28 degree half-angle, the walls 3 m aside),
    matched against the instants behind it; those voxels come in, on the walls."""
    ctx = [Frames([_image(0.8 * k, 0.1 * k)], np.eye(4), 0.1 * k, offset=k) for k in (-4, -3, -2, -1, 1, 2)]
    frames = Frames([_image(0.0, 0.0)], np.eye(4), 0.0, context=ctx)
    one = evidence_scene(frames, _to_chunk(), CFG.model_copy(update={"references": [0]}))
    two = evidence_scene(frames, _to_chunk(), CFG.model_copy(update={"references": [0, -2]}))

    def walls_between(s, lo, hi):
        c = CHUNK_CORNER + (s.ijk[s.channels["observed"].data] + 0.5) * s.voxel_size
        on = (np.abs(np.abs(c[:, 1]) - 3.0) < 0.2) & (c[:, 0] > lo) & (c[:, 0] < hi) & (c[:, 2] > 0.3)
        return c[on]

    assert len(walls_between(one, 4.2, 5.4)) == 0
    extra = walls_between(two, 4.2, 5.4)
    assert len(extra) > 20 and np.median(_truth_distance(extra)) < 0.12
    assert len(walls_between(two, 8.0, 16.0)) >= 0.9 * len(walls_between(one, 8.0, 16.0))


def test_a_reference_instant_the_frames_lack_is_skipped(scene):
    other = _convert({"references": [0, -7]})  # its metadata records the references it was given
    np.testing.assert_array_equal(other.ijk, scene.ijk)
    assert other.params.tobytes() == scene.params.tobytes()


def test_with_nothing_measured_the_scene_is_the_road_under_the_ego():
    # one image, no other camera, no instant: no stereo; the ground is filled at the ego's road, z = 0
    alone = Frames([_image(0.0, 0.0)], np.eye(4), 0.0)
    s = evidence_scene(alone, _to_chunk(), CFG)
    assert not s.channels["observed"].data.any() and np.all(s.labels == LABEL_IDS["road"])
    assert s.metadata["ground_field"]["measured"] is False
    z = s.gaussians().means[:, 2] + s.origin[2]
    assert np.abs(z).max() < 1e-3
    with pytest.raises(InputError, match="nothing to fit"):
        evidence_scene(alone, _to_chunk(), CFG.model_copy(update={"fill_ground": False}))


def test_a_rig_that_looks_back_gets_a_chunk_centred_on_the_ego():
    """nuScenes' six cameras see behind the ego: the chunk (the same size) is centred, so the ground
    under what the rear camera saw is there; a forward rig keeps the paper's chunk ahead."""
    from dataclasses import replace

    from scube_sim.reconstruct.evidence import grid_corner
    from scube_sim.transforms import pose_from_xyz_rpy

    front = _image(0.0, 0.0)
    turned = pose_from_xyz_rpy([0, 0, 0], [0, 0, 180]) @ front.cam_to_world  # yawed to look back
    back = replace(front, name="BACK", cam_to_world=turned)
    np.testing.assert_array_equal(grid_corner(Frames([front], np.eye(4), 0.0), _to_chunk()), CHUNK_CORNER)
    both = Frames([front, back], np.eye(4), 0.0)
    np.testing.assert_allclose(grid_corner(both, _to_chunk()), [-51.2, -51.2, CHUNK_CORNER[2]])
    forward = evidence_scene(Frames([front], np.eye(4), 0.0), _to_chunk(), CFG)
    around = evidence_scene(both, _to_chunk(), CFG)
    for scene, lo in ((forward, CHUNK_CORNER[0]), (around, -51.2)):
        x = scene.gaussians().means[:, 0] + scene.origin[0]
        assert lo <= x.min() < lo + scene.voxel_size and x.max() < lo + 102.4


def test_the_command_line_defaults_are_the_converters():
    """convert, eval sensor-to-sensor, the demo and a batch convert default to `DEFAULT_PROFILE`
    (`converter.profile`, which imports no torch)."""
    import inspect

    from scube_sim.cli.convert import convert_cmd
    from scube_sim.cli.eval import eval_sensor_to_sensor_cmd
    from scube_sim.cli.runs import demo_cmd
    from scube_sim.converter.profile import DEFAULT_PROFILE
    from scube_sim.runs.demo import run_demo

    assert DEFAULT_PROFILE == "evidence-complete"
    for fn in (convert_cmd, eval_sensor_to_sensor_cmd, demo_cmd):
        assert inspect.signature(fn).parameters["profile"].default.default == DEFAULT_PROFILE, fn.__name__
    assert inspect.signature(run_demo).parameters["profile"].default == DEFAULT_PROFILE
    from scube_sim.runs.batch_jobs import ConvertSettings

    assert ConvertSettings().profile == DEFAULT_PROFILE and ConvertSettings().context is None  # the profile's
    from scube_sim.runs.scenario import FramesSpec

    assert FramesSpec.model_fields["profile"].default == DEFAULT_PROFILE  # a scenario's frames



def _sparse_wall(z_lo: float, label: int):
    """A wall in the plane x = 5.05 (y 0..2 m, z from `z_lo`, 1 m tall) measured only along one
    vertical texture edge per 0.2 m voxel (at its centre, y = 0.1 m + k 0.2 m), as stereo measures a
    plain door at its few edges: the fitted VoxSplat, all voxels observed and labelled `label`."""
    from scube_sim.fit import FitOptions, fit_voxsplat

    vs = 0.2
    y = (np.arange(10) + 0.5) * vs
    z = z_lo + (np.arange(60) + 0.5) * (1.0 / 60)
    yy, zz = np.meshgrid(y, z, indexing="ij")
    pts = np.column_stack([np.full(yy.size, 5.05), yy.ravel(), zz.ravel()])
    scene = fit_voxsplat(pts, vs, fit=FitOptions(gaussians_per_voxel=4, max_normal_scale=0.006))
    scene.labels[:] = label
    scene.set_channel("observed", np.ones(scene.num_voxels, bool))
    return scene


def _wall_hits(scene, z_lo: float, beside: float) -> np.ndarray:
    """Level rays from x = 0 along +x, `beside` metres to the side of each measured edge, at heights
    over the wall's face -> their ranges (inf: no hit)."""
    y, z = np.meshgrid((np.arange(10) + 0.5) * 0.2 + beside, np.linspace(z_lo + 0.05, z_lo + 0.95, 10), indexing="ij")
    o = np.column_stack([np.zeros(y.size), y.ravel(), z.ravel()])
    d = np.tile([1.0, 0.0, 0.0], (len(o), 1))
    hits = Tracer(scene, mode="entry").trace(o - scene.origin, d)
    return np.where(hits.hit, hits.t, np.inf)


def test_widened_surfels_close_a_sparsely_measured_wall_and_leave_the_road_and_its_rims_alone():
    """`widen_surfels` (`EvidenceConfig.min_width_share`): a wall measured along one edge per voxel
    lets a ray 6 cm beside the edges through; with each surfel at least 0.144 of the voxel wide
    (3 sigma: 8.6 cm to either side), it stops at the wall's plane, the surfels as flat as fitted.
    Surfels on the road, or lower than `above_m` over the ground field, keep their size."""
    from scube_sim.reconstruct.ground import flat_height_field
    from scube_sim.reconstruct.surfels import widen_surfels

    field = flat_height_field((-10.0, 10.0, -10.0, 10.0), z=0.0)
    wall = _sparse_wall(1.0, LABEL_IDS["undefined"])
    on_edge, beside = _wall_hits(wall, 1.0, 0.0), _wall_hits(wall, 1.0, 0.06)
    thickness = wall.scales()[..., 0].copy()
    assert np.isfinite(on_edge).all() and not np.isfinite(beside).any()
    n = widen_surfels(wall, field, 0.144, 0.3)
    assert n == wall.valid.sum() == 4 * 50
    beside = _wall_hits(wall, 1.0, 0.06)
    # flat surfels 6 mm thick: entered within 3 sigma (1.8 cm) of the plane
    assert np.isfinite(beside).all()
    np.testing.assert_allclose(beside, 5.05, atol=0.02)
    np.testing.assert_allclose(_wall_hits(wall, 1.0, 0.0), 5.05, atol=0.02)
    np.testing.assert_array_equal(wall.scales()[..., 0], thickness)
    # 10 cm beside them (half-way to the next edge): past the widened discs' 8.6 cm
    assert not np.isfinite(_wall_hits(wall, 1.0, 0.099)).any()
    # the same wall as road, or standing on the ground below 0.3 m: untouched
    for z_lo, label in ((1.0, LABEL_IDS["road"]), (-0.9, LABEL_IDS["undefined"])):
        other = _sparse_wall(z_lo, label)
        params = other.params.copy()
        assert widen_surfels(other, field, 0.144, 0.3) == 0
        np.testing.assert_array_equal(other.params, params)


def test_points_inside_a_moving_objects_box_neither_fit_the_ground_nor_take_its_label():
    # a camera looking up at a flat "ground" 10 m off (the stereo tests' plane, z up), and over its
    # middle a 6 x 5 m surface 0.9 m nearer, facing the same way: a car's hood, which the height
    # field's low quantile takes for the road unless the car's box keeps it out
    im, depth = _shot("cam", _pose(), 0.0)
    rays = im.intrinsics.pixel_rays()
    x, y = rays[..., 0] / rays[..., 2] * 9.1, rays[..., 1] / rays[..., 2] * 9.1
    hood = (np.abs(x) <= 3.0) & (np.abs(y) <= 2.5)
    depth = np.where(hood, np.float32(9.1), depth).astype(np.float32)
    obs = DepthObservation(im, depth, np.full(depth.shape, 0.9, np.float32))
    box = Box(np.array([0.0, 0.0, 9.1]), np.array([6.2, 5.2, 0.4]), np.eye(3))
    plain = fuse_evidence([obs], CHUNK_CORNER, np.eye(4))
    kept = fuse_evidence([obs], CHUNK_CORNER, np.eye(4), objects=(box,))
    centre = np.zeros((1, 2))
    assert plain.field.height_at(centre)[0] < 9.3  # the hood became the ground ...
    assert abs(kept.field.height_at(centre)[0] - 10.0) < 0.05  # ... unless its box keeps it out
    on_hood = points_in_boxes(kept.grid.points, [box]) >= 0
    assert on_hood.sum() > 100
    # 80 % of the hood's points were road (its rim's normals are undefined: not flat)
    assert (plain.labels[points_in_boxes(plain.grid.points, [box]) >= 0] == GROUND_LABEL).mean() > 0.7
    assert not (kept.labels[on_hood] == GROUND_LABEL).any()


def _wall_seen_ahead(uncarved: tuple = ()) -> DepthObservation:
    """The corridor's camera at (0, 0, 1.5) looking along +x, its every pixel confidently on a
    wall 30 m ahead (the plane x = 30)."""
    pose = np.eye(4)
    pose[:3, :3], pose[:3, 3] = CAM_R, [0.0, 0.0, CAM_HEIGHT]
    im = CameraImage("FRONT", np.zeros((H, W, 3), np.uint8), INTR, pose, 0.0)
    return DepthObservation(im, np.full((H, W), 30.0, np.float32), np.full((H, W), 0.9, np.float32), uncarved)


def _first_hit(scene, origin, direction) -> float:
    hits = Tracer(scene, mode="entry").trace(np.asarray([origin], np.float64) - scene.origin,
                                             np.asarray([direction], np.float64))
    return float(hits.t[0]) if hits.hit[0] else np.inf


def test_boxed_objects_no_camera_saw_are_filled_and_one_a_camera_saw_through_is_not():
    """`EvidenceConfig.fill_boxes`: a truck's box behind the camera becomes its box's faces, a car's
    its silhouette (body to 0.65 of the height, cabin on half the length, 0.12 of it back, 0.88 as
    wide), both unobserved and labelled; a box in front that the camera saw through to a wall stays
    empty unless the image's `uncarved` boxes hold it (it saw that space at another instant)."""
    from scube_sim.reconstruct.surfels import scene_from_evidence

    truck = Box(np.array([-6.0, 0.0, 1.0]), np.array([2.0, 2.0, 2.0]), np.eye(3), label=LABEL_IDS["truck"])
    car = Box(np.array([-6.0, 6.0, 0.8]), np.array([4.5, 1.8, 1.6]), np.eye(3), label=LABEL_IDS["car"])
    ahead = Box(np.array([15.0, 0.0, 1.5]), np.array([2.0, 2.0, 2.0]), np.eye(3), label=LABEL_IDS["truck"])
    # no ground under them (`fill_ground` off): the rays meet the boxes and the wall only
    cfg = CFG.model_copy(update={"fill_boxes": True, "fill_ground": False})
    boxes = (truck, car, ahead)
    scene = scene_from_evidence(fuse_evidence([_wall_seen_ahead()], CHUNK_CORNER, np.eye(4), cfg, boxes=boxes), cfg)
    # flat surfels (6 mm thick at most) entered within 3 sigma of the face
    assert abs(_first_hit(scene, [0.0, 0.0, 1.0], [-1.0, 0.0, 0.0]) - 5.0) < 0.05  # the truck's face x = -5
    assert abs(_first_hit(scene, [0.0, 0.0, 1.5], [1.0, 0.0, 0.0]) - 30.0) < 0.05  # through the box ahead
    cabin_x, cabin_side = -6.0 - 0.12 * 4.5, 6.0 - 0.9 * 0.88
    # level rays towards the car from y = 2 (beside the truck)
    assert abs(_first_hit(scene, [cabin_x, 2.0, 1.3], [0.0, 1.0, 0.0]) - (cabin_side - 2.0)) < 0.05
    assert abs(_first_hit(scene, [-4.2, 2.0, 0.6], [0.0, 1.0, 0.0]) - 3.1) < 0.05  # the body's side
    assert _first_hit(scene, [-4.2, 2.0, 1.3], [0.0, 1.0, 0.0]) == np.inf  # over the hood
    assert _first_hit(scene, [-6.0, 6.0, 3.0], [0.0, 0.0, -1.0]) == pytest.approx(1.4, abs=0.05)  # the roof
    filled = ~scene.channel("observed")
    assert {LABEL_IDS["truck"], LABEL_IDS["car"]} <= set(np.unique(scene.labels[filled]).tolist())
    np.testing.assert_allclose(scene.channel("confidence")[filled], cfg.ground_confidence)
    # the same image taken at another instant, where the box ahead stands now
    moved = fuse_evidence([_wall_seen_ahead(uncarved=(ahead,))], CHUNK_CORNER, np.eye(4), cfg, boxes=boxes)
    assert abs(_first_hit(scene_from_evidence(moved, cfg), [0.0, 0.0, 1.5], [1.0, 0.0, 0.0]) - 14.0) < 0.05
    # off (the default): the boxes change nothing
    plain = cfg.model_copy(update={"fill_boxes": False})
    off = scene_from_evidence(fuse_evidence([_wall_seen_ahead()], CHUNK_CORNER, np.eye(4), plain, boxes=boxes), plain)
    assert _first_hit(off, [0.0, 0.0, 1.0], [-1.0, 0.0, 0.0]) == np.inf
    assert off.metadata["box_samples"] == 0 < scene.metadata["box_samples"]


def test_measured_evidence_keeps_the_frames_boxes_in_the_chunk_frame_with_their_labels():
    from scube_sim.reconstruct.evidence import measure_evidence

    frames = _frames()
    frames.boxes = [Box(np.array([-6.0, 0.0, 1.0]), np.array([2.0, 2.0, 2.0]), np.eye(3), label=LABEL_IDS["truck"],
                        instance=7)]
    to_chunk = np.eye(4)
    to_chunk[:3, 3] = [1.0, -2.0, 0.0]
    ev = measure_evidence(frames, to_chunk, CFG)
    (box,) = ev.boxes
    np.testing.assert_allclose(box.center, [-5.0, -2.0, 1.0])
    np.testing.assert_allclose(box.size, [2.0, 2.0, 2.0])
    assert (box.label, box.instance) == (LABEL_IDS["truck"], 7)
