"""`generate_world` against expectations computed here: array equality for determinism, oriented
box and separating-axis tests written below, finite differences of the tracks, vertical rays cast
on the static mesh, and the ground heights the generator promises (road 0, sidewalk and median
0.15, terrain 0.10) looked up with the layout's own classifier only to pick test points."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from scube_sim.boxes import Box
from scube_sim.labels import label_id
from scube_sim.lidar.config import ConfigError
from scube_sim.raytrace.tracer import Tracer
from scube_sim.worlds.generator import STYLES, WorldConfig, generate_world

REPO = Path(__file__).resolve().parents[2]
SCENARIOS = sorted((REPO / "scenarios").glob("*.yaml"))

ROAD, SIDEWALK, BUILDING = label_id("road"), label_id("sidewalk"), label_id("building")
CAR, TRUCK, PED = label_id("car"), label_id("truck"), label_id("pedestrian")
VEG, FENCE = label_id("vegetation"), label_id("fence")
VEHICLES = (CAR, TRUCK)

# Chunk extent in the ego frame at T (documented in groundtruth: x -10.24..92.16, y +-51.2).
CHUNK_LO, CHUNK_HI = np.array([-10.24, -51.2]), np.array([92.16, 51.2])


@pytest.fixture(scope="module")
def worlds():
    """One world per style (seed 0; 'auto' layout)."""
    return {s: generate_world(WorldConfig(style=s, seed=0)) for s in STYLES}


# --- helpers written for the tests -----------------------------------------------------------------


def convex_hull_2d(p: np.ndarray) -> np.ndarray:
    """Counter-clockwise convex hull (Andrew's monotone chain) of 2D points."""
    pts = sorted(set(map(tuple, np.round(p, 9))))
    if len(pts) <= 2:
        return np.array(pts)

    def cross(o, a, b):
        return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])

    lower, upper = [], []
    for q in pts:
        while len(lower) >= 2 and cross(lower[-2], lower[-1], q) <= 0:
            lower.pop()
        lower.append(q)
    for q in reversed(pts):
        while len(upper) >= 2 and cross(upper[-2], upper[-1], q) <= 0:
            upper.pop()
        upper.append(q)
    return np.array(lower[:-1] + upper[:-1])


def polygons_overlap(p: np.ndarray, q: np.ndarray, tol: float = 1e-6) -> bool:
    """Separating-axis test for two convex polygons: True if their interiors overlap by more than tol."""
    for poly in (p, q):
        e = np.roll(poly, -1, axis=0) - poly
        for n in np.stack([-e[:, 1], e[:, 0]], 1):
            ln = np.linalg.norm(n)
            if ln < 1e-12:
                continue
            a, b = p @ (n / ln), q @ (n / ln)
            if a.max() <= b.min() + tol or b.max() <= a.min() + tol:
                return False
    return True


def box_rect(box: Box) -> np.ndarray:
    """(4, 2) footprint corners of an upright box (center, size, yaw)."""
    c, s = np.cos(box.yaw), np.sin(box.yaw)
    half = box.size[:2] / 2
    local = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]]) * half
    return local @ np.array([[c, -s], [s, c]]).T + box.center[:2]


def in_box(points: np.ndarray, box: Box, tol: float) -> np.ndarray:
    """Points inside an upright oriented box (rotation about z by yaw), with a tolerance."""
    c, s = np.cos(box.yaw), np.sin(box.yaw)
    d = points - box.center
    local = np.c_[c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1], d[:, 2]]
    return np.all(np.abs(local) <= box.size / 2 + tol, axis=1)


def building_footprints(world) -> dict[int, np.ndarray]:
    """Per building instance: the corners of its ground-level outline (hull of its lowest vertices)."""
    m = world.static
    out = {}
    is_b = m.labels == BUILDING
    for inst in np.unique(m.instances[is_b]):
        v = m.vertices[np.unique(m.faces[is_b & (m.instances == inst)])]
        low = v[v[:, 2] < v[:, 2].min() + 1e-6]
        out[int(inst)] = convex_hull_2d(low[:, :2])
    return out


def building_hulls(world) -> dict[int, np.ndarray]:
    """Per building instance: hull of every vertex in plan view (canopies and balconies included)."""
    m = world.static
    is_b = m.labels == BUILDING
    return {int(i): convex_hull_2d(m.vertices[np.unique(m.faces[is_b & (m.instances == i)])][:, :2])
            for i in np.unique(m.instances[is_b])}


