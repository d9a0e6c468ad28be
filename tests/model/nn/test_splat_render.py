"""The CPU Gaussian renderer against an independent float64 per-pixel oracle (projection by
`camera.model.Intrinsics.project`, its Jacobian by finite differences, compositing one Gaussian
at a time), its gradients by `gradcheck`, its projection against gsplat's own pure-torch
implementation, and at the extremes (huge and tiny scales, zero quaternions, Gaussians behind or
at the camera)."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest
import torch

from scube_sim.camera.model import Intrinsics
from scube_sim.model.nn.camera import distort, distort_jacobian
from scube_sim.model.nn.splat_render import project_gaussians, rasterization

W, H = 40, 24  # three by two tiles of 16, the right and bottom ones partial


def random_scene(seed: int, n: int = 40):
    """Gaussians scattered in front of (and a few behind) a camera at the origin looking down +z."""
    g = torch.Generator().manual_seed(seed)
    means = torch.stack([torch.empty(n).uniform_(-3, 3, generator=g), torch.empty(n).uniform_(-2, 2, generator=g),
                         torch.empty(n).uniform_(-1, 9, generator=g)], 1).double()
    quats = torch.randn(n, 4, generator=g, dtype=torch.float64)
    scales = torch.exp(torch.empty(n, 3, dtype=torch.float64).uniform_(-2.5, -0.5, generator=g))
    opac = torch.empty(n, dtype=torch.float64).uniform_(0.05, 0.99, generator=g)
    colors = torch.rand(n, 3, generator=g, dtype=torch.float64)
    return means, quats, scales, opac, colors


def camera(model="pinhole"):
    dist = {"pinhole": (), "opencv": (-0.28, 0.09, 0.001, -0.0005, -0.012), "fisheye": (0.05, -0.01, 0.002, 0.0)}[model]
    intr = Intrinsics(W, H, 30.0, 31.0, 20.3, 11.7, model, dist)
    pose = np.eye(4)
    ang = np.deg2rad(7.0)
    pose[:3, :3] = [[np.cos(ang), 0, np.sin(ang)], [0, 1, 0], [-np.sin(ang), 0, np.cos(ang)]]
    pose[:3, 3] = [0.2, -0.1, -0.5]  # world-to-camera
    return intr, pose


def oracle(intr: Intrinsics, viewmat, means, quats, scales, opac, colors, bg, eps2d=0.3):
    """float64 numpy, one pixel and one Gaussian at a time (gsplat's rules; see splat_render)."""
    W, H = intr.width, intr.height
    R, T = viewmat[:3, :3], viewmat[:3, 3]
    q = quats / np.linalg.norm(quats, axis=1, keepdims=True)
    out_c = np.zeros((H, W, 3))
    out_a = np.zeros((H, W))
    out_d = np.zeros((H, W))
    gauss = []
    for i in range(len(means)):
        t = R @ means[i] + T
        if not (0.01 < t[2] < 1e10):
            continue
        w, x, y, z = q[i]
        rq = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                       [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                       [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])
        cov = R @ rq @ np.diag(scales[i] ** 2) @ rq.T @ R.T
        uv, _ = intr.project(t[None])
        if not np.all(np.isfinite(uv)):
            continue
        # the Jacobian of the whole projection, by central differences, at gsplat's clamped point
        tanx, tany = 0.5 * W / intr.fx, 0.5 * H / intr.fy
        xj = np.clip(t[0] / t[2], -(intr.cx / intr.fx + 0.3 * tanx), (W - intr.cx) / intr.fx + 0.3 * tanx)
        yj = np.clip(t[1] / t[2], -(intr.cy / intr.fy + 0.3 * tany), (H - intr.cy) / intr.fy + 0.3 * tany)
        tj = np.array([xj * t[2], yj * t[2], t[2]])
        jac = np.zeros((2, 3))
        for k in range(3):
            h = 1e-6 * max(1.0, abs(tj[k]))
            e = np.zeros(3)
            e[k] = h
            jac[:, k] = (intr.project((tj + e)[None])[0][0] - intr.project((tj - e)[None])[0][0]) / (2 * h)
        c2 = jac @ cov @ jac.T + eps2d * np.eye(2)
        r = np.ceil(3.33 * np.sqrt(np.diag(c2)))
        if not (uv[0, 0] + r[0] > 0 and uv[0, 0] - r[0] < W and uv[0, 1] + r[1] > 0 and uv[0, 1] - r[1] < H):
            continue
        gauss.append((t[2], uv[0], np.linalg.inv(c2), opac[i], colors[i]))
    gauss.sort(key=lambda g: g[0])
    for v in range(H):
        for u in range(W):
            p = np.array([u + 0.5, v + 0.5])
            tr, col, dep = 1.0, np.zeros(3), 0.0
            for z, m, inv, o, c in gauss:
                d = p - m
                sigma = 0.5 * d @ inv @ d
                if sigma < 0:
                    continue
                a = min(0.999, o * np.exp(-sigma))
                if a < 1 / 255:
                    continue
                if tr * (1 - a) <= 1e-4:
                    break
                col += a * tr * c
                dep += a * tr * z
                tr *= 1 - a
            out_c[v, u] = col + tr * bg
            out_a[v, u] = 1 - tr
            out_d[v, u] = dep
    return out_c, out_a, out_d


def render(intr, viewmat, scene, dtype=torch.float64, bg=None, mode="RGB+D", **kw):
    means, quats, scales, opac, colors = (x.to(dtype) for x in scene)
    K = torch.tensor(intr.K, dtype=dtype)[None]
    model = intr.model
    dist = torch.tensor([intr.dist], dtype=torch.float64) if model != "pinhole" else None
    return rasterization(means, quats, scales, opac, colors, torch.tensor(viewmat, dtype=dtype)[None], K,
                         intr.width, intr.height,
                         backgrounds=None if bg is None else torch.tensor(bg, dtype=dtype)[None],
                         render_mode=mode, camera_model=model, dist_coeffs=dist, **kw)


@pytest.mark.parametrize("model", ["pinhole", "opencv", "fisheye"])
def test_matches_the_float64_oracle(model):
    intr, viewmat = camera(model)
    scene = random_scene(1)
    bg = np.array([0.1, 0.4, 0.7])
    want_c, want_a, want_d = oracle(intr, viewmat, *(x.numpy() for x in scene), bg)
    assert 0.2 < want_a.mean() < 0.999 and want_a.max() - want_a.min() > 0.2  # cover that varies
    for dtype, tol in ((torch.float64, 1e-5), (torch.float32, 1e-4)):
        img, alpha, meta = render(intr, viewmat, scene, dtype, bg)
        np.testing.assert_allclose(img[0, ..., :3].double().numpy(), want_c, atol=tol)
        np.testing.assert_allclose(alpha[0, ..., 0].double().numpy(), want_a, atol=tol)
        np.testing.assert_allclose(img[0, ..., 3].double().numpy(), want_d, atol=tol * 10)  # metres
    assert meta["tiles_hit"] == [6]


def test_expected_depth_and_a_scene_with_nothing_in_view():
    intr, viewmat = camera()
    scene = random_scene(2)
    img, alpha, _ = render(intr, viewmat, scene, mode="RGB+ED")
    d, _, _ = render(intr, viewmat, scene, mode="D")
    a = alpha[0, ..., 0]
    covered = a > 1e-3
    torch.testing.assert_close(img[0, ..., 3][covered], d[0, ..., 0][covered] / a[covered])
    behind = [x.clone() for x in scene]
    behind[0][:, 2] = -5.0  # all behind the camera
    img, alpha, meta = render(intr, viewmat, behind, bg=[0.3, 0.2, 0.1], mode="RGB")
    assert meta["tiles_hit"] == [0] and float(alpha.abs().max()) == 0.0
    torch.testing.assert_close(img[0], torch.tensor([0.3, 0.2, 0.1], dtype=torch.float64).expand(H, W, 3))


def test_gradients_by_gradcheck():
    """Three overlapping Gaussians that cover the whole 10 x 8 image (no pixel near a threshold),
    float64: analytic gradients of colour, alpha and depth to every input equal finite differences."""
    from torch.autograd import gradcheck

    w, h = 10, 8
    intr = Intrinsics(w, h, 12.0, 12.0, 5.0, 4.0)
    means = torch.tensor([[0.1, -0.1, 4.0], [-0.3, 0.2, 5.0], [0.2, 0.3, 6.0]], dtype=torch.float64,
                         requires_grad=True)
    quats = torch.tensor([[1.0, 0.1, 0.2, 0.0], [0.9, -0.2, 0.1, 0.3], [0.5, 0.5, 0.5, 0.5]], dtype=torch.float64,
                         requires_grad=True)
    scales = torch.tensor([[1.5, 1.0, 0.5], [1.0, 2.0, 0.7], [2.0, 1.5, 1.0]], dtype=torch.float64,
                          requires_grad=True)
    opac = torch.tensor([0.4, 0.5, 0.6], dtype=torch.float64, requires_grad=True)
    colors = torch.rand(3, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(0)).requires_grad_()
    K = torch.tensor(intr.K, dtype=torch.float64)[None]
    vm = torch.eye(4, dtype=torch.float64)[None]

    def f(m, q, s, o, c):
        img, alpha, _ = rasterization(m, q, s, o, c, vm, K, w, h, render_mode="RGB+D", use_checkpoint=True)
        return img, alpha

    assert gradcheck(f, (means, quats, scales, opac, colors), eps=1e-6, atol=1e-5, rtol=1e-4)


def _gsplat_torch_impl():
    spec = importlib.util.find_spec("gsplat")
    if spec is None or not spec.submodule_search_locations:
        pytest.skip("gsplat is not installed (pip install 'scube-sim[test]')")
    path = Path(next(iter(spec.submodule_search_locations))) / "cuda" / "_torch_impl.py"
    mod_spec = importlib.util.spec_from_file_location("gsplat_torch_impl", path)  # not gsplat/__init__ (CUDA)
    mod = importlib.util.module_from_spec(mod_spec)
    mod_spec.loader.exec_module(mod)
    return mod


def test_projection_matches_gsplats_pure_torch_helpers():
    impl = _gsplat_torch_impl()
    intr, viewmat = camera()
    means, quats, scales, _, _ = random_scene(3, n=500)
    means[:, 0] *= 3  # many off-screen, several past gsplat's 30 % clamp
    vm = torch.tensor(viewmat)[None]
    K = torch.tensor(intr.K)[None]
    ours = project_gaussians(means, quats, scales, vm, K, W, H)
    covars, _ = impl._quat_scale_to_covar_preci(quats, scales, compute_covar=True, compute_preci=False, triu=False)
    radii, means2d, depths, conics, _ = impl._fully_fused_projection(means, covars, vm, K, W, H)
    shown = (radii > 0).all(-1)
    assert 50 < int(shown.sum()) < 450
    torch.testing.assert_close(ours.radii, radii.to(torch.int32))
    torch.testing.assert_close(ours.means2d[shown], means2d[shown], rtol=1e-10, atol=1e-9)
    torch.testing.assert_close(ours.conics[shown], conics[shown], rtol=1e-9, atol=1e-12)
    torch.testing.assert_close(ours.depths, depths)


@pytest.mark.parametrize("model", ["opencv", "fisheye"])
def test_distortion_equals_the_camera_model_and_its_jacobian_autograd(model):
    intr, _ = camera(model)
    g = torch.Generator().manual_seed(4)
    x = torch.empty(300, dtype=torch.float64).uniform_(-0.8, 0.8, generator=g)
    y = torch.empty(300, dtype=torch.float64).uniform_(-0.6, 0.6, generator=g)
    x[0] = y[0] = 0.0  # the axis itself (fisheye: r = 0)
    xd, yd = distort(x, y, model, intr.dist)
    wx, wy = intr.distort(x.numpy(), y.numpy())
    np.testing.assert_allclose(xd.numpy(), wx, rtol=0, atol=1e-14)
    np.testing.assert_allclose(yd.numpy(), wy, rtol=0, atol=1e-14)
    jac = distort_jacobian(x, y, model, intr.dist)
    for i in (0, 1, 17, 299):
        want = torch.autograd.functional.jacobian(lambda p: torch.stack(distort(p[0], p[1], model, intr.dist)),
                                                  torch.stack([x[i], y[i]]))
        torch.testing.assert_close(jac[i], want, rtol=1e-9, atol=1e-12)


def test_extremes_render_and_backpropagate_without_nan():
    """Scale logits of +-20 (4.9e8 m and 2e-9 m), zero and near-zero quaternions, Gaussians behind
    the camera, exactly at it and on its plane: finite images and finite gradients everywhere."""
    intr, viewmat = camera()
    means = torch.tensor([[0.0, 0.0, 5.0], [0.5, 0.2, 4.0], [0.0, 0.0, -3.0], [0.2, -0.5, 0.5], [0.0, 0.0, 0.0],
                          [1.0, 0.0, 1e-9], [-0.4, 0.1, 6.0]], dtype=torch.float32, requires_grad=True)
    log_s = torch.tensor([[20.0] * 3, [-20.0] * 3, [0.0] * 3, [20.0, -20.0, 0.0], [1.0] * 3, [0.0] * 3, [-1.0] * 3])
    log_s.requires_grad_()
    quats = torch.tensor([[0.0, 0.0, 0.0, 0.0], [1e-30, 0, 0, 0], [1.0, 0, 0, 0], [0.3, 0.1, 0.2, 0.9],
                          [1.0, 0, 0, 0], [1.0, 0, 0, 0], [1e-20, 1e-20, 0, 0]], requires_grad=True)
    opac = torch.full((7,), 0.8, requires_grad=True)
    colors = torch.rand(7, 3, generator=torch.Generator().manual_seed(5)).requires_grad_()
    vm = torch.tensor(viewmat, dtype=torch.float32)[None]
    K = torch.tensor(intr.K, dtype=torch.float32)[None]
    img, alpha, _ = rasterization(means, quats, torch.exp(log_s), opac, colors, vm, K, W, H, render_mode="RGB+ED")
    assert torch.isfinite(img).all() and torch.isfinite(alpha).all()
    assert float(alpha.detach().max()) > 0.5  # the huge one covers the view
    (img.sum() + alpha.sum()).backward()
    for t in (means, log_s, quats, opac, colors):
        assert torch.isfinite(t.grad).all()


def test_a_distorted_camera_backpropagates():
    """Gradients through the lens model (the fold-limit cull once broke autograd in place)."""
    intr, viewmat = camera("opencv")
    scene = [x.clone().requires_grad_() for x in random_scene(6, n=30)]
    img, alpha, _ = render(intr, viewmat, scene, torch.float64, bg=[0.2, 0.2, 0.2])
    (img.sum() + alpha.sum()).backward()
    for t in scene:
        assert t.grad is not None and torch.isfinite(t.grad).all()
    assert float(scene[0].grad.abs().sum()) > 0
