"""Camera intrinsics with lens distortion: pixel rays and projection.

Camera frame (OpenCV): x right, y down, z forward; pixel (u, v) has its centre at integer + 0.5
coordinates measured from the image's top-left corner. Distortion models:
- ``pinhole``: none;
- ``opencv``: Brown-Conrady radial (k1, k2, k3) and tangential (p1, p2), OpenCV's order
  ``[k1, k2, p1, p2, k3]``;
- ``fisheye``: OpenCV's equidistant model ``theta_d = theta (1 + k1 t^2 + k2 t^4 + k3 t^6 + k4 t^8)``.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field

import numpy as np

from ..errors import InputError

DISTORTION_MODELS = ("pinhole", "opencv", "fisheye")
K_PIXEL_CENTRE_SHIFT = 0.5  # ours minus OpenCV's principal point: see `Intrinsics.from_k`


@functools.lru_cache(maxsize=64)
def _pixel_rays(intr: "Intrinsics") -> np.ndarray:
    return intr._compute_pixel_rays()


@functools.lru_cache(maxsize=64)
def _fold_limit(intr: "Intrinsics") -> float:
    """The ideal radius (opencv: r = |(x, y)|; fisheye: theta, radians) where the radial
    distortion polynomial stops increasing; inf if it never does within 89.9 degrees.

    Beyond it the polynomial turns back, so a point far off-axis would land inside the image:
    Waymo's cameras fold at ~42 degrees off-axis (their own camera model rejects those points)."""
    if intr.model == "pinhole" or not any(intr.dist):
        return np.inf
    if intr.model == "opencv":
        k1, k2, _, _, k3 = intr._coeffs()
        r = np.linspace(0.0, np.tan(np.deg2rad(89.9)), 200_001)
        r2 = r * r
        slope = 1 + r2 * (3 * k1 + r2 * (5 * k2 + r2 * 7 * k3))  # d(r * radial)/dr
    else:
        k1, k2, k3, k4 = intr._coeffs()
        r = np.linspace(0.0, np.deg2rad(89.9), 200_001)
        t2 = r * r
        slope = 1 + t2 * (3 * k1 + t2 * (5 * k2 + t2 * (7 * k3 + t2 * 9 * k4)))
    bad = np.flatnonzero(slope <= 0)
    return float(r[bad[0] - 1]) if bad.size else np.inf


