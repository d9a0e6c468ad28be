"""Ground-truth products against expectations built here: an independent random surface sampler,
an exact triangle-box separating-axis test, voxel sets of boxes counted by hand, brute-force
coarsening and majority labels, analytic planes, and occlusion set up so the answer is known."""

from __future__ import annotations

from collections import defaultdict

import numpy as np
import pytest

from scube_sim.camera.model import Intrinsics
from scube_sim.camera.render import render_camera
from scube_sim.camera.rig import load_rig
from scube_sim.labels import label_id
from scube_sim.mesh import TriangleMesh
from scube_sim.raytrace.tracer import Tracer
from scube_sim.transforms import invert_pose, make_pose, transform_points
from scube_sim.worlds import primitives as pr
from scube_sim.worlds.generator import WorldConfig, generate_world
from scube_sim.worlds.groundtruth import (
    CHUNK_CORNER,
    CHUNK_SIZE,
    VoxelGrid,
    chunk_samples,
    coarsen,
    depth_to_points,
    gt_voxsplat,
    mark_visible,
    voxelize,
    voxelize_mesh,
)
from scube_sim.worlds.textures import albedo
from tests.conftest import look_at

ROAD, BUILDING, CAR = label_id("road"), label_id("building"), label_id("car")


# --- helpers -----------------------------------------------------------------------------------------


def yaw_pose(yaw: float, t) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    return make_pose(np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]), t)


def grid_set(grid: VoxelGrid) -> set[tuple[int, int, int]]:
    return set(map(tuple, grid.ijk.tolist()))


def voxel_index(points_chunk: np.ndarray, voxel: float) -> np.ndarray:
    return np.floor((points_chunk - CHUNK_CORNER) / voxel).astype(np.int64)


def contains_points(grid: VoxelGrid, points_chunk: np.ndarray, boundary_tol: float = 1e-6) -> np.ndarray:
    """(N,) bool: the voxel holding each point is in the grid. A point within boundary_tol (voxel
    units) of a voxel face may be claimed by the voxel on either side."""
    have = grid_set(grid)
    u = (points_chunk - CHUNK_CORNER) / grid.voxel_size
    base = np.floor(u).astype(np.int64)
    frac = u - base
    ok = np.zeros(len(u), bool)
    for n, (b, f) in enumerate(zip(base, frac)):
        options = [[b[a]] + ([b[a] - 1] if f[a] < boundary_tol else [])
                   + ([b[a] + 1] if f[a] > 1 - boundary_tol else []) for a in range(3)]
        ok[n] = any((i, j, k) in have for i in options[0] for j in options[1] for k in options[2])
    return ok


def triangle_box_overlap(tri: np.ndarray, centres: np.ndarray, half: float, eps: float) -> np.ndarray:
    """Separating-axis test (Akenine-Moller's 13 axes) of one triangle (3, 3) against axis-aligned
    cubes (N centres, half size). Overlap when no axis separates the projections by more than
    eps (eps < 0 demands a real overlap of at least -eps; eps > 0 also accepts near misses)."""
    v = tri[None, :, :] - centres[:, None, :]  # (N, 3, 3)
    e = [tri[1] - tri[0], tri[2] - tri[1], tri[0] - tri[2]]
    axes = [np.eye(3)[i] for i in range(3)] + [np.cross(e[0], e[1])]
    axes += [np.cross(np.eye(3)[i], ej) for i in range(3) for ej in e]
    ok = np.ones(len(centres), bool)
    for a in axes:
        ln = np.linalg.norm(a)
        if ln < 1e-12:
            continue
        a = a / ln
        p = v @ a  # (N, 3)
        r = half * np.abs(a).sum()
        ok &= ~((p.min(1) > r + eps) | (p.max(1) < -r - eps))
    return ok


