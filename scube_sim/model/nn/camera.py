"""The camera model of `camera/model.py` in torch: lens distortion, its Jacobian, projection.

Same conventions (OpenCV camera frame: x right, y down, z forward; pixel centres at integer +
0.5) and the same formulas as `Intrinsics.distort` / `Intrinsics.project`, differentiable; a
parity test holds the two together. Used by the Gaussian renderer and the sky panorama.
"""

from __future__ import annotations

import math

import torch

from ...camera.model import Intrinsics

__all__ = ["distort", "distort_jacobian", "fold_limit", "project"]


def distort(x: torch.Tensor, y: torch.Tensor, model: str, coeffs):
    """Ideal normalised image coordinates -> distorted ones; `camera.model.Intrinsics.distort`
    in torch (pinhole: unchanged; opencv: [k1, k2, p1, p2, k3]; fisheye: [k1, k2, k3, k4])."""
    if model == "pinhole":
        return x, y
    if model == "opencv":
        k1, k2, p1, p2, k3 = coeffs
        r2 = x * x + y * y
        radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
        return (x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x),
                y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y)
    k1, k2, k3, k4 = coeffs
    r2 = x * x + y * y
    small = r2 < 1e-16
    rs = torch.sqrt(torch.where(small, torch.ones_like(r2), r2))  # no sqrt(0) in the backward: no NaN
    theta = torch.atan(rs)
    t2 = theta * theta
    scale = torch.where(small, torch.ones_like(r2), theta * (1 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4)))) / rs)
    return x * scale, y * scale


def distort_jacobian(x: torch.Tensor, y: torch.Tensor, model: str, coeffs) -> torch.Tensor:
    """(..., 2, 2) d(xd, yd) / d(x, y) of `distort`, analytic (differentiable itself)."""
    one, zero = torch.ones_like(x), torch.zeros_like(x)
    if model == "pinhole":
        return torch.stack([one, zero, zero, one], -1).reshape(x.shape + (2, 2))
    if model == "opencv":
        k1, k2, p1, p2, k3 = coeffs
        r2 = x * x + y * y
        radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
        drad = 2 * (k1 + r2 * (2 * k2 + 3 * k3 * r2))  # d(radial)/dx = drad * x
        j11 = radial + x * x * drad + 2 * p1 * y + 6 * p2 * x
        j12 = x * y * drad + 2 * p1 * x + 2 * p2 * y
        j22 = radial + y * y * drad + 6 * p1 * y + 2 * p2 * x
        return torch.stack([j11, j12, j12, j22], -1).reshape(x.shape + (2, 2))
    k1, k2, k3, k4 = coeffs
    r2 = x * x + y * y
    small = r2 < 1e-12
    rs = torch.sqrt(torch.where(small, torch.ones_like(r2), r2))
    theta = torch.atan(rs)
    t2 = theta * theta
    theta_d = theta * (1 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4))))
    dtheta_d = (1 + t2 * (3 * k1 + t2 * (5 * k2 + t2 * (7 * k3 + t2 * 9 * k4)))) / (1 + rs * rs)
    s = theta_d / rs
    ds_over_r = (dtheta_d * rs - theta_d) / rs**3  # s'(r) / r
    s = torch.where(small, one, s)
    ds_over_r = torch.where(small, zero, ds_over_r)
    return torch.stack([s + x * x * ds_over_r, x * y * ds_over_r, x * y * ds_over_r, s + y * y * ds_over_r],
                       -1).reshape(x.shape + (2, 2))


def fold_limit(model: str, coeffs) -> float:
    """The lens model's fold limit (`camera.model.Intrinsics.fold_limit`) for these coefficients."""
    if model == "pinhole":
        return math.inf
    c = [float(v) for v in coeffs]
    return Intrinsics(1, 1, 1.0, 1.0, 0.0, 0.0, model, c).fold_limit


def project(points_cam: torch.Tensor, K: torch.Tensor, model: str = "pinhole", coeffs=(), near: float = 1e-6):
    """(..., 3) camera-frame points -> ((..., 2) pixels, (...,) bool valid): in front of the
    camera (z > near) and within the lens's fold limit. Invalid points get finite placeholder
    pixels (no NaN in a backward pass), so mask them with `valid`. K (3, 3)."""
    if model != "pinhole" and len(coeffs) == 0:
        coeffs = (0.0,) * (5 if model == "opencv" else 4)
    z = points_cam[..., 2]
    front = z > near
    zs = torch.where(front, z, torch.ones_like(z))
    x, y = points_cam[..., 0] / zs, points_cam[..., 1] / zs
    xd, yd = distort(x, y, model, coeffs)
    valid = front
    limit = fold_limit(model, coeffs)
    if math.isfinite(limit):
        r = torch.sqrt(x * x + y * y)
        valid = valid & ((r if model == "opencv" else torch.atan(r)) <= limit)
    uv = torch.stack([K[0, 0] * xd + K[0, 2], K[1, 1] * yd + K[1, 2]], -1)
    return uv, valid
