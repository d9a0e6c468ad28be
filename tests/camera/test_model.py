"""Camera intrinsics against formulas written out here (OpenCV's documented distortion models),
closed-form geometry and the real Waymo FRONT calibration.

OpenCV (`cv2`) is not installed in this environment, so the reference formulas are the ones of
OpenCV's documentation, typed out independently of `scube_sim.camera.model`:
- pinhole + Brown-Conrady ("opencv", [k1, k2, p1, p2, k3]), calib3d `projectPoints`:
    r2 = x^2 + y^2
    x' = x (1 + k1 r2 + k2 r2^2 + k3 r2^3) + 2 p1 x y + p2 (r2 + 2 x^2)
    y' = y (1 + k1 r2 + k2 r2^2 + k3 r2^3) + p1 (r2 + 2 y^2) + 2 p2 x y
- equidistant fisheye ([k1..k4]), `cv::fisheye`:
    theta = atan(r), theta_d = theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 + k4 theta^8),
    x' = (theta_d / r) x, y' = (theta_d / r) y
and u = fx x' + cx, v = fy y' + cy with pixel centres at integer + 0.5.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from scube_sim.camera.model import Intrinsics

from ..conftest import require

# A plausible wide-angle lens (coefficients of the magnitude OpenCV calibrations give); every
# coefficient non-zero so that a swapped or dropped term shows.
OPENCV_DIST = (-0.28, 0.09, 0.0012, -0.0007, -0.012)
FISHEYE_DIST = (0.05, -0.01, 0.002, -0.0005)


def ref_opencv(x, y, k1, k2, p1, p2, k3):
    r2 = x ** 2 + y ** 2
    radial = 1 + k1 * r2 + k2 * r2 ** 2 + k3 * r2 ** 3
    return x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x ** 2), y * radial + p1 * (r2 + 2 * y ** 2) + 2 * p2 * x * y


def ref_fisheye(x, y, k1, k2, k3, k4):
    r = np.hypot(x, y)
    theta = np.arctan(r)
    theta_d = theta * (1 + k1 * theta ** 2 + k2 * theta ** 4 + k3 * theta ** 6 + k4 * theta ** 8)
    s = np.where(r > 0, theta_d / np.where(r > 0, r, 1.0), 1.0)
    return x * s, y * s


def pixel_centres(intr: Intrinsics):
    """(H*W, 2) pixel centres in row-major (v, u) order, as the docs define them."""
    uu, vv = np.meshgrid(np.arange(intr.width) + 0.5, np.arange(intr.height) + 0.5)
    return np.stack([uu.ravel(), vv.ravel()], 1)


@pytest.fixture(scope="module")
def waymo_front(shared_data) -> Intrinsics:
    """Waymo FRONT intrinsics straight from the source JSON (not through our rig YAML)."""
    meta = json.loads(require(shared_data / "waymo-open-dataset-frame" / "frame_metadata.json").read_text())
    c = next(c for c in meta["camera_calibrations"] if c["name"] == "FRONT")
    fu, fv, cu, cv, k1, k2, p1, p2, k3 = c["intrinsic_fu_fv_cu_cv_k1_k2_p1_p2_k3"]
    return Intrinsics(c["width"], c["height"], fu, fv, cu, cv, "opencv", (k1, k2, p1, p2, k3))


# --- distortion formulas ---------------------------------------------------------------------

def test_opencv_distortion_matches_reference_formula(rng):
    intr = Intrinsics(640, 480, 500.0, 505.0, 321.0, 239.0, "opencv", OPENCV_DIST)
    x, y = rng.uniform(-0.8, 0.8, 2000), rng.uniform(-0.6, 0.6, 2000)
    xd, yd = intr.distort(x, y)
    ex, ey = ref_opencv(x, y, *OPENCV_DIST)
    np.testing.assert_allclose(xd, ex, rtol=0, atol=1e-14)
    np.testing.assert_allclose(yd, ey, rtol=0, atol=1e-14)
    # and through `project` to pixels
    z = rng.uniform(0.5, 50.0, x.size)
    uv, depth = intr.project(np.c_[x * z, y * z, z])
    np.testing.assert_allclose(uv[:, 0], 500.0 * ex + 321.0, rtol=0, atol=1e-9)
    np.testing.assert_allclose(uv[:, 1], 505.0 * ey + 239.0, rtol=0, atol=1e-9)
    np.testing.assert_array_equal(depth, z)


@pytest.mark.parametrize("which", range(5))
def test_opencv_each_coefficient_lands_in_its_place(which):
    """One coefficient at a time: catches [k1, k2, p1, p2, k3] read in another order."""
    coeffs = [0.0] * 5
    coeffs[which] = 0.05
    intr = Intrinsics(100, 100, 100.0, 100.0, 50.0, 50.0, "opencv", tuple(coeffs))
    x, y = np.array([0.3, -0.2, 0.5]), np.array([0.1, 0.4, -0.35])
    np.testing.assert_allclose(np.stack(intr.distort(x, y)), np.stack(ref_opencv(x, y, *coeffs)), atol=1e-15)


def test_fisheye_distortion_matches_reference_formula(rng):
    intr = Intrinsics(640, 480, 300.0, 300.0, 320.0, 240.0, "fisheye", FISHEYE_DIST)
    x, y = rng.uniform(-2.0, 2.0, 2000), rng.uniform(-2.0, 2.0, 2000)
    xd, yd = intr.distort(x, y)
    ex, ey = ref_fisheye(x, y, *FISHEYE_DIST)
    np.testing.assert_allclose(xd, ex, rtol=0, atol=1e-14)
    np.testing.assert_allclose(yd, ey, rtol=0, atol=1e-14)
    # the optical axis itself is not moved (r = 0 limit)
    assert intr.distort(np.zeros(1), np.zeros(1)) == (0.0, 0.0)


def test_fisheye_with_zero_coefficients_is_equidistant_not_pinhole():
    intr = Intrinsics(640, 480, 300.0, 300.0, 320.0, 240.0, "fisheye", (0.0, 0.0, 0.0, 0.0))
    x, y = np.array([1.0, 0.3]), np.array([0.0, -0.4])
    np.testing.assert_allclose(np.stack(intr.distort(x, y)), np.stack(ref_fisheye(x, y, 0, 0, 0, 0)), atol=1e-12)


def test_pinhole_has_no_distortion(rng):
    intr = Intrinsics(64, 48, 50.0, 50.0, 32.0, 24.0)
    x, y = rng.normal(size=10), rng.normal(size=10)
    xd, yd = intr.distort(x, y)
    np.testing.assert_array_equal(xd, x)
    np.testing.assert_array_equal(yd, y)


# --- undistortion on the real Waymo FRONT lens -----------------------------------------------

def test_undistort_inverts_distort_over_waymo_front_image(waymo_front):
    intr = waymo_front
    # Every 8th pixel plus the exact image border (corners included).
    u = np.r_[np.arange(0, intr.width, 8.0), intr.width]
    v = np.r_[np.arange(0, intr.height, 8.0), intr.height]
    uu, vv = np.meshgrid(u, v)
    xd, yd = (uu - intr.cx) / intr.fx, (vv - intr.cy) / intr.fy
    x, y = intr.undistort(xd, yd)
    # the ideal points really are ideal: the reference forward model maps them back on the pixels
    ex, ey = ref_opencv(x, y, *intr.dist)
    assert np.abs(ex - xd).max() < 1e-9 and np.abs(ey - yd).max() < 1e-9
    # and the other way round: ideal grid spanning the same area -> distort -> undistort
    xi, yi = np.meshgrid(np.linspace(x.min(), x.max(), 97), np.linspace(y.min(), y.max(), 73))
    xr, yr = intr.undistort(*intr.distort(xi, yi))
    assert np.abs(xr - xi).max() < 1e-9 and np.abs(yr - yi).max() < 1e-9


# --- rays and projection ---------------------------------------------------------------------

def test_pixel_rays_pinhole_convention():
    """Pixel (0, 0)'s centre is at (0.5, 0.5); x right, y down, z forward; unit length."""
    intr = Intrinsics(8, 6, 10.0, 12.0, 3.0, 2.5)
    rays = intr.pixel_rays()
    assert rays.shape == (6, 8, 3) and rays.dtype == np.float64
    np.testing.assert_allclose(np.linalg.norm(rays, axis=-1), 1.0, atol=1e-15)
    for v, u in [(0, 0), (5, 7), (2, 4)]:
        d = np.array([(u + 0.5 - 3.0) / 10.0, (v + 0.5 - 2.5) / 12.0, 1.0])
        np.testing.assert_allclose(rays[v, u], d / np.linalg.norm(d), atol=1e-15)
    assert rays[0, 0, 0] < 0 and rays[0, 0, 1] < 0  # top-left pixel looks left and up
    assert rays[-1, -1, 0] > 0 and rays[-1, -1, 1] > 0