def exact_voxels(tris_chunk: np.ndarray, voxel: float, eps: float) -> set[tuple[int, int, int]]:
    """Every voxel whose cube overlaps a triangle (chunk frame), by brute force over each bbox."""
    out = set()
    for tri in tris_chunk:
        u = (tri - CHUNK_CORNER) / voxel
        lo = np.floor(u.min(0) - 1).astype(int)
        hi = np.floor(u.max(0) + 1).astype(int)
        ii = np.stack(np.meshgrid(*[np.arange(lo[a], hi[a] + 1) for a in range(3)], indexing="ij"), -1).reshape(-1, 3)
        hit = triangle_box_overlap(u, ii + 0.5, 0.5, eps)
        n = int(round(CHUNK_SIZE / voxel))
        keep = hit & np.all((ii >= 0) & (ii < n), axis=1)
        out |= set(map(tuple, ii[keep].tolist()))
    return out


def box_shell_voxels(lo, hi, voxel: float) -> set[tuple[int, int, int]]:
    """Voxels the faces of the axis-aligned box [lo, hi] (chunk frame) pass through, by hand: the
    index range of the box on each axis, minus the voxels strictly inside (no face crosses them).
    Assumes no face lies on a voxel boundary."""
    a = np.floor((np.asarray(lo) - CHUNK_CORNER) / voxel).astype(int)
    b = np.floor((np.asarray(hi) - CHUNK_CORNER) / voxel).astype(int)
    out = set()
    for i in range(a[0], b[0] + 1):
        for j in range(a[1], b[1] + 1):
            for k in range(a[2], b[2] + 1):
                if i in (a[0], b[0]) or j in (a[1], b[1]) or k in (a[2], b[2]):
                    out.add((i, j, k))
    return out


# --- voxelize_mesh -----------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def world():
    return generate_world(WorldConfig(style="urban", seed=2, layout="curved"))


def test_voxelize_mesh_contains_random_surface_samples_of_a_world(world):
    mesh = world.mesh_at(0.0)
    chunk_to_world = world.ego_pose_at(0.0)
    grid = voxelize_mesh(mesh, chunk_to_world, 0.4)
    assert grid.voxel_size == 0.4 and grid.dims == 256
    assert np.all((grid.ijk >= 0) & (grid.ijk < 256))
    s = mesh.sample_surface(1.0, np.random.default_rng(7))
    p = transform_points(invert_pose(chunk_to_world), s["points"] + mesh.origin)
    inside = np.all((p >= CHUNK_CORNER) & (p < CHUNK_CORNER + CHUNK_SIZE), axis=1)
    p = p[inside]
    assert len(p) > 20_000
    # fast path: exact voxel membership; the few misses get the boundary-tolerant check
    have = grid_set(grid)
    missing = np.array([k not in have for k in map(tuple, voxel_index(p, 0.4).tolist())])
    ok = ~missing
    if missing.any():
        ok[missing] = contains_points(grid, p[missing])
    assert ok.all(), f"{np.sum(~ok)} surface samples fall in voxels the grid lacks, e.g. {p[~ok][:3]}"
    # every voxel holds some surface: the grid is not the whole chunk
    assert len(grid) < 0.02 * 256**3


def _random_triangles(voxel):
    rng = np.random.default_rng(3)
    chunk_to_world = yaw_pose(0.7, [120.0, -40.0, 3.0])
    tris = []
    for _ in range(25):
        c = rng.uniform(CHUNK_CORNER + 5, CHUNK_CORNER + CHUNK_SIZE - 5)
        scale = rng.choice([0.2, 1.0, 4.0])
        tris.append(c + rng.normal(size=(3, 3)) * scale)
    tris = np.array(tris)
    world_v = transform_points(chunk_to_world, tris.reshape(-1, 3))
    mesh = TriangleMesh(world_v, np.arange(len(world_v)).reshape(-1, 3), np.full(len(tris), CAR))
    return tris, mesh, voxelize_mesh(mesh, chunk_to_world, voxel)


