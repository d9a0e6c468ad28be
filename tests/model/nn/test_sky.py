"""The sky panorama against an analytic sky: five cameras (two with strong lens distortion) see
a known colour per direction; the panorama built from them, sampled at a yaw no input camera
looks along, gives that colour back (and a gradient, not a constant)."""

from __future__ import annotations

import math

import numpy as np
import torch

from scube_sim.model.nn.sky import (
    SkyDecoder,
    build_panorama,
    camera_ray_directions,
    panorama_directions,
    sample_panorama,
)

W, H = 64, 40
# OpenCV camera axes in the chunk frame: x right = -y, y down = -z, z forward = +x
R0 = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def sky_colour(d: torch.Tensor) -> torch.Tensor:
    """(..., 3) unit directions -> (3, ...) smooth RGB varying with elevation and azimuth."""
    phi = torch.atan2(d[..., 1], d[..., 0])
    return torch.stack([0.5 + 0.45 * d[..., 2], 0.5 + 0.4 * torch.cos(phi), 0.5 + 0.4 * torch.sin(phi)], 0)


def pose(yaw_deg: float, pitch_deg: float = 0.0, t=(0.0, 0.0, 0.0)) -> torch.Tensor:
    y, p = math.radians(yaw_deg), math.radians(pitch_deg)
    rz = np.array([[math.cos(y), -math.sin(y), 0], [math.sin(y), math.cos(y), 0], [0, 0, 1]])
    ry = np.array([[math.cos(p), 0, -math.sin(p)], [0, 1, 0], [math.sin(p), 0, math.cos(p)]])  # nose up
    m = np.eye(4)
    m[:3, :3] = rz @ ry @ R0
    m[:3, 3] = t
    return torch.tensor(m)


def rig(translations=None):
    f = 0.5 * W / math.tan(math.radians(40))  # 80 degrees across
    K = torch.tensor([[f, 0, W / 2 + 0.3], [0, f, H / 2 - 0.2], [0, 0, 1.0]])
    dist = torch.zeros(5, 5)
    dist[1] = torch.tensor([-0.3, 0.1, 0.001, -0.002, -0.02])  # strong barrel
    dist[3] = torch.tensor([0.1, -0.02, 0.0, 0.0, 0.0])
    rng = np.random.default_rng(0)
    poses = torch.stack([pose(72.0 * i, 8.0, rng.normal(0, 50, 3) if translations else (0, 0, 0)) for i in range(5)])
    images, sky = [], []
    for i in range(5):
        dirs = camera_ray_directions(K, dist[i], poses[i], H, W)
        ground = dirs[..., 2] < -0.05
        img = sky_colour(dirs.double()).float()
        img[:, ground] = 0.0  # ground must not leak into the sky
        images.append(img)
        sky.append(~ground)
    return torch.stack(images), torch.stack(sky), poses, K.expand(5, 3, 3), dist


def test_a_gradient_sky_is_recovered_at_a_novel_yaw():
    images, sky, poses, K, dist = rig()
    pano, weight = build_panorama(images, sky, poses, K, dist, 48, 96)
    assert pano.shape == (3, 48, 96) and weight.shape == (48, 96)
    assert 0.15 < float((weight > 0).float().mean()) < 0.5  # the band of sky the five cameras see
    novel = pose(36.0, 12.0)  # between the first two inputs, looking a little higher
    Kn = torch.tensor([[30.0, 0, 32], [0, 30.0, 20], [0, 0, 1]])
    dirs = camera_ray_directions(Kn, None, novel, H, W)
    seen = (sample_panorama((weight > 0).double()[None], dirs)[0] > 0.999) & (dirs[..., 2] > 0.05)
    assert float(seen.float().mean()) > 0.4
    got = sample_panorama(pano, dirs)
    want = sky_colour(dirs.double()).float()
    err = (got - want).abs()[:, seen]
    assert float(err.mean()) < 0.01 and float(err.max()) < 0.06, (float(err.mean()), float(err.max()))
    assert float(got[:, seen].std(1).min()) > 0.02  # a gradient, not a constant colour


def test_only_the_direction_matters():
    a = build_panorama(*rig(translations=False), 24, 48)
    b = build_panorama(*rig(translations=True), 24, 48)
    torch.testing.assert_close(a[0], b[0], rtol=0, atol=1e-6)
    torch.testing.assert_close(a[1], b[1], rtol=0, atol=1e-6)


def test_sampling_wraps_in_azimuth_and_hits_pixel_centres():
    hp, wp = 6, 12
    pano = torch.arange(hp * wp, dtype=torch.float64).reshape(1, hp, wp)
    dirs = panorama_directions(hp, wp, torch.float64)
    torch.testing.assert_close(sample_panorama(pano, dirs), pano)  # each centre gives its own pixel
    # straight backwards (phi = +-pi) lies between the last and the first column: their mean
    back = torch.tensor([[-math.cos(0.3), 0.0, math.sin(0.3)]], dtype=torch.float64)
    v = sample_panorama(pano, back)[0, 0]
    r = (math.pi / 2 - 0.3) / math.pi * hp - 0.5  # the row coordinate of elevation 0.3
    lo = int(math.floor(r))
    row = lambda c: (1 - (r - lo)) * pano[0, lo, c] + (r - lo) * pano[0, lo + 1, c]  # noqa: E731
    torch.testing.assert_close(v, 0.5 * (row(0) + row(wp - 1)))


def test_gradients_reach_sky_pixels_only_and_the_decoder_keeps_the_size():
    images, sky, poses, K, dist = rig()
    feats = images.clone().requires_grad_()
    pano, _ = build_panorama(feats, sky, poses, K, dist, 24, 48)
    pano.sum().backward()
    g = feats.grad.abs().sum(1)  # (N, H, W)
    deep_ground = torch.stack([camera_ray_directions(K[i], dist[i], poses[i], H, W)[..., 2] < -0.3 for i in range(5)])
    assert float(g[deep_ground].max()) == 0.0 and float(g[sky].sum()) > 0
    dec = SkyDecoder(3, 16)
    with torch.no_grad():
        out = dec(pano[None])
    assert out.shape == (1, 3, 24, 48) and float(out.min()) >= 0 and float(out.max()) <= 1
