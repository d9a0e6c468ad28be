"""Camera intrinsics with lens distortion: pixel rays and projection.

Camera frame (OpenCV): x right, y down, z forward; pixel (u, v) has its centre at integer + 0.5
coordinates measured from the image's top-left corner. Distortion models:
- ``pinhole``: none;
- ``opencv``: Brown-Conrady radial (k1, k2, k3) and tangential (p1, p2), OpenCV's order
  ``[k1, k2, p1, p2, k3]``;
- ``fisheye``: OpenCV's equidistant model ``theta_d = theta (1 + k1 t^2 + k2 t^4 + k3 t^6 + k4 t^8)``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

DISTORTION_MODELS = ("pinhole", "opencv", "fisheye")


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
        if self.model not in DISTORTION_MODELS:
            raise ValueError(f"distortion model: expected one of {DISTORTION_MODELS}, got {self.model!r}")
        if self.width <= 0 or self.height <= 0 or not (self.fx > 0 and self.fy > 0):
            raise ValueError(f"intrinsics: need positive size and focal lengths, got {self}")
        need = {"pinhole": 0, "opencv": 5, "fisheye": 4}[self.model]
        if len(self.dist) not in (0, need):
            raise ValueError(f"distortion {self.model!r}: expected {need} coefficients, got {len(self.dist)}")

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0, self.cx], [0, self.fy, self.cy], [0, 0, 1.0]])

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
    def distort(self, x: np.ndarray, y: np.ndarray):
        """Ideal normalised image coordinates -> distorted ones."""
        if self.model == "pinhole" or not self.dist or not np.any(self.dist):
            return x, y
        if self.model == "opencv":
            k1, k2, p1, p2, k3 = self.dist
            r2 = x * x + y * y
            radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
            xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
            yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
            return xd, yd
        k1, k2, k3, k4 = self.dist
        r = np.sqrt(x * x + y * y)
        theta = np.arctan(r)
        t2 = theta * theta
        theta_d = theta * (1 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4))))
        scale = np.where(r > 1e-12, theta_d / np.maximum(r, 1e-12), 1.0)
        return x * scale, y * scale

    def undistort(self, xd: np.ndarray, yd: np.ndarray, iterations: int = 20):
        """Distorted normalised coordinates -> ideal ones (fixed-point iteration, as OpenCV)."""
        if self.model == "pinhole" or not self.dist or not np.any(self.dist):
            return xd, yd
        x, y = xd.copy(), yd.copy()
        for _ in range(iterations):
            xe, ye = self.distort(x, y)
            x, y = x + (xd - xe), y + (yd - ye)
        return x, y

    # --- rays and projection -----------------------------------------------------------------
    def pixel_rays(self) -> np.ndarray:
        """(H, W, 3) float64 unit ray directions through the pixel centres, camera frame."""
        u = np.arange(self.width) + 0.5
        v = np.arange(self.height) + 0.5
        uu, vv = np.meshgrid(u, v)
        x, y = self.undistort((uu - self.cx) / self.fx, (vv - self.cy) / self.fy)
        d = np.stack([x, y, np.ones_like(x)], axis=-1)
        return d / np.linalg.norm(d, axis=-1, keepdims=True)

    def project(self, points_cam: np.ndarray):
        """(N, 3) camera-frame points -> (N, 2) pixel coordinates and (N,) depth z; points behind
        the camera (z <= 0) get NaN pixels."""
        p = np.asarray(points_cam, np.float64)
        z = p[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            x, y = p[:, 0] / z, p[:, 1] / z
        xd, yd = self.distort(x, y)
        uv = np.stack([self.fx * xd + self.cx, self.fy * yd + self.cy], axis=1)
        uv[z <= 0] = np.nan
        return uv, z