def test_voxelize_mesh_of_random_triangles_holds_every_voxel_they_enter():
    voxel = 0.4
    tris, mesh, grid = _random_triangles(voxel)
    got = grid_set(grid)
    must = exact_voxels(tris, voxel, eps=-1e-7)  # the surface really enters these (exact SAT)
    assert len(must) > 1000
    assert must <= got, f"{len(must - got)} voxels the triangles pass through are missing"
    # and an independent random sampler agrees
    s = TriangleMesh(tris.reshape(-1, 3), mesh.faces).sample_surface(400.0, np.random.default_rng(1))
    assert set(map(tuple, voxel_index(s["points"], voxel).tolist())) <= got
    assert np.all(grid.labels == CAR)
    # conservative, but not wildly so
    assert len(got) < 1.1 * len(must)


def test_voxelize_mesh_of_random_triangles_adds_only_grazed_voxels():
    voxel = 0.4
    tris, _, grid = _random_triangles(voxel)
    extra = grid_set(grid) - exact_voxels(tris, voxel, eps=1e-6)  # a micrometre of slack
    assert not extra, f"{len(extra)} voxels the triangles do not touch, e.g. {sorted(extra)[:3]}"


def test_voxelize_mesh_of_a_box_is_its_shell():
    voxel = 0.4
    lo, hi = np.array([1.13, -2.27, 0.31]), np.array([3.71, 1.09, 2.05])
    box = pr.box((lo + hi) / 2, hi - lo, label=BUILDING)
    grid = voxelize_mesh(box, np.eye(4), voxel)
    expected = box_shell_voxels(lo, hi, voxel)
    # by hand: x 11.37..13.95 / 0.4 -> voxels 28..34 (7), y 48.93..52.29 -> 122..130 (9),
    # z 3.51..5.25 -> 8..13 (6); the shell is all but the 5 x 7 x 4 strictly inside
    a = np.floor((lo - CHUNK_CORNER) / voxel).astype(int)
    b = np.floor((hi - CHUNK_CORNER) / voxel).astype(int)
    assert a.tolist() == [28, 122, 8] and b.tolist() == [34, 130, 13]
    assert len(expected) == 7 * 9 * 6 - 5 * 7 * 4 == 238
    assert grid_set(grid) == expected
    assert np.all(grid.labels == BUILDING)


def test_voxelize_mesh_area_is_the_surface_area():
    voxel = 0.4
    lo, hi = np.array([1.13, -2.27, 0.31]), np.array([3.71, 1.09, 2.05])
    grid = voxelize_mesh(pr.box((lo + hi) / 2, hi - lo, label=BUILDING), np.eye(4), voxel)
    d = hi - lo
    area = 2 * (d[0] * d[1] + d[1] * d[2] + d[0] * d[2])
    # Partly covered columns count their covered fraction from 4 x 4 sub-cell centres: a few
    # per cent of the area of the edge columns.
    assert grid.area.sum() == pytest.approx(area, rel=0.05)


def test_voxelize_mesh_area_of_a_flat_quad_is_one_square_per_voxel():
    voxel = 0.4
    q = pr.quad([[-5.03, -5.03, 1.1], [5.03, -5.03, 1.1], [5.03, 5.03, 1.1], [-5.03, 5.03, 1.1]], label=ROAD)
    grid = voxelize_mesh(q, np.eye(4), voxel)
    lo_c = grid.ijk * voxel + CHUNK_CORNER
    interior = np.all((lo_c[:, :2] > -5.03) & (lo_c[:, :2] + voxel < 5.03), axis=1)
    assert interior.sum() > 500
    np.testing.assert_allclose(grid.area[interior], voxel**2, rtol=1e-5)


