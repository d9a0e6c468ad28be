"""`render_camera` against geometry computed without our tracer: open3d's RaycastingScene
(distances and its own ray casts), closed-form ray-plane and ray-box (slab) intersections, and
analytic sun shadows. Small images (<= 192 x 128) keep it fast."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest

from scube_sim.camera.model import Intrinsics
from scube_sim.camera.render import render_camera
from scube_sim.camera.rig import load_rig
from scube_sim.labels import label_id
from scube_sim.mesh import TriangleMesh
from scube_sim.raytrace.tracer import Tracer
from scube_sim.worlds import primitives as pr
from scube_sim.worlds.generator import WorldConfig, generate_world
from scube_sim.worlds.textures import albedo
from tests.conftest import look_at

SKY = label_id("sky")
KEYS = ("rgb", "depth", "semantic", "instance", "sky")


def pinhole_dirs(intr: Intrinsics, cam_to_world: np.ndarray) -> np.ndarray:
    """(H*W, 3) world ray directions with camera z-component 1 (so the ray parameter IS z-depth),
    from K alone (pixel centres at +0.5), not from `pixel_rays`."""
    uu, vv = np.meshgrid(np.arange(intr.width) + 0.5, np.arange(intr.height) + 0.5)
    d = np.stack([(uu - intr.cx) / intr.fx, (vv - intr.cy) / intr.fy, np.ones_like(uu)], -1).reshape(-1, 3)
    return d @ cam_to_world[:3, :3].T


def slab(o, d, center, size, yaw):
    """Ray (o (3,) or (N, 3), d (N, 3)) vs box: entry t (inf on a miss), entry axis (box frame),
    and a margin (how far the ray is from missing / from an edge between two faces), all float64."""
    c, s = np.cos(yaw), np.sin(yaw)
    rz_t = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])  # world -> box
    o_b = (np.broadcast_to(o, d.shape) - np.asarray(center, float)) @ rz_t.T
    d_b = d @ rz_t.T
    h = np.asarray(size, float) / 2
    with np.errstate(divide="ignore", invalid="ignore"):
        t1, t2 = (-h - o_b) / d_b, (h - o_b) / d_b
    lo, hi = np.minimum(t1, t2), np.maximum(t1, t2)
    lo = np.where(np.isnan(lo), -np.inf, lo)
    hi = np.where(np.isnan(hi), np.inf, hi)
    tn, tf = lo.max(1), hi.min(1)
    hit = (tn <= tf) & (tf > 0)
    srt = np.sort(lo, 1)
    margin = np.minimum(np.abs(tf - tn), srt[:, 2] - srt[:, 1])
    return np.where(hit, np.maximum(tn, 0.0), np.inf), lo.argmax(1), margin, d_b


def closest_point_on_triangles(p, a, b, c):
    """Exact float64 closest points on triangles (a, b, c) to p, all (N, 3) (Ericson, RTCD 5.1.5)."""
    dot = lambda u, v: np.einsum("ij,ij->i", u, v)  # noqa: E731
    ab, ac, ap, bp, cp = b - a, c - a, p - a, p - b, p - c
    d1, d2, d3, d4, d5, d6 = dot(ab, ap), dot(ac, ap), dot(ab, bp), dot(ac, bp), dot(ab, cp), dot(ac, cp)
    vc, vb, va = d1 * d4 - d3 * d2, d5 * d2 - d1 * d6, d3 * d6 - d5 * d4
    with np.errstate(divide="ignore", invalid="ignore"):
        e_ab = a + (d1 / (d1 - d3))[:, None] * ab
        e_ac = a + (d2 / (d2 - d6))[:, None] * ac
        e_bc = b + ((d4 - d3) / ((d4 - d3) + (d5 - d6)))[:, None] * (c - b)
        den = 1.0 / (va + vb + vc)
        face = a + (vb * den)[:, None] * ab + (vc * den)[:, None] * ac
    conds = [(d1 <= 0) & (d2 <= 0), (d3 >= 0) & (d4 <= d3), (vc <= 0) & (d1 >= 0) & (d3 <= 0),
             (d6 >= 0) & (d5 <= d6), (vb <= 0) & (d2 >= 0) & (d6 <= 0), (va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0)]
    out = face.copy()
    for cond, val in reversed(list(zip(conds, [a, b, e_ab, c, e_ac, e_bc]))):
        out[cond] = val[cond]
    return out


def o3d_scene(mesh: TriangleMesh) -> o3d.t.geometry.RaycastingScene:
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(mesh.vertices.astype(np.float32)),
                        o3d.core.Tensor(mesh.faces.astype(np.uint32)))
    return scene


def flat_albedo(points, normals, labels, base, instances, **_):
    """The face colour itself: shading tests compare one albedo under different light."""
    return np.asarray(base, np.float32)


# --- a generated street, seen by the real Waymo FRONT camera ---------------------------------

@pytest.fixture(scope="module")
def street():
    world = generate_world(WorldConfig(style="urban", seed=5))
    mesh = world.mesh_at(0.0)  # static scene and actors
    cam = load_rig("waymo-5").camera("FRONT")
    intr = cam.intrinsics().scaled(0.1)  # 192 x 128, real distortion
    cam_to_world = world.ego_pose_at(0.0) @ cam.cam_to_ego()
    tracer = Tracer(mesh)
    out = render_camera([tracer], intr, cam_to_world, sun_dir=world.sun_dir, albedo_fn=albedo)
    return dict(world=world, mesh=mesh, intr=intr, cam_to_world=cam_to_world, out=out, scene=o3d_scene(mesh))


def test_street_render_outputs(street):
    out, intr = street["out"], street["intr"]
    shape = (intr.height, intr.width)
    assert out["rgb"].shape == shape + (3,) and out["rgb"].dtype == np.uint8
    assert out["depth"].shape == shape and out["depth"].dtype == np.float32
    assert out["semantic"].dtype == np.int16 and out["instance"].dtype == np.int32 and out["sky"].dtype == bool
    # a street scene: mostly geometry, some sky, road and buildings among the labels
    assert 0.5 < np.isfinite(out["depth"]).mean() < 0.99
    assert {label_id("road"), label_id("building"), SKY} <= set(np.unique(out["semantic"]).tolist())


def test_depth_back_projects_onto_the_mesh(street):
    """Every finite depth pixel, back-projected along its (distorted) pixel ray as z-depth, lies on
    the mesh: unsigned distance from open3d < 1 mm.

    open3d's compute_distance works in float32 and is itself off by up to ~3 mm on this world's
    long, thin facade slivers (21 m x 0.15 m triangles: it reports the closest point a few mm
    along the sliver although the exact float64 point-triangle distance is ~1e-7 m). So the bound
    asserted for every point is the exact float64 distance to the triangle open3d's closest-point
    query picks (any triangle's distance bounds the distance to the mesh), and open3d's own number
    must be < 1 mm for >= 99.9 % of the points."""
    out, intr, c2w, mesh, scene = street["out"], street["intr"], street["cam_to_world"], street["mesh"], street["scene"]
    depth = out["depth"].astype(np.float64).reshape(-1)
    fin = np.isfinite(depth)
    rays = intr.pixel_rays().reshape(-1, 3)[fin]
    p_cam = rays / rays[:, 2:3] * depth[fin, None]  # z-depth -> point on the ray
    p = p_cam @ c2w[:3, :3].T + c2w[:3, 3] - mesh.origin
    d_o3d = scene.compute_distance(o3d.core.Tensor(p.astype(np.float32))).numpy()
    assert (d_o3d < 1e-3).mean() >= 0.999 and np.median(d_o3d) < 1e-5
    prim = scene.compute_closest_points(o3d.core.Tensor(p.astype(np.float32)))["primitive_ids"].numpy().astype(np.int64)
    tri = mesh.vertices[mesh.faces[prim]]
    exact = np.linalg.norm(p - closest_point_on_triangles(p, tri[:, 0], tri[:, 1], tri[:, 2]), axis=1)
    # Also the exact distance to the triangle open3d's own ray cast of the same pixel hits.
    d_world = rays @ c2w[:3, :3].T
    cast = scene.cast_rays(o3d.core.Tensor(np.c_[np.broadcast_to(c2w[:3, 3] - mesh.origin, d_world.shape),
                                                 d_world].astype(np.float32)))["primitive_ids"].numpy().astype(np.int64)
    ok = cast != scene.INVALID_ID
    tri_c = mesh.vertices[mesh.faces[np.where(ok, cast, 0)]]
    exact_c = np.where(ok, np.linalg.norm(p - closest_point_on_triangles(p, tri_c[:, 0], tri_c[:, 1], tri_c[:, 2]), axis=1),
                       np.inf)
    bound = np.minimum(np.minimum(exact, exact_c), d_o3d)
    assert bound.max() < 1e-3, f"{(bound >= 1e-3).sum()} pixels' back-projections are >= 1 mm off the mesh"


def test_semantics_match_open3d_ray_casts(street):
    """The same pixel rays cast by open3d (not our Tracer): hit mask, label of the triangle hit
    (sky where nothing is hit) and instance agree on every pixel, depth to float32 precision."""
    out, intr, c2w, mesh, scene = street["out"], street["intr"], street["cam_to_world"], street["mesh"], street["scene"]
    d_cam = intr.pixel_rays().reshape(-1, 3)
    d = d_cam @ c2w[:3, :3].T
    rays = np.c_[np.broadcast_to(c2w[:3, 3] - mesh.origin, d.shape), d].astype(np.float32)
    ans = scene.cast_rays(o3d.core.Tensor(rays))
    t_hit = ans["t_hit"].numpy().astype(np.float64)
    prim = ans["primitive_ids"].numpy().astype(np.int64)
    hit = np.isfinite(t_hit)
    sem = np.full(hit.shape, SKY, np.int16)
    sem[hit] = mesh.labels[prim[hit]]
    inst = np.zeros(hit.shape, np.int32)
    inst[hit] = mesh.instances[prim[hit]]
    np.testing.assert_array_equal(out["sky"].reshape(-1), ~hit)
    np.testing.assert_array_equal(out["semantic"].reshape(-1), sem)
    np.testing.assert_array_equal(out["instance"].reshape(-1), inst)
    assert len(np.unique(inst)) > 1  # some actors are in view, so instances are really compared
    np.testing.assert_allclose(out["depth"].reshape(-1)[hit], t_hit[hit] * d_cam[hit, 2], rtol=1e-5, atol=1e-4)


def test_sky_mask_semantic_and_depth_agree(street):
    out = street["out"]
    np.testing.assert_array_equal(out["sky"], out["semantic"] == SKY)
    np.testing.assert_array_equal(out["sky"], ~np.isfinite(out["depth"]))
    assert np.all(out["depth"][~out["sky"]] > 0)
    assert np.all(out["instance"][out["sky"]] == 0)
    # sky is above the horizon: the top row has more of it than the bottom row (none there)
    assert out["sky"][0].mean() > 0.1 and not out["sky"][-1].any()


def test_render_is_deterministic(street):
    """A second render, with a freshly built tracer, is byte-identical."""
    again = render_camera([Tracer(street["mesh"])], street["intr"], street["cam_to_world"],
                          sun_dir=street["world"].sun_dir, albedo_fn=albedo)
    for k in KEYS:
        assert again[k].dtype == street["out"][k].dtype and again[k].tobytes() == street["out"][k].tobytes(), k


def test_static_and_actor_tracers_equal_one_mesh(street):
    """Rendering the static scene and each actor as separate tracers gives the same image as the
    concatenated mesh (nearest hit over tracers)."""
    world = street["world"]
    tracers = [Tracer(world.static)] + [Tracer(m) for m in world.actor_meshes_at(0.0)]
    split = render_camera(tracers, street["intr"], street["cam_to_world"], sun_dir=world.sun_dir, albedo_fn=albedo)
    for k in ("depth", "semantic", "instance", "sky"):
        np.testing.assert_array_equal(split[k], street["out"][k], err_msg=k)


# --- analytic scenes -------------------------------------------------------------------------

def _random_rotation(seed: int) -> np.ndarray:
    q = np.random.default_rng(seed).normal(size=4)
    w, x, y, z = q / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("camera", ["pinhole", "waymo_front"])
def test_plane_facing_camera_gives_depth_10_everywhere(seed, camera):
    """A camera 10 m in front of a large plane that faces it: z-depth is 10 m for every pixel, also
    through the real distorted Waymo lens (whose corner rays are ~30 deg off-axis)."""
    if camera == "pinhole":
        intr = Intrinsics.from_fov(64, 48, 100.0)
    else:
        intr = load_rig("waymo-5").camera("FRONT").intrinsics().scaled(0.05)
    c2w = np.eye(4)
    if seed:
        c2w[:3, :3] = _random_rotation(seed)
        c2w[:3, 3] = np.random.default_rng(seed).uniform(-50, 50, 3)
    else:  # axis-aligned: camera at the origin looking along world +x
        c2w = look_at((0, 0, 0), (1, 0, 0))
    axis, a, b = c2w[:3, 2], c2w[:3, 0], c2w[:3, 1]
    centre = c2w[:3, 3] + 10.0 * axis
    corners = [centre + 200 * (sa * a + sb * b) for sa, sb in [(-1, -1), (-1, 1), (1, 1), (1, -1)]]
    out = render_camera([Tracer(pr.quad(corners, label=label_id("building")))], intr, c2w, albedo_fn=albedo)
    assert not out["sky"].any()
    np.testing.assert_allclose(out["depth"], 10.0, rtol=0, atol=2e-6)
    assert np.all(out["semantic"] == label_id("building"))


def test_box_depth_matches_slab_intersection():
    intr = Intrinsics.from_fov(96, 72, 60.0)
    c2w = look_at((5.0, -3.0, 4.0), (12.0, 1.0, 1.0))
    center, size, yaw = (12.0, 1.0, 1.0), (4.0, 2.5, 2.0), 0.5
    box = pr.box(center, size, yaw=yaw, label=label_id("car"), instance=7)
    out = render_camera([Tracer(box)], intr, c2w, albedo_fn=albedo)
    d = pinhole_dirs(intr, c2w)
    t, _, margin, _ = slab(c2w[:3, 3], d, center, size, yaw)
    expect_hit = np.isfinite(t)
    assert 0.1 < expect_hit.mean() < 0.9  # the box fills part of the view
    got_hit = ~out["sky"].reshape(-1)
    disagree = got_hit != expect_hit
    assert not np.any(disagree & (margin > 1e-6)), "hit mask differs away from the box's silhouette"
    both = got_hit & expect_hit
    np.testing.assert_allclose(out["depth"].reshape(-1)[both], t[both], rtol=1e-6, atol=1e-6)
    assert np.all(out["semantic"].reshape(-1)[both] == label_id("car"))
    assert np.all(out["instance"].reshape(-1)[both] == 7)
    # sky mask == semantic sky == non-finite depth here too
    np.testing.assert_array_equal(out["sky"], out["semantic"] == SKY)
    np.testing.assert_array_equal(out["sky"], ~np.isfinite(out["depth"]))


# --- shading -----------------------------------------------------------------------------------

def _luma(rgb):
    return rgb.reshape(-1, 3).astype(np.float64) @ np.array([0.2126, 0.7152, 0.0722])


def test_face_towards_sun_is_brighter_than_face_away():
    """A box seen corner-on: two vertical faces, same albedo, same ambient; the sun lights one of
    them (n.s > 0) and is behind the other (n.s < 0)."""
    intr = Intrinsics.from_fov(96, 64, 50.0)
    c2w = look_at((0.0, 0.0, 1.0), (10.0, 0.0, 1.0))
    center, size, yaw = (10.0, 0.0, 1.0), (3.0, 3.0, 2.0), np.deg2rad(45.0)
    sun = np.array([-0.5, -0.8, 0.33])
    sun /= np.linalg.norm(sun)
    box = pr.box(center, size, yaw=yaw, color=(0.5, 0.5, 0.5))
    out = render_camera([Tracer(box)], intr, c2w, sun_dir=sun, albedo_fn=flat_albedo)
    t, axis, margin, d_b = slab(c2w[:3, 3], pinhole_dirs(intr, c2w), center, size, yaw)
    ok = np.isfinite(t) & (margin > 1e-3)
    # outward normal of the entry face in the world: -sign(d_b) along the box axis, rotated by yaw
    c, s = np.cos(yaw), np.sin(yaw)
    axes = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])
    n = -np.sign(d_b[np.arange(len(t)), axis])[:, None] * axes[axis]
    ndots = n @ sun
    lit, away = ok & (ndots > 0.3), ok & (ndots < -0.1)
    assert lit.sum() > 50 and away.sum() > 50
    y = _luma(out["rgb"])
    assert y[lit].min() > y[away].max() + 30, (y[lit].min(), y[away].max())
    # each planar face under a directional sun with a flat albedo is one uniform colour
    assert np.ptp(out["rgb"].reshape(-1, 3)[lit], axis=0).max() <= 1
    assert np.ptp(out["rgb"].reshape(-1, 3)[away], axis=0).max() <= 1


def test_shadow_of_a_box_on_the_ground():
    """A box between the sun and the ground: the ground points whose ray to the sun meets the box
    (computed analytically here) are darker than the lit ground, and those are the only dark ones."""
    intr = Intrinsics.from_fov(128, 96, 80.0)
    c2w = look_at((-6.0, 0.0, 9.0), (8.0, 0.0, 0.0))
    sun = np.array([-0.6, 0.3, 0.4])
    sun /= np.linalg.norm(sun)
    center, size, yaw = (4.0, 1.0, 2.0), (2.0, 2.5, 4.0), 0.3
    ground = pr.quad([(-100, -100, 0), (100, -100, 0), (100, 100, 0), (-100, 100, 0)], color=(0.6, 0.6, 0.6))
    box = pr.box(center, size, yaw=yaw, color=(0.6, 0.6, 0.6))
    scene = TriangleMesh.concatenate([ground, box])
    out = render_camera([Tracer(scene)], intr, c2w, sun_dir=sun, albedo_fn=flat_albedo)
    o, d = c2w[:3, 3], pinhole_dirs(intr, c2w)
    t_box, _, m_box, _ = slab(o, d, center, size, yaw)
    t_ground = np.where(d[:, 2] < 0, -o[2] / d[:, 2], np.inf)
    with np.errstate(invalid="ignore"):
        inside_quad = np.all(np.abs(o[:2] + t_ground[:, None] * d[:, :2]) < 99.0, axis=1)
    on_ground = np.isfinite(t_ground) & inside_quad & (t_ground < t_box) & (m_box > 1e-3)
    g = o + t_ground[on_ground, None] * d[on_ground]
    t_sh, _, m_sh, _ = slab(g, np.broadcast_to(sun, g.shape), center, size, yaw)
    shadow = np.isfinite(t_sh)
    clear = m_sh > 1e-3  # not grazing the box's silhouette as seen from the sun
    assert (shadow & clear).sum() > 100 and (~shadow & clear).sum() > 100
    y = _luma(out["rgb"])[on_ground]
    assert y[shadow & clear].max() < y[~shadow & clear].min() - 30
    # the dark ground is exactly the analytic shadow (two uniform levels)
    np.testing.assert_array_equal((y < (y[shadow & clear].max() + y[~shadow & clear].min()) / 2)[clear], shadow[clear])
    # the depth of the ground pixels is the analytic plane depth too
    np.testing.assert_allclose(out["depth"].reshape(-1)[on_ground], t_ground[on_ground], rtol=1e-6)
    # without shadows the same ground is uniformly lit
    flat = render_camera([Tracer(scene)], intr, c2w, sun_dir=sun, albedo_fn=flat_albedo, shadows=False)
    assert np.ptp(_luma(flat["rgb"])[on_ground]) <= 1


def test_exposure_scales_linear_light_and_vignetting_darkens_the_corners():
    """A wall filling the view, flat albedo, no shadows: exposure multiplies every pixel's linear
    light; vignetting v leaves the principal point and scales a pixel at r (over the half-diagonal)
    by 1 - v r^2."""
    intr = Intrinsics.from_fov(96, 64, 60.0)
    c2w = look_at((0.0, 0.0, 1.0), (10.0, 0.0, 1.0))
    wall = pr.quad([(8, -50, -50), (8, 50, -50), (8, 50, 50), (8, -50, 50)], color=(0.5, 0.5, 0.5))

    def linear(**kw):
        out = render_camera([Tracer(wall)], intr, c2w, albedo_fn=flat_albedo, shadows=False, **kw)
        return (out["rgb"].astype(np.float64) / 255.0) ** 2.2

    base, bright = linear(), linear(exposure=1.3)
    # 8-bit rounding: half a level near 100/255 moves linear light by 2.2 x 0.5 / 100 = 1.1 %, twice
    np.testing.assert_allclose(bright / base, 1.3, rtol=0.03)
    vig = linear(vignetting=0.25)
    uu, vv = np.meshgrid(np.arange(intr.width) + 0.5, np.arange(intr.height) + 0.5)
    r2 = ((uu - intr.cx) ** 2 + (vv - intr.cy) ** 2) / ((intr.width / 2) ** 2 + (intr.height / 2) ** 2)
    np.testing.assert_allclose(vig[..., 0] / base[..., 0], 1.0 - 0.25 * r2, atol=0.03)
    assert vig[0, 0, 0] < 0.8 * base[0, 0, 0]  # a corner loses about a quarter