def _check_project_round_trip(intr: Intrinsics, rng, tol_px=1e-6):
    rays = intr.pixel_rays().reshape(-1, 3)
    depth = rng.uniform(0.3, 300.0, rays.shape[0])
    uv, z = intr.project(rays * depth[:, None])
    np.testing.assert_allclose(z, rays[:, 2] * depth, rtol=1e-15)
    err = np.abs(uv - pixel_centres(intr)).max()
    assert err < tol_px, f"{intr.model}: project(pixel_rays) is {err:.3g} px from the pixel centres"


def test_project_inverts_pixel_rays_pinhole(rng):
    _check_project_round_trip(Intrinsics(160, 120, 90.0, 95.0, 81.3, 58.9), rng)


def test_project_inverts_pixel_rays_opencv_waymo_front(waymo_front, rng):
    # Full 1920 x 1280 resolution of the real lens.
    _check_project_round_trip(waymo_front, rng)


def test_project_inverts_pixel_rays_fisheye_narrow(rng):
    # Corner rays about 28 degrees off-axis.
    _check_project_round_trip(Intrinsics(640, 480, 800.0, 800.0, 320.0, 240.0, "fisheye", FISHEYE_DIST), rng)


def test_project_inverts_pixel_rays_fisheye_wide(rng):
    _check_project_round_trip(Intrinsics(640, 480, 300.0, 300.0, 320.0, 240.0, "fisheye", FISHEYE_DIST), rng)


