"""A sensor's intensity response: measured reflectance <-> the intensity the sensor reports.

One function (`IntensityResponse` in `lidar/config.py`), used both ways:
- forward, by the LiDAR model, for hits on surfaces with measured reflectance:
  ``I = clip(gain * channel_gain[c] * rho * cos(theta)**a * min(1, (r0 / r)**b), 0, 1)``,
  then, where the sensor has the Velodyne driver's per-laser table, that correction on the
  0-255 byte scale;
- inverse, by the build (`reconstruct.py`), to turn each real return into a reflectance estimate.

I is on the common 0-1 scale: a fraction of the sensor's full-scale reading (a dataset's
`intensity / intensity_max`); rho is Lambertian-equivalent reflectance (1 = a white diffuse
target; retroreflectors read above 1). theta is the angle between the beam and the surface
normal, r the range in metres, c the channel (laser) index in the pattern's order; a channel
outside the tables (e.g. unknown: -1) gets gain 1 and no per-laser correction.
"""

from __future__ import annotations

import numpy as np

from .config import Intensity

FULL_SCALE_BYTES = 255.0  # the Velodyne driver's intensity byte
# The inverse divides by cos(theta)**a: below this cosine (beyond ~87 degrees) a normal estimate
# is too uncertain to divide by, so the division stops growing there.
MIN_COS = 0.05


class Response:
    """The response of one sensor (`LidarConfig.intensity`), vectorised over returns."""

    def __init__(self, intensity: Intensity):
        self.config = intensity
        r = intensity.response
        self.gain = float(r.gain)
        self.incidence_exponent = float(r.incidence_exponent)
        self._channel_gain = None if r.channel_gain is None else np.asarray(r.channel_gain, np.float64)
        v = r.velodyne
        if v is None:
            self._velodyne = None
        else:
            n = len(v.focal_distance)
            lo = np.zeros(n) if v.min_intensity is None else np.asarray(v.min_intensity, np.float64)
            hi = np.full(n, FULL_SCALE_BYTES) if v.max_intensity is None else np.asarray(v.max_intensity, np.float64)
            focal_offset = 256.0 * (1.0 - np.asarray(v.focal_distance, np.float64) / 13100.0) ** 2
            self._velodyne = (focal_offset, np.asarray(v.focal_slope, np.float64), lo, hi,
                              float(v.distance_resolution_m))

    @staticmethod
    def _table(table: np.ndarray | None, channel: np.ndarray, default: float) -> np.ndarray:
        """Per-return values of a per-channel table (`default` outside it)."""
        c = np.asarray(channel, np.int64)
        if table is None:
            return np.full(c.shape, default)
        ok = (c >= 0) & (c < table.shape[0])
        return np.where(ok, table[np.clip(c, 0, table.shape[0] - 1)], default)

    def _shape(self, cos_inc, rng, channel) -> np.ndarray:
        """gain x channel gain x cos^a x range fall-off (N,)."""
        ic = self.config
        cos_inc = np.clip(np.asarray(cos_inc, np.float64), 0.0, 1.0)
        with np.errstate(divide="ignore"):
            fall = np.minimum(1.0, (ic.reference_range_m / np.maximum(np.asarray(rng, np.float64), 1e-6))
                              ** ic.falloff_exponent)
        return self.gain * self._table(self._channel_gain, channel, 1.0) * cos_inc ** self.incidence_exponent * fall

    def _focal(self, rng, channel):
        """The Velodyne per-laser correction (N,) in bytes, and its clamp (lo, hi) (N,) each."""
        offset, slope, lo, hi, res = self._velodyne
        d = np.asarray(rng, np.float64) / res
        term = self._table(slope, channel, 0.0) * np.abs(self._table(offset, channel, 256.0)
                                                         - 256.0 * (1.0 - d / 65535.0) ** 2)
        return term, self._table(lo, channel, 0.0), self._table(hi, channel, FULL_SCALE_BYTES)

    def forward(self, rho, cos_inc, rng, channel) -> np.ndarray:
        """Reported intensity (N,) float64 on the 0-1 scale for reflectance rho (N,), |cos| of the
        incidence angle (N,), range (N,) metres and channel (N,) int."""
        i = np.clip(np.asarray(rho, np.float64) * self._shape(cos_inc, rng, channel), 0.0, 1.0)
        if self._velodyne is not None:
            term, lo, hi = self._focal(rng, channel)
            i = np.clip(i * FULL_SCALE_BYTES + term, lo, hi) / FULL_SCALE_BYTES
        return np.clip(i, 0.0, 1.0)

    def inverse(self, intensity, cos_inc, rng, channel) -> np.ndarray:
        """Reflectance estimates (N,) float64 >= 0 of returns of reported intensity (N,) on the 0-1
        scale; cos_inc is floored at MIN_COS. Readings at the sensor's clamps give bounds only."""
        i = np.asarray(intensity, np.float64)
        if self._velodyne is not None:
            term, _, _ = self._focal(rng, channel)
            i = (i * FULL_SCALE_BYTES - term) / FULL_SCALE_BYTES
        shape = self._shape(np.maximum(np.asarray(cos_inc, np.float64), MIN_COS), rng, channel)
        return np.maximum(i, 0.0) / shape