def chunk_grid(world, spacing: float, z: float = 200.0) -> np.ndarray:
    """World-frame ray origins on a grid over the chunk (the ego frame at T), offset off the 0.25 m
    ground lattice so no ray runs exactly along a mesh edge."""
    xs = np.arange(CHUNK_LO[0], CHUNK_HI[0], spacing) + 0.0113
    ys = np.arange(CHUNK_LO[1], CHUNK_HI[1], spacing) + 0.0071
    gx, gy = np.meshgrid(xs, ys, indexing="ij")
    local = np.c_[gx.ravel(), gy.ravel(), np.zeros(gx.size)]
    ego = world.ego_pose_at(0.0)
    o = local @ ego[:3, :3].T + ego[:3, 3]
    o[:, 2] = z
    return o


def cast_down(world, origins):
    tr = Tracer(world.static)
    return tr.trace_world(origins, np.tile([0.0, 0.0, -1.0], (len(origins), 1)))


def distance_to_polygon_edges(p: np.ndarray, poly: np.ndarray) -> np.ndarray:
    a, b = poly, np.roll(poly, -1, axis=0)
    d = np.full(len(p), np.inf)
    for ai, bi in zip(a, b):
        ab = bi - ai
        t = np.clip((p - ai) @ ab / (ab @ ab), 0, 1)
        d = np.minimum(d, np.linalg.norm(ai + t[:, None] * ab - p, axis=1))
    return d


# --- determinism ---------------------------------------------------------------------------------


def _world_arrays(w) -> dict[str, np.ndarray]:
    out = {"static_v": w.static.vertices, "static_f": w.static.faces, "static_l": w.static.labels,
           "static_i": w.static.instances, "static_c": w.static.colors, "ego_t": w.ego_times,
           "ego_p": w.ego_poses, "sun": w.sun_dir}
    for k, a in enumerate(w.actors):
        out.update({f"a{k}_t": a.times, f"a{k}_p": a.poses, f"a{k}_v": a.mesh.vertices, f"a{k}_f": a.mesh.faces,
                    f"a{k}_s": a.size, f"a{k}_id": np.array([a.instance, a.label])})
    for k, b in enumerate(w.boxes_static):
        out.update({f"b{k}_{key}": np.atleast_1d(np.asarray(getattr(b, key)))
                    for key in ("center", "size", "rotation", "label", "instance")})
    for k, r in enumerate(w.layout.roads):
        out[f"road{k}"] = r.centerline
    return out


def test_same_config_gives_identical_worlds():
    cfg = WorldConfig(style="suburban", seed=3)
    a, b = _world_arrays(generate_world(cfg)), _world_arrays(generate_world(cfg.model_copy()))
    assert a.keys() == b.keys()
    for k in a:
        assert a[k].dtype == b[k].dtype and np.array_equal(a[k], b[k]), k


def test_different_seeds_give_different_worlds():
    a = generate_world(WorldConfig(style="suburban", seed=3))
    b = generate_world(WorldConfig(style="suburban", seed=4))
    same_shape = a.static.vertices.shape == b.static.vertices.shape
    assert not (same_shape and np.array_equal(a.static.vertices, b.static.vertices))
    assert not np.array_equal(a.sun_dir, b.sun_dir)


# --- content per style -----------------------------------------------------------------------------


@pytest.mark.parametrize("style", STYLES)
def test_style_has_road_sidewalk_building_and_cars(worlds, style):
    labels = set(worlds[style].mesh_at(0.0).labels.tolist())
    for name, lab in (("road", ROAD), ("sidewalk", SIDEWALK), ("building", BUILDING), ("car", CAR)):
        assert lab in labels, f"{style}: no {name} faces"


def test_boulevard_median_has_vegetation(worlds):
    w = worlds["boulevard"]
    assert w.layout.main.median > 0
    m = w.static
    veg = m.labels == VEG
    centroids = m.vertices[m.faces[veg]].mean(axis=1)
    cls, _ = w.layout.classify(centroids[:, :2])
    on_median = cls == 3
    # Several distinct plants stand on the median, not just one stray face.
    assert len(np.unique(m.instances[veg][on_median])) >= 3