def test_voxelize_mesh_label_is_the_area_majority():
    """A road voxel (0.0625 m^2 of road) that a building's wall and floor only clip (2 cm of wall,
    a 1 cm strip of floor: 0.0075 m^2) must stay road."""
    voxel = 0.25
    z_road = 0.1  # road layer k = 13: z 0.05 .. 0.30
    road = pr.quad([[-8.0, -12.0, z_road], [30.0, -12.0, z_road], [30.0, 12.0, z_road], [-8.0, 12.0, z_road]],
                   label=ROAD)
    x_wall = -10.24 + 93 * voxel + 0.01  # 1 cm past the lower face of voxel column i = 93
    blo, bhi = np.array([5.1, -3.1, 0.28]), np.array([x_wall, 4.1, 6.0])
    bld = pr.box((blo + bhi) / 2, bhi - blo, label=BUILDING)
    grid = voxelize_mesh(TriangleMesh.concatenate([road, bld]), np.eye(4), voxel)
    sel = (grid.ijk[:, 0] == 93) & (grid.ijk[:, 2] == 13)
    lo_y = grid.ijk[:, 1] * voxel + CHUNK_CORNER[1]
    sel &= (lo_y > blo[1]) & (lo_y + voxel < bhi[1])
    assert sel.sum() == 28
    assert np.all(grid.labels[sel] == ROAD), f"{np.sum(grid.labels[sel] != ROAD)} of 28 voxels labelled building"




def test_voxelize_mesh_of_a_turned_box_in_a_moved_chunk():
    """The same box, with the chunk frame moved and turned in the world: the voxel set is the
    same (the grid is in the chunk frame)."""
    voxel = 0.4
    lo, hi = np.array([20.13, 5.07, 1.11]), np.array([23.35, 7.71, 3.93])
    chunk_to_world = yaw_pose(-1.1, [-300.0, 250.0, -7.0])
    box = pr.box((lo + hi) / 2, hi - lo, label=BUILDING)
    box.vertices = transform_points(chunk_to_world, box.vertices)
    grid = voxelize_mesh(box, chunk_to_world, voxel)
    assert grid_set(grid) == box_shell_voxels(lo, hi, voxel)


def test_voxelize_mesh_labels_building_on_road():
    """A road with a building standing on it, the floor in the road's voxel layer: inside the walls
    floor and road tie in area, and ties go to the smaller id (building). The road is tiled so that
    the piece under the building has the building's outline (no road triangle edge crosses it)."""
    voxel = 0.25
    z_road = 0.1  # chunk frame: layer k = floor((0.1 + 3.2) / 0.25) = 13 spans z 0.05 .. 0.30
    blo, bhi = np.array([5.1, -3.1, 0.07]), np.array([13.1, 4.1, 6.0])
    xs, ys = [-8.0, blo[0], bhi[0], 30.0], [-12.0, blo[1], bhi[1], 12.0]
    tiles = [pr.quad([[xs[a], ys[b], z_road], [xs[a + 1], ys[b], z_road], [xs[a + 1], ys[b + 1], z_road],
                      [xs[a], ys[b + 1], z_road]], label=ROAD) for a in range(3) for b in range(3)]
    bld = pr.box((blo + bhi) / 2, bhi - blo, label=BUILDING)
    grid = voxelize_mesh(TriangleMesh.concatenate(tiles + [bld]), np.eye(4), voxel)
    ijk, lab = grid.ijk, grid.labels
    lo_c = ijk * voxel + CHUNK_CORNER  # voxel lower corners, chunk frame
    hi_c = lo_c + voxel
    road_k = int(np.floor((z_road - CHUNK_CORNER[2]) / voxel))
    assert road_k == 13
    in_road_layer = ijk[:, 2] == road_k
    assert set(ijk[:, 2].tolist()) >= {13, 14} and ijk[:, 2].min() == 13
    # open road: road-layer voxels at least a voxel clear of the building's outline
    clear = ((hi_c[:, 0] < blo[0] - voxel) | (lo_c[:, 0] > bhi[0] + voxel)
             | (hi_c[:, 1] < blo[1] - voxel) | (lo_c[:, 1] > bhi[1] + voxel))
    open_road = in_road_layer & clear
    assert open_road.sum() > 10_000
    assert np.all(lab[open_road] == ROAD)
    # voxels fully inside the walls (their square strictly inside the footprint), every layer
    inside = (lo_c[:, 0] > blo[0]) & (hi_c[:, 0] < bhi[0]) & (lo_c[:, 1] > blo[1]) & (hi_c[:, 1] < bhi[1])
    assert (inside & in_road_layer).sum() == 31 * 28  # by hand: x 5.26..13.01 -> 31 voxels, y -2.95..4.05 -> 28
    assert np.all(lab[inside] == BUILDING)
    # wall and roof voxels above the road layer hold only the building
    above = ijk[:, 2] > road_k
    assert above.sum() > 500
    assert np.all(lab[above] == BUILDING)
    assert set(lab.tolist()) == {ROAD, BUILDING}