def test_project_inverts_pixel_rays_opencv_wide_angle(rng):
    _check_project_round_trip(Intrinsics(1280, 960, 900.0, 900.0, 640.0, 480.0, "opencv", OPENCV_DIST), rng)


@pytest.mark.parametrize("max_deg", [40.0, 90.0])
def test_fisheye_pixel_rays_have_the_equidistant_angle(max_deg):
    """Independent of `project`: the angle of each pixel ray off the axis must solve
    theta (1 + k1 t^2 + ...) = r_d, found here by bisection (theta_d is increasing here)."""
    intr = Intrinsics(640, 480, 300.0, 300.0, 320.0, 240.0, "fisheye", FISHEYE_DIST)
    k1, k2, k3, k4 = FISHEYE_DIST
    # pixels along the row just below the centre, from the centre out to the right border
    rays = intr.pixel_rays()[240, 320::20]
    r_d = np.hypot((np.arange(320, 640, 20) + 0.5 - 320.0) / 300.0, (240 + 0.5 - 240.0) / 300.0)
    lo, hi = np.zeros_like(r_d), np.full_like(r_d, np.pi / 2)
    for _ in range(80):
        mid = (lo + hi) / 2
        f = mid * (1 + k1 * mid ** 2 + k2 * mid ** 4 + k3 * mid ** 6 + k4 * mid ** 8)
        lo, hi = np.where(f < r_d, mid, lo), np.where(f < r_d, hi, mid)
    theta_true = (lo + hi) / 2
    theta = np.arccos(np.clip(rays[:, 2], -1, 1))
    # the azimuth is kept whatever the radial error
    np.testing.assert_allclose(np.arctan2(rays[:, 1], rays[:, 0]),
                               np.arctan2(0.5, np.arange(320, 640, 20) + 0.5 - 320.0), atol=1e-12)
    ok = theta_true < np.deg2rad(max_deg)
    assert ok.sum() >= 5
    np.testing.assert_allclose(theta[ok], theta_true[ok], rtol=0, atol=1e-9)


def test_project_points_behind_camera_are_nan():
    intr = Intrinsics(64, 48, 50.0, 50.0, 32.0, 24.0, "opencv", OPENCV_DIST)
    uv, z = intr.project(np.array([[0.1, 0.2, -3.0], [0.0, 0.0, 0.0], [0.1, 0.1, 2.0]]))
    assert np.isnan(uv[:2]).all() and np.isfinite(uv[2]).all()
    np.testing.assert_array_equal(z, [-3.0, 0.0, 2.0])


# --- from_fov and scaled -----------------------------------------------------------------------

@pytest.mark.parametrize("hfov", [30.0, 60.0, 90.0, 120.0])
def test_from_fov_horizontal_field_of_view(hfov):
    intr = Intrinsics.from_fov(800, 450, hfov)
    assert (intr.cx, intr.cy) == (400.0, 225.0) and intr.fx == intr.fy
    # A point at hfov/2 to the right / left on the horizon projects to the image's right / left edge.
    a = np.deg2rad(hfov / 2)
    uv, _ = intr.project(np.array([[np.sin(a), 0.0, np.cos(a)], [-np.sin(a), 0.0, np.cos(a)]]))
    np.testing.assert_allclose(uv, [[800.0, 225.0], [0.0, 225.0]], atol=1e-9)
    # and the edge-to-edge angle recomputed from fx
    np.testing.assert_allclose(np.degrees(2 * np.arctan(400.0 / intr.fx)), hfov, rtol=1e-12)


def _fovs(intr: Intrinsics):
    """Horizontal and vertical FOV in radians, measured at the image edges (any principal point)."""
    h = np.arctan(intr.cx / intr.fx) + np.arctan((intr.width - intr.cx) / intr.fx)
    v = np.arctan(intr.cy / intr.fy) + np.arctan((intr.height - intr.cy) / intr.fy)
    return h, v