def test_suburban_has_fences_or_hedges(worlds):
    m = worlds["suburban"].static
    fence = np.any(m.labels == FENCE)
    # A hedge is a vegetation box: an instance of exactly 12 vegetation faces, all axis-like planar
    # (each face normal is horizontal or vertical); trees and bushes are icospheres.
    hedges = 0
    veg = m.labels == VEG
    normals = m.face_normals()
    for inst in np.unique(m.instances[veg]):
        sel = veg & (m.instances == inst)
        n = normals[sel]
        if sel.sum() == 12 and np.all((np.abs(n[:, 2]) > 0.999) | (np.abs(n[:, 2]) < 1e-9)):
            hedges += 1
    assert fence or hedges > 0


# --- actors and boxes ------------------------------------------------------------------------------


@pytest.mark.parametrize("style", STYLES)
def test_tracks_are_sampled_at_10_hz(worlds, style):
    w = worlds[style]
    assert len(w.actors) > 0
    for a in [*w.actors, None]:
        t = w.ego_times if a is None else a.times
        assert t[0] == 0.0
        np.testing.assert_allclose(t * 10, np.round(t * 10), atol=1e-9)
        np.testing.assert_allclose(np.diff(t), 0.1, atol=1e-9)
        assert t[-1] == pytest.approx(w.config.duration_s, abs=1e-9)
        poses = w.ego_poses if a is None else a.poses
        assert poses.shape == (len(t), 4, 4)


@pytest.mark.parametrize("style", STYLES)
@pytest.mark.parametrize("t", [0.0, 0.05, 0.73, 2.0])
def test_posed_actor_vertices_lie_in_their_boxes(worlds, style, t):
    w = worlds[style]
    boxes = {b.instance: b for b in w.boxes_at(t)}
    for a, m in zip(w.actors, w.actor_meshes_at(t)):
        box = boxes[a.instance]
        assert isinstance(box, Box) and box.label == a.label
        inside = in_box(m.vertices + m.origin, box, tol=1e-6)
        assert inside.all(), f"actor {a.instance}: {np.sum(~inside)} vertices outside its box at t={t}"
        # The box is tight: the mesh reaches its top and both ends (not a loose over-estimate).
        z = m.vertices[:, 2] + m.origin[2]
        assert z.max() == pytest.approx(box.center[2] + box.size[2] / 2, abs=1e-6)


@pytest.mark.parametrize("style", STYLES)
def test_parked_vehicle_boxes_contain_their_meshes(worlds, style):
    w = worlds[style]
    m = w.static
    assert len(w.boxes_static) > 0
    for b in w.boxes_static:
        assert isinstance(b, Box)
        sel = m.instances == b.instance
        assert sel.any(), f"no faces for parked vehicle {b.instance}"
        assert np.all(m.labels[sel] == b.label) and b.label in VEHICLES
        v = m.vertices[np.unique(m.faces[sel])] + m.origin
        assert in_box(v, b, tol=1e-6).all()
        # resting on the road (wheels are 10-sided prisms: the lowest vertex is a little above 0)
        assert 0.0 <= v[:, 2].min() < 0.03


@pytest.mark.parametrize("style", STYLES)
def test_moving_vehicles_drive_forward_at_plausible_speeds(worlds, style):
    w = worlds[style]
    for a in w.actors:
        p = a.poses[:, :3, 3]
        vel = np.diff(p, axis=0) / np.diff(a.times)[:, None]
        speed = np.linalg.norm(vel, axis=1)
        if a.label in VEHICLES:
            assert np.all(speed > 1.0) and np.all(speed < 20.0), (a.instance, speed)
            # it moves along its own x axis (forward), not sideways or backwards
            fwd = a.poses[:-1, :3, 0]
            cosang = np.einsum("ij,ij->i", vel / speed[:, None], fwd)
            assert np.all(cosang > 0.99), (a.instance, cosang)
        else:
            assert a.label == PED
            assert np.all(speed < 3.0)
        # upright: z axis up, no roll or pitch
        np.testing.assert_allclose(a.poses[:, :3, 2], np.tile([0, 0, 1.0], (len(a.times), 1)), atol=1e-9)