# --- voxelize / coarsen --------------------------------------------------------------------------------


def _brute_majority(keys, labels, weights):
    acc = defaultdict(lambda: defaultdict(float))
    for k, lab, w in zip(keys, labels, weights):
        acc[k][int(lab)] += float(w)
    out = {}
    for k, d in acc.items():
        best = max(d.values())
        out[k] = (min(lab for lab, w in d.items() if w == best), sum(d.values()))
    return out


def test_voxelize_points_majority_by_weight():
    rng = np.random.default_rng(5)
    voxel = 0.8
    centres = CHUNK_CORNER + (rng.integers(0, 128, (60, 3)) + 0.5) * voxel
    pts = np.repeat(centres, 20, axis=0) + rng.uniform(-0.39, 0.39, (1200, 3))
    labels = rng.integers(0, 4, 1200)
    weights = rng.choice([0.5, 1.0, 2.0], 1200)
    grid = voxelize(pts, labels, weights, voxel)
    ijk = voxel_index(pts, voxel)
    expect = _brute_majority(map(tuple, ijk.tolist()), labels, weights)
    got = {tuple(k): (int(lab), float(a)) for k, lab, a in zip(grid.ijk.tolist(), grid.labels, grid.area)}
    assert got.keys() == expect.keys()
    for k in expect:
        assert got[k][0] == expect[k][0]
        assert got[k][1] == pytest.approx(expect[k][1], rel=1e-6)


def test_voxelize_drops_points_outside_the_chunk():
    pts = np.array([CHUNK_CORNER - 0.01, CHUNK_CORNER + CHUNK_SIZE + 0.01, CHUNK_CORNER + 1.0])
    grid = voxelize(pts, np.array([1, 1, 2]), np.ones(3), 0.4)
    assert grid_set(grid) == {(2, 2, 2)} and grid.labels.tolist() == [2]