@pytest.mark.parametrize("size", [(1920, 1280), (1920, 886), (1600, 900)])
def test_scaled_keeps_fov_and_principal_point_ratio(waymo_front, size):
    w, h = size
    intr = Intrinsics(w, h, waymo_front.fx, waymo_front.fy, waymo_front.cx * w / 1920, waymo_front.cy * h / 1280,
                      "opencv", waymo_front.dist)
    s = intr.scaled(0.25)
    assert (s.width, s.height) == (round(w / 4), round(h / 4))
    assert (s.model, s.dist) == (intr.model, intr.dist)
    np.testing.assert_allclose(_fovs(s), _fovs(intr), rtol=1e-12)
    np.testing.assert_allclose([s.cx / s.width, s.cy / s.height], [intr.cx / w, intr.cy / h], rtol=1e-12)
    # Same ray through the same relative image position (pixel corners scale exactly).
    p = np.array([[0.3, -0.2, 1.0], [-0.5, 0.25, 1.0]])
    uv, _ = intr.project(p)
    uvs, _ = s.project(p)
    np.testing.assert_allclose(uvs / [s.width, s.height], uv / [w, h], rtol=1e-12)


# --- validation ----------------------------------------------------------------------------------

@pytest.mark.parametrize("kwargs, words", [
    (dict(model="kannala"), ["distortion model", "kannala", "fisheye"]),
    (dict(model="opencv", dist=(0.1, 0.2, 0.3)), ["opencv", "expected 5", "got 3"]),
    (dict(model="fisheye", dist=(0.1, 0.2, 0.3, 0.4, 0.5)), ["fisheye", "expected 4", "got 5"]),
    (dict(model="pinhole", dist=(0.1,)), ["pinhole", "expected 0", "got 1"]),
    (dict(width=0), ["positive size"]),
    (dict(height=-4), ["positive size"]),
    (dict(fx=0.0), ["focal"]),
    (dict(fy=-10.0), ["focal"]),
    (dict(fx=float("nan")), ["focal"]),
])
def test_bad_intrinsics_raise_value_error_naming_the_problem(kwargs, words):
    base = dict(width=64, height=48, fx=50.0, fy=50.0, cx=32.0, cy=24.0)
    base.update(kwargs)
    with pytest.raises(ValueError) as exc:
        Intrinsics(**base)
    for w in words:
        assert w in str(exc.value), f"{w!r} not in {exc.value}"


@pytest.mark.parametrize("kwargs", [dict(cx=float("nan")), dict(cy=float("inf")), dict(fx=float("inf")),
                                    dict(model="opencv", dist=(float("nan"), 0.0, 0.0, 0.0, 0.0))])
def test_non_finite_intrinsics_are_rejected(kwargs):
    base = dict(width=64, height=48, fx=50.0, fy=50.0, cx=32.0, cy=24.0)
    base.update(kwargs)
    with pytest.raises(ValueError):
        Intrinsics(**base)


def test_points_beyond_the_fold_of_the_distortion_polynomial_do_not_project():
    # Waymo FRONT (k1 0.040, k2 -0.330): r (1 + k1 r^2 + k2 r^4) peaks at r = 0.90 (42 degrees).
    intr = Intrinsics(1920, 1280, 2055.6, 2055.6, 939.7, 641.1, "opencv", (0.0404, -0.330, 0.0, 0.0, 0.0))
    r = np.linspace(0, 2, 20001)
    rd = r * (1 + 0.0404 * r**2 - 0.330 * r**4)
    assert abs(intr.fold_limit - r[np.argmax(rd)]) < 1e-3
    far = np.array([[1.3, 0.0, 1.0]])  # 52 degrees off-axis: the polynomial gives r_d = 0.16
    xd, _ = intr.distort(far[:, 0] / far[:, 2], far[:, 1] / far[:, 2])
    assert 0 <= intr.fx * xd[0] + intr.cx < intr.width  # the polynomial alone folds it into the image
    assert np.all(np.isnan(intr.project(far)[0]))
    near = np.array([[np.sin(np.deg2rad(30)), 0.0, np.cos(np.deg2rad(30))]])
    assert np.all(np.isfinite(intr.project(near)[0]))
    # Every pixel's own ray projects back onto its centre (the whole image is inside the fold).
    rays = intr.pixel_rays()[::97, ::101].reshape(-1, 3)
    uv, _ = intr.project(rays)
    vv, uu = np.meshgrid(np.arange(0, 1280, 97) + 0.5, np.arange(0, 1920, 101) + 0.5, indexing="ij")
    assert np.allclose(uv, np.c_[uu.ravel(), vv.ravel()], atol=1e-6)