@pytest.mark.parametrize("style", STYLES)
def test_ego_starts_at_origin_heading_x_and_stays_on_the_road(worlds, style):
    w = worlds[style]
    p0 = w.ego_poses[0]
    assert p0[0, 3] == pytest.approx(0.0, abs=0.05)
    heading = np.arctan2(p0[1, 0], p0[0, 0])
    assert abs(heading) < 0.05
    assert w.ego_pose_at(0.0)[0, 3] == pytest.approx(p0[0, 3])
    xy = w.ego_poses[:, :2, 3]
    cls, edge = w.layout.classify(xy)
    assert np.all(cls == 1), cls
    # the ego's lane: right of the centreline (right-hand traffic), inside the carriageway
    assert np.all(edge < -0.5)
    speed = np.linalg.norm(np.diff(xy, axis=0), axis=1) / 0.1
    assert np.all((speed > 1.0) & (speed < 20.0))


@pytest.mark.parametrize("layout", ["curved", "straight"])
def test_ego_follows_its_lane_for_longer_drives(layout):
    w = generate_world(WorldConfig(style="suburban", seed=8, layout=layout, duration_s=5.0, ego_speed_mps=12.0))
    cls, _ = w.layout.classify(w.ego_poses[:, :2, 3])
    assert np.all(cls == 1)
    # signed side of the centreline, computed here from the nearest centreline vertex's segment
    line = w.layout.main.centerline
    for p in w.ego_poses[:, :2, 3]:
        k = int(np.argmin(np.linalg.norm(line - p, axis=1)))
        k = min(k, len(line) - 2)
        ab, ap = line[k + 1] - line[k], p - line[k]
        assert ab[0] * ap[1] - ab[1] * ap[0] < 0  # right of travel
    speed = np.linalg.norm(np.diff(w.ego_poses[:, :3, 3], axis=0), axis=1) / 0.1
    # ego_speed_mps is the centreline speed; the lane 1.6-1.9 m inside a >= 70 m radius is a few % slower
    np.testing.assert_allclose(speed, 12.0, rtol=0.05)


# --- buildings -------------------------------------------------------------------------------------


@pytest.mark.parametrize("style", STYLES)
def test_buildings_do_not_overlap(worlds, style):
    fps = building_footprints(worlds[style])
    assert len(fps) >= 4
    ids = list(fps)
    for i, a in enumerate(ids):
        assert len(fps[a]) == 4, f"building {a}: footprint is not a rectangle"
        for b in ids[i + 1:]:
            assert not polygons_overlap(fps[a], fps[b]), f"buildings {a} and {b} overlap"


@pytest.mark.parametrize("style", STYLES)
def test_no_building_part_enters_another_building(worlds, style):
    """Canopies and balconies stick out of the facade; they must not reach into a neighbour."""
    fps, hulls = building_footprints(worlds[style]), building_hulls(worlds[style])
    for a in hulls:
        for b in fps:
            if a != b:
                assert not polygons_overlap(hulls[a], fps[b]), f"building {a} reaches into building {b}"


@pytest.mark.parametrize("style", STYLES)
def test_vehicle_boxes_clear_of_buildings(worlds, style):
    w = worlds[style]
    fps = list(building_footprints(w).values())
    for t in (0.0, 1.0, 2.0):
        for box in w.boxes_at(t):
            rect = box_rect(box)
            for fp in fps:
                assert not polygons_overlap(rect, fp), f"box {box.instance} at t={t} hits a building"


# --- ground --------------------------------------------------------------------------------------


@pytest.mark.parametrize("style,layout", [("urban", "x_junction"), ("suburban", "curved"),
                                          ("intersection", "x_junction"), ("boulevard", "straight")])
def test_ground_has_no_holes_away_from_buildings(style, layout):
    w = generate_world(WorldConfig(style=style, seed=1, layout=layout))
    o = chunk_grid(w, 0.31)
    # keep rays at least 0.3 m from every building outline (the walls themselves: see the test below)
    near = np.zeros(len(o), bool)
    for fp in building_footprints(w).values():
        near |= distance_to_polygon_edges(o[:, :2], fp) < 0.3
    h = cast_down(w, o[~near])
    assert h.hit.all(), f"{np.sum(~h.hit)} of {h.hit.size} vertical rays miss: holes, first at {o[~near][~h.hit][:3]}"