@pytest.mark.parametrize("factor", [2, 4])
def test_coarsen_matches_brute_force(factor):
    rng = np.random.default_rng(11)
    n = 256
    ijk = rng.integers(0, n, (400, 3))
    # clustered so coarse voxels gather several fine ones
    ijk = np.vstack([ijk, (ijk[:200, None, :] + rng.integers(0, 3, (200, 6, 3))).reshape(-1, 3)])
    ijk = np.unique(np.clip(ijk, 0, n - 1), axis=0)
    labels = rng.integers(1, 6, len(ijk)).astype(np.int16)
    area = rng.choice([0.01, 0.02, 0.05], len(ijk)).astype(np.float32)
    visible = rng.random(len(ijk)) < 0.2
    fine = VoxelGrid(ijk.astype(np.int32), labels, area, 0.4, visible)
    coarse = coarsen(fine, factor)
    expect = _brute_majority([tuple(k) for k in (ijk // factor).tolist()], labels, area)
    vis = defaultdict(bool)
    for k, v in zip((ijk // factor).tolist(), visible):
        vis[tuple(k)] |= bool(v)
    got = {tuple(k): (int(lab), float(a), bool(v))
           for k, lab, a, v in zip(coarse.ijk.tolist(), coarse.labels, coarse.area, coarse.visible)}
    assert got.keys() == expect.keys()
    for k in expect:
        assert got[k][0] == expect[k][0], k
        assert got[k][1] == pytest.approx(expect[k][1], rel=1e-5)
        assert got[k][2] == vis[k], k
    assert coarse.voxel_size == pytest.approx(0.4 * factor)
    assert coarse.dims == n // factor


def test_coarsen_without_visibility():
    fine = VoxelGrid(np.array([[0, 0, 0], [1, 1, 1], [2, 0, 0]], np.int32), np.array([3, 3, 5], np.int16),
                     np.array([1.0, 1.0, 3.0], np.float32), 0.1)
    c = coarsen(fine, 2)
    assert c.visible is None
    assert sorted(map(tuple, c.ijk.tolist())) == [(0, 0, 0), (1, 0, 0)]
    assert dict(zip(map(tuple, c.ijk.tolist()), c.labels.tolist())) == {(0, 0, 0): 3, (1, 0, 0): 5}


# --- visibility ----------------------------------------------------------------------------------------


def test_mark_visible_wall_hides_the_box_behind_it():
    voxel = 0.4
    wall_lo, wall_hi = np.array([9.5, -3.0, 0.1]), np.array([10.5, 3.0, 3.9])
    box_lo, box_hi = np.array([15.1, -0.45, 1.55]), np.array([16.1, 0.45, 2.45])
    wall = pr.box((wall_lo + wall_hi) / 2, wall_hi - wall_lo, label=BUILDING, instance=1)
    hidden = pr.box((box_lo + box_hi) / 2, box_hi - box_lo, label=CAR, instance=2)
    mesh = TriangleMesh.concatenate([wall, hidden])
    chunk_to_world = np.eye(4)
    grid = voxelize_mesh(mesh, chunk_to_world, voxel)
    assert grid_set(grid) == box_shell_voxels(wall_lo, wall_hi, voxel) | box_shell_voxels(box_lo, box_hi, voxel)

    intr = Intrinsics.from_fov(160, 120, 70.0)
    pose = look_at([0.0, 0.0, 2.0], [10.0, 0.0, 2.0])
    r = render_camera([Tracer(mesh)], intr, pose, shading=False)
    assert r["rgb"] is None and np.isfinite(r["depth"]).sum() > 1000
    assert not np.any(r["instance"] == 2)  # the renderer agrees: the box is out of sight
    seen = depth_to_points(r["depth"], intr, pose)
    vis = mark_visible(grid, seen)
    cells = {k: bool(v) for k, v in zip(map(tuple, grid.ijk.tolist()), vis)}

    # the wall's front face (x = 9.5), sampled inset from its edges: all of its voxels are seen
    ys, zs = np.meshgrid(np.linspace(-2.9, 2.9, 40), np.linspace(0.2, 3.8, 30))
    front = np.c_[np.full(ys.size, 9.5), ys.ravel(), zs.ravel()]
    front_vox = set(map(tuple, voxel_index(front, voxel).tolist()))
    assert all(cells[k] for k in front_vox)
    # the hidden box and the wall's back (x = 10.5) are unseen
    assert not any(cells[k] for k in box_shell_voxels(box_lo, box_hi, voxel))
    back_i = int(np.floor((wall_hi[0] - CHUNK_CORNER[0]) / voxel))
    assert not any(v for k, v in cells.items() if k[0] == back_i)
    # nothing else is marked: the visible voxels are exactly those of the front face
    assert {k for k, v in cells.items() if v} == front_vox


def test_mark_visible_points_outside_the_chunk_are_ignored():
    grid = VoxelGrid(np.array([[0, 0, 0], [5, 5, 5]], np.int32), np.zeros(2, np.int16), np.ones(2, np.float32), 1.0)
    pts = np.array([CHUNK_CORNER + 0.5, CHUNK_CORNER - 0.5, CHUNK_CORNER + CHUNK_SIZE + 0.5])
    assert mark_visible(grid, pts).tolist() == [True, False]


# --- depth_to_points -----------------------------------------------------------------------------------


@pytest.mark.parametrize("camera", ["pinhole", "FRONT", "SIDE_LEFT"])
def test_depth_to_points_lands_on_the_rendered_plane(camera):
    # a tilted plane through p0 with normal n, as one big quad
    n = np.array([0.2, -0.1, 1.0])
    n /= np.linalg.norm(n)
    p0 = np.array([20.0, 5.0, -1.0])
    u = np.cross(n, [0.0, 1.0, 0.0])
    u /= np.linalg.norm(u)
    v = np.cross(n, u)
    corners = [p0 + 200 * (a * u + b * v) for a, b in ((-1, -1), (1, -1), (1, 1), (-1, 1))]
    plane = pr.quad(corners, label=ROAD)
    if camera == "pinhole":
        intr = Intrinsics.from_fov(96, 64, 80.0)
        pose = look_at([0.0, 0.0, 6.0], [20.0, 5.0, -1.0])
    else:
        cam = load_rig("waymo-5").camera(camera)  # real calibration, with lens distortion
        intr = cam.intrinsics().scaled(0.05)
        pose = make_pose(np.eye(3), [3.0, 1.0, 4.0]) @ cam.cam_to_ego()
    r = render_camera([Tracer(plane)], intr, pose, shading=False)
    pts = depth_to_points(r["depth"], intr, pose)
    assert len(pts) == np.isfinite(r["depth"]).sum() > 0.1 * intr.width * intr.height
    dist = np.abs((pts - p0) @ n)
    # float16 would not do; the render's float32 depth gives well under a millimetre
    assert dist.max() < 1e-3, dist.max()
    # the points are in front of the camera, along its rays
    cam_pts = transform_points(invert_pose(pose), pts)
    assert np.all(cam_pts[:, 2] > 0)


def test_depth_to_points_skips_sky_and_zero():
    intr = Intrinsics.from_fov(4, 2, 60.0)
    depth = np.array([[np.inf, 2.0, 0.0, 5.0], [np.nan, 1.0, np.inf, 3.0]], np.float32)
    pts = depth_to_points(depth, intr, np.eye(4))
    assert len(pts) == 4
    np.testing.assert_allclose(np.sort(pts[:, 2]), [1.0, 2.0, 3.0, 5.0], rtol=1e-6)


# --- chunk samples -------------------------------------------------------------------------------------


def test_chunk_samples_lie_on_the_mesh_inside_the_chunk():
    chunk_to_world = yaw_pose(0.4, [50.0, 20.0, 1.0])
    # a quad half in, half out of the chunk (chunk frame x from -10.24)
    corners_c = np.array([[-20.0, -2.0, 0.5], [10.0, -2.0, 0.5], [10.0, 3.0, 0.5], [-20.0, 3.0, 0.5]])
    q = pr.quad(transform_points(chunk_to_world, corners_c), label=ROAD, instance=4)
    s = chunk_samples(q, chunk_to_world, 0.2)
    p = s["points"]
    assert np.all((p >= CHUNK_CORNER) & (p < CHUNK_CORNER + CHUNK_SIZE))
    np.testing.assert_allclose(p[:, 2], 0.5, atol=1e-9)
    assert p[:, 0].min() < -10.0 and p[:, 0].max() > 9.5
    # weights add up to the area inside the chunk: (10 + 10.24) x 5
    assert s["weights"].sum() == pytest.approx(20.24 * 5, rel=0.02)
    assert np.all(s["instances"] == 4) and np.all(s["labels"] == ROAD)


# --- gt_voxsplat ---------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def flat_splat():
    """A 6 x 6 m road patch at chunk z = 0, the chunk frame moved and turned in the world."""
    chunk_to_world = yaw_pose(0.6, [140.0, -35.0, 2.0])
    c = np.array([[20.03, -2.97, 0.0], [26.03, -2.97, 0.0], [26.03, 3.03, 0.0], [20.03, 3.03, 0.0]])
    plane = pr.ground_grid(20.03, -2.97, 26.03, 3.03, 0.0, 1.0, label=ROAD, color=(0.22, 0.22, 0.24))
    plane.vertices = transform_points(chunk_to_world, plane.vertices)
    vs = gt_voxsplat(plane, chunk_to_world, 0.4, gaussians_per_voxel=4)
    return vs, chunk_to_world, c


def test_gt_voxsplat_lies_flat_on_the_plane(flat_splat):
    vs, chunk_to_world, c = flat_splat
    assert np.allclose(vs.origin, CHUNK_CORNER)
    assert np.allclose(np.asarray(vs.metadata["chunk_to_world"]), chunk_to_world)
    assert vs.gaussians_per_voxel == 4 and np.all(vs.labels == ROAD)
    g = vs.gaussians()
    means = g.means + vs.origin  # chunk frame
    assert len(means) >= 4 * 15 * 15 * 0.9
    assert np.abs(means[:, 2]).max() < 1e-6
    assert np.all((means[:, 0] > c[0, 0]) & (means[:, 0] < c[1, 0]) & (means[:, 1] > c[0, 1]) & (means[:, 1] < c[2, 1]))
    # the voxels are the plane's: k = 8 (z from 0 to 0.4 above the corner -3.2) or just below
    assert set(vs.ijk[:, 2].tolist()) <= {7, 8}
    rot = vs.rotations()[vs.valid]
    scales = vs.scales()[vs.valid]
    flat = np.argmin(scales, axis=1)
    normal = rot[np.arange(len(rot)), :, flat]
    assert np.all(np.abs(normal[:, 2]) > 0.999)
    assert np.all(scales.min(1) <= 0.01 * 0.4 * (1 + 1e-6))  # the fit's floor: 1 % of the voxel
    assert np.all(scales.min(1) < 0.25 * np.median(scales, axis=1))


def test_gt_voxsplat_colours_are_the_road_albedo(flat_splat):
    vs, chunk_to_world, _ = flat_splat
    g = vs.gaussians()
    colors = vs.colors()[vs.valid]
    world_means = transform_points(chunk_to_world, g.means + vs.origin)
    up = np.tile([0.0, 0.0, 1.0], (len(world_means), 1))
    # the fit textures its samples with their 0.2 m spacing as the footprint (voxel 0.4 m)
    expect = albedo(world_means, up, np.full(len(up), ROAD), np.tile([0.22, 0.22, 0.24], (len(up), 1)),
                    np.zeros(len(up), np.int32), footprint=0.2)
    err = np.abs(colors - expect)
    # each Gaussian averages the asphalt's metre-scale wear over its 0.2 m patch: what is left
    # finer than the footprint is filtered out of both
    assert err.max() < 0.04 and err.mean() < 0.012, (err.max(), err.mean())


def test_gt_voxsplat_traced_from_above_gives_the_plane_height(flat_splat):
    vs, chunk_to_world, _ = flat_splat
    tr = Tracer(vs, mode="max_response")
    rng = np.random.default_rng(2)
    xy = rng.uniform([20.6, -2.4], [25.4, 2.4], (500, 2))
    origins = np.c_[xy, np.full(len(xy), 5.0)]  # chunk frame = the VoxSplat's world frame
    h = tr.trace_world(origins, np.tile([0.0, 0.0, -1.0], (len(xy), 1)))
    assert h.hit.all()
    z = h.points[:, 2] + tr.origin[2]
    assert np.abs(z).max() < 0.01, np.abs(z).max()
    np.testing.assert_allclose(h.t, 5.0, atol=0.01)
    assert np.all(h.label == ROAD)