@dataclass(frozen=True)
class Intrinsics:
    """width, height in pixels; fx, fy, cx, cy in pixels; distortion coefficients per `model`."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    model: str = "pinhole"
    dist: tuple[float, ...] = field(default_factory=tuple)

    def __post_init__(self):
        # Accept any sequence (numpy arrays too) but store a tuple: the camera is hashable.
        object.__setattr__(self, "dist", tuple(float(c) for c in np.ravel(self.dist)))
        if self.model not in DISTORTION_MODELS:
            raise InputError(f"distortion model: expected one of {DISTORTION_MODELS}, got {self.model!r}")
        if self.width <= 0 or self.height <= 0 or not (self.fx > 0 and self.fy > 0):
            raise InputError(f"intrinsics: need positive size and focal lengths, got {self}")
        if not np.all(np.isfinite([self.fx, self.fy, self.cx, self.cy, *self.dist])):
            raise InputError(f"intrinsics: focal lengths, principal point and distortion must be finite, got {self}")
        need = {"pinhole": 0, "opencv": 5, "fisheye": 4}[self.model]
        if len(self.dist) not in (0, need):
            raise InputError(f"distortion {self.model!r}: expected {need} coefficients, got {len(self.dist)}")

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0, self.cx], [0, self.fy, self.cy], [0, 0, 1.0]])

    @classmethod
    def from_k(cls, k, width: int, height: int, model: str = "pinhole", dist=()) -> "Intrinsics":
        """From a dataset's (3, 3) OpenCV-convention K, whose pixel centres sit at integers. Ours
        sit at integer + 0.5 (the top-left pixel spans [0, 1)), so cx, cy move by half a pixel
        (`K_PIXEL_CENTRE_SHIFT`) and pixel (i, j) of a render sees the ray of the real image's (i, j)."""
        k = np.asarray(k, np.float64)
        return cls(int(width), int(height), float(k[0, 0]), float(k[1, 1]), float(k[0, 2]) + K_PIXEL_CENTRE_SHIFT,
                   float(k[1, 2]) + K_PIXEL_CENTRE_SHIFT, model, dist)

    @classmethod
    def from_fov(cls, width: int, height: int, hfov_deg: float, **kw) -> "Intrinsics":
        """Square pixels, principal point at the centre, horizontal field of view in degrees."""
        f = 0.5 * width / np.tan(np.deg2rad(hfov_deg) / 2)
        return cls(width, height, f, f, width / 2, height / 2, **kw)

    def scaled(self, factor: float) -> "Intrinsics":
        """The same camera at `factor` times the resolution (e.g. 0.25 for training renders)."""
        w, h = max(1, round(self.width * factor)), max(1, round(self.height * factor))
        sx, sy = w / self.width, h / self.height
        return Intrinsics(w, h, self.fx * sx, self.fy * sy, self.cx * sx, self.cy * sy, self.model, self.dist)

    def to_dict(self) -> dict:
        return {"width": self.width, "height": self.height, "fx": self.fx, "fy": self.fy, "cx": self.cx,
                "cy": self.cy, "model": self.model, "dist": list(self.dist)}

    # --- distortion on normalised coordinates ------------------------------------------------
    def _coeffs(self) -> tuple[float, ...]:
        need = {"pinhole": 0, "opencv": 5, "fisheye": 4}[self.model]
        return self.dist if self.dist else (0.0,) * need

    def distort(self, x: np.ndarray, y: np.ndarray):
        """Ideal normalised image coordinates -> distorted ones."""
        if self.model == "pinhole" or (self.model == "opencv" and not any(self.dist)):
            return x, y
        if self.model == "opencv":
            k1, k2, p1, p2, k3 = self._coeffs()
            r2 = x * x + y * y
            radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
            xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
            yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
            return xd, yd
        # fisheye (equidistant): even with zero coefficients theta_d = atan(r), not r
        k1, k2, k3, k4 = self._coeffs()
        r = np.sqrt(x * x + y * y)
        theta = np.arctan(r)
        t2 = theta * theta
        theta_d = theta * (1 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4))))
        scale = np.where(r > 1e-12, theta_d / np.maximum(r, 1e-12), 1.0)
        return x * scale, y * scale

    def undistort(self, xd: np.ndarray, yd: np.ndarray, iterations: int = 30):
        """Distorted normalised coordinates -> ideal ones, by Newton's method (quadratic
        convergence, so strong barrel distortion and wide fisheye angles converge too)."""
        xd = np.asarray(xd, np.float64)
        yd = np.asarray(yd, np.float64)
        if self.model == "pinhole" or (self.model == "opencv" and not any(self.dist)):
            return xd, yd
        if self.model == "fisheye":
            k1, k2, k3, k4 = self._coeffs()
            theta_d = np.sqrt(xd * xd + yd * yd)
            theta = theta_d.copy()
            for _ in range(iterations):
                t2 = theta * theta
                f = theta * (1 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4)))) - theta_d
                df = 1 + t2 * (3 * k1 + t2 * (5 * k2 + t2 * (7 * k3 + t2 * 9 * k4)))
                theta = np.clip(theta - f / np.where(np.abs(df) > 1e-12, df, 1e-12), 0.0, np.pi / 2 - 1e-9)
                if np.abs(f).max(initial=0.0) < 1e-14:
                    break
            scale = np.where(theta_d > 1e-12, np.tan(theta) / np.maximum(theta_d, 1e-12), 1.0)
            return xd * scale, yd * scale
        k1, k2, p1, p2, k3 = self._coeffs()
        x, y = xd.copy(), yd.copy()
        for _ in range(iterations):
            r2 = x * x + y * y
            radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
            drad = 2 * k1 + r2 * (4 * k2 + 6 * k3 * r2)  # d(radial)/d(x) = drad * x
            ex = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x) - xd
            ey = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y - yd
            j11 = radial + x * x * drad + 2 * p1 * y + 6 * p2 * x
            j12 = x * y * drad + 2 * p1 * x + 2 * p2 * y
            j22 = radial + y * y * drad + 6 * p1 * y + 2 * p2 * x
            det = j11 * j22 - j12 * j12
            det = np.where(np.abs(det) > 1e-12, det, 1e-12)
            x = x - (j22 * ex - j12 * ey) / det
            y = y - (j11 * ey - j12 * ex) / det
            if max(np.abs(ex).max(initial=0.0), np.abs(ey).max(initial=0.0)) < 1e-14:
                break  # converged (quadratically): a few steps for real lenses
        return x, y

    # --- rays and projection -----------------------------------------------------------------
    def pixel_rays(self) -> np.ndarray:
        """(H, W, 3) float64 unit ray directions through the pixel centres, camera frame
        (cached per camera: read-only)."""
        return _pixel_rays(self)

    def _compute_pixel_rays(self) -> np.ndarray:
        u = np.arange(self.width) + 0.5
        v = np.arange(self.height) + 0.5
        uu, vv = np.meshgrid(u, v)
        x, y = self.undistort((uu - self.cx) / self.fx, (vv - self.cy) / self.fy)
        d = np.stack([x, y, np.ones_like(x)], axis=-1)
        d /= np.linalg.norm(d, axis=-1, keepdims=True)
        d.flags.writeable = False
        return d

    @property
    def fold_limit(self) -> float:
        """Largest ideal radius the lens model maps one to one (see `_fold_limit`)."""
        return _fold_limit(self)

    def project(self, points_cam: np.ndarray):
        """(N, 3) camera-frame points -> (N, 2) pixel coordinates and (N,) depth z; points behind
        the camera (z <= 0), or so far off-axis that the distortion polynomial folds back
        (`fold_limit`), get NaN pixels."""
        p = np.asarray(points_cam, np.float64)
        z = p[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            x, y = p[:, 0] / z, p[:, 1] / z
        xd, yd = self.distort(x, y)
        uv = np.stack([self.fx * xd + self.cx, self.fy * yd + self.cy], axis=1)
        uv[z <= 0] = np.nan
        limit = self.fold_limit
        if np.isfinite(limit):
            with np.errstate(invalid="ignore"):
                r = np.hypot(x, y)
                radius = r if self.model == "opencv" else np.arctan(r)
                uv[radius > limit] = np.nan
        return uv, z