def test_t_junction_ground_covers_the_chunk():
    w = generate_world(WorldConfig(style="urban", seed=1, layout="t_junction"))
    o = chunk_grid(w, 0.5)
    o = o[min_wall_distance(w, o[:, :2]) >= 0.3]  # the slivers by the walls are another matter
    h = cast_down(w, o)
    assert h.hit.all(), (f"{np.sum(~h.hit)} of {h.hit.size} vertical rays miss, all at x >= "
                         f"{o[~h.hit, 0].min():.2f} m (junction at x = {w.layout.junction[0]:.2f} m)")


@pytest.mark.parametrize("style,layout", [("urban", "straight"), ("suburban", "straight")])
def test_ground_meets_building_walls_without_gaps(style, layout):
    w = generate_world(WorldConfig(style=style, seed=0, layout=layout))
    o = chunk_grid(w, 0.173)
    h = cast_down(w, o)
    miss = o[~h.hit, :2]
    assert h.hit.all(), (f"{len(miss)} of {h.hit.size} rays miss; distance of the misses to the nearest "
                         f"building wall: max {min_wall_distance(w, miss).max():.3f} m")


def min_wall_distance(w, p):
    d = np.full(len(p), np.inf)
    for fp in building_footprints(w).values():
        d = np.minimum(d, distance_to_polygon_edges(p, fp))
    return d


@pytest.mark.parametrize("style", STYLES)
def test_ground_height_per_class(worlds, style):
    """Road at z = 0 (lane paint 5 mm above), sidewalk and median 0.15 m, terrain 0.10 m, at points
    whose class is the same on a 0.5 m circle around them (away from curbs)."""
    w = worlds[style]
    o = chunk_grid(w, 0.7)
    xy = o[:, :2]
    cls, _ = w.layout.classify(xy)
    stable = np.ones(len(xy), bool)
    for r in (0.25, 0.5):
        for ang in np.linspace(0, 2 * np.pi, 12, endpoint=False):
            c2, _ = w.layout.classify(xy + r * np.array([np.cos(ang), np.sin(ang)]))
            stable &= c2 == cls
    h = cast_down(w, o)
    ground = stable & h.hit & (h.instance == 0)  # instance 0: the static ground (not objects on it)
    z = h.points[:, 2] + w.static.origin[2]
    expect = {1: (0.0, 0.0051), 2: (0.15, 0.15), 3: (0.15, 0.15), 0: (0.10, 0.10)}
    for c, (lo, hi) in expect.items():
        sel = ground & (cls == c)
        if c in (1, 2):
            assert sel.sum() > 100, f"class {c}: too few test points"
        if sel.any():
            assert np.all((z[sel] >= lo - 1e-6) & (z[sel] <= hi + 1e-6)), (
                f"class {c}: z in [{z[sel].min():.4f}, {z[sel].max():.4f}], expected [{lo}, {hi}]")
    # and the road surface really is hit as road
    road_hits = ground & (cls == 1) & (z < 0.001)
    assert np.all(h.label[road_hits] == ROAD)


# --- scenario files --------------------------------------------------------------------------------


@pytest.mark.parametrize("path", SCENARIOS, ids=lambda p: p.stem)
def test_scenarios_load(path):
    import yaml

    cfg = WorldConfig.from_yaml(path)
    data = yaml.safe_load(path.read_text())
    scene = data.get("scene", {})
    raw = scene["world"] if "world" in scene else scene["frames"]["world"] if "frames" in scene else data["world"]
    for key, value in raw.items():
        assert getattr(cfg, key) == value
    assert cfg.style in STYLES


def test_scenarios_exist():
    assert len(SCENARIOS) >= 4


def test_world_only_yaml_file(tmp_path):
    p = tmp_path / "w.yaml"
    p.write_text("style: boulevard\nseed: 12\n")
    cfg = WorldConfig.from_yaml(p)
    assert (cfg.style, cfg.seed) == ("boulevard", 12)


def test_bad_key_names_file_and_key(tmp_path):
    p = tmp_path / "bad.yaml"
    p.write_text("name: x\nworld:\n  style: urban\n  sed: 3\n")
    with pytest.raises(ConfigError) as e:
        WorldConfig.from_yaml(p)
    msg = str(e.value)
    assert str(p) in msg and "sed" in msg


def test_bad_value_names_file_and_key(tmp_path):
    p = tmp_path / "bad.yaml"
    p.write_text("world:\n  style: rural\n")
    with pytest.raises(ConfigError) as e:
        WorldConfig.from_yaml(p)
    assert str(p) in str(e.value) and "style" in str(e.value)
