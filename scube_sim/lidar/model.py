"""The LiDAR model: a scan pattern traced through a scene, with the sensor's physical effects.

One sweep, step by step (each effect only when its config asks for it):
1. rays of the scan pattern (sensor frame), split into sub-rays across the beam divergence;
2. the sensor pose at each ray's fire time (motion distortion: SLERP/lerp between the sweep's
   start and end poses, or a pose function), rays to the world frame;
3. the ego-body box blocks rays; the tracer finds the nearest surface within the max range;
4. intensity = reflectivity x cos(incidence) x range fall-off; on surfaces with measured
   reflectance (the VoxSplat `reflectance` channel) the sensor's own response instead
   (`intensity.response`, `lidar/response.py`); sub-ray hits form echoes, and the return mode
   picks one or two per pulse;
5. drops (min range, random, grazing, weak, dark-and-far, a fitted drop model), range noise,
   quantisation;
6. points in the sensor frame at their own fire time ('raw') or at the sweep's reference
   instant ('compensated').
Randomness comes from one seeded generator: the same seed gives the same sweep, bit for bit.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ..config import ConfigError
from ..errors import InputError
from ..labels import LABEL_IDS, LABEL_REFLECTIVITY
from ..raytrace.compose import nearest_hits
from ..raytrace.tracer import Tracer
from ..transforms import (
    PoseFn,
    check_pose,
    check_poses,
    interpolate_poses,
    invert_pose,
    rotate_vectors,
    transform_points,
)
from .config import LidarConfig, check_rays_per_sweep
from .drop import DropModel
from .pattern import ScanPattern, make_pattern
from .response import Response

POINT_DTYPE = np.dtype([
    ("x", np.float32), ("y", np.float32), ("z", np.float32), ("intensity", np.float32),
    ("ring", np.uint16), ("time", np.float32), ("range", np.float32), ("azimuth", np.float32),
    ("label", np.int16), ("instance", np.int32), ("column", np.int32), ("return_id", np.uint8),
])
"""One LiDAR return. x y z metres in the output frame (sensor frame, see Motion); intensity in
model units x output_scale (on surfaces with measured reflectance: the sensor's 0-1 scale); ring: channel index; time: seconds after the sweep start; range:
metres from the beam origin; azimuth: radians, beam direction CCW from +x; label: semantic id;
instance: actor id (0 = static scene); column: firing column; return_id: 0 first/only, 1 second."""

PROVENANCE_FIELDS = [("observed", np.uint8), ("confidence", np.float32)]
CONVERTED_POINT_DTYPE = np.dtype(POINT_DTYPE.descr + PROVENANCE_FIELDS)
"""A return from a scene that holds inferred surfaces (a converted VoxSplat): POINT_DTYPE and
observed (1: an input camera saw the voxel the return came from, or the surface was not inferred:
a mesh, an actor, a ground-truth or measured VoxSplat; 0: the converter filled it in) and
confidence (the converter's per-voxel confidence, metadata ``confidence_kind``; 1 where nothing
was inferred). A sweep has these fields only when its scene holds such surfaces."""


def point_dtype(provenance: bool) -> np.dtype:
    """The sweep's point records: CONVERTED_POINT_DTYPE where the scene holds inferred surfaces."""
    return CONVERTED_POINT_DTYPE if provenance else POINT_DTYPE


def scene_has_provenance(scene) -> bool:
    """Whether a Tracer, a list of them, or a time-aware scene holds inferred surfaces."""
    if isinstance(scene, (list, tuple)):
        return any(scene_has_provenance(s) for s in scene)
    return bool(getattr(scene, "has_provenance", False))



@dataclass
class Sweep:
    """One sweep's returns and where it was taken.

    points: structured POINT_DTYPE array, in firing order. t_start / t_end: absolute seconds.
    pose_start / pose_end: (4, 4) sensor-to-world poses at those instants; pose_reference: the
    pose of the output frame (identity-relative to the points: world = pose_reference @ p for
    compensated output; for raw output each point has its own pose at its own time).
    """

    points: np.ndarray
    t_start: float
    t_end: float
    pose_start: np.ndarray
    pose_end: np.ndarray
    pose_reference: np.ndarray
    output: str
    sensor: str
    channels: int
    columns: int
    ring_elevation_deg: np.ndarray
    num_rays: int

    def __len__(self) -> int:
        return int(self.points.shape[0])

    def xyz(self) -> np.ndarray:
        """(N, 3) float32 points in the output frame."""
        p = self.points
        return np.stack([p["x"], p["y"], p["z"]], axis=1)

    def pixels(self, points: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Each point's (row, column) in `range_image` (rows by decreasing elevation): two (N,)
        int64 arrays, for `points` (default all of this sweep's). Spinning patterns only."""
        if self.columns <= 0:
            raise InputError("range_image: needs a spinning pattern (an emitter table has no columns)")
        p = self.points if points is None else points
        row_of_ring = np.empty(self.channels, np.int64)
        row_of_ring[np.argsort(-self.ring_elevation_deg, kind="stable")] = np.arange(self.channels)
        return row_of_ring[p["ring"]], p["column"].astype(np.int64)

    def range_image(self, field: str = "range", return_id: int = 0) -> np.ndarray:
        """(rings, columns) float32 view, rows by decreasing elevation (top beam first), NaN
        where a ray gave no return. Spinning patterns only."""
        p = self.points[self.points["return_id"] == return_id]
        rows, cols = self.pixels(p)
        img = np.full((self.channels, self.columns), np.nan, np.float32)
        img[rows, cols] = p[field]
        return img


def _luminance(rgb: np.ndarray) -> np.ndarray:
    return (0.2126 * rgb[:, 0] + 0.7152 * rgb[:, 1] + 0.0722 * rgb[:, 2]).astype(np.float64)


def _subray_offsets(samples: int, divergence_rad: float):
    """Deterministic footprint samples: centre plus a Vogel (sunflower) spiral over the disc of
    half-angle divergence/2. Returns angular radius (S,), polar angle (S,), weights (S,) summing
    to 1 from a Gaussian beam profile whose 1/e^2 radius is the disc edge."""
    if samples == 1 or divergence_rad == 0:
        return np.zeros(1), np.zeros(1), np.ones(1)
    half = 0.5 * divergence_rad
    i = np.arange(samples)
    rho = half * np.sqrt(i / (samples - 1))
    phi = i * np.pi * (3.0 - np.sqrt(5.0))
    w = np.exp(-2.0 * (rho / half) ** 2)
    return rho, phi, w / w.sum()


def _perp_basis(d: np.ndarray):
    """Two unit vectors perpendicular to each (N, 3) unit direction."""
    ref = np.where(np.abs(d[:, 2:3]) < 0.9, np.array([[0.0, 0.0, 1.0]]), np.array([[1.0, 0.0, 0.0]]))
    u = np.cross(d, ref)
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    return u, np.cross(d, u)


def _ray_box(o: np.ndarray, d: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Entry distance of rays into an axis-aligned box (inf on a miss; 0 when starting inside)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / d
        t1 = (lo - o) * inv
        t2 = (hi - o) * inv
        tlo = np.nanmax(np.minimum(t1, t2), axis=1)
        thi = np.nanmin(np.maximum(t1, t2), axis=1)
    hit = (thi >= np.maximum(tlo, 0.0))
    return np.where(hit, np.maximum(tlo, 0.0), np.inf)


def class_reflectivity_table(config: LidarConfig) -> np.ndarray:
    """(NUM_LABELS,) float64 reflectivity per label id: labels.py's, with the config's
    `intensity.class_reflectivity` overrides."""
    refl = LABEL_REFLECTIVITY.astype(np.float64).copy()
    for name, rho in config.intensity.class_reflectivity.items():
        refl[LABEL_IDS[name]] = rho
    return refl


@dataclass
class SubRayHits:
    """What each sub-ray of a sweep met, (P*S,) per field for P pulses of S sub-rays: `hit` bool,
    `range` float64 metres, `label` int16, `instance`, `cos_incidence` |cos| of the incidence
    angle, `color` (P*S, 3), `measured` reflectance (NaN: none), and the scene's provenance
    `observed` and `confidence` (a converted scene's; the tracer fills defaults otherwise)."""

    hit: np.ndarray
    range: np.ndarray
    label: np.ndarray
    instance: np.ndarray
    cos_incidence: np.ndarray
    color: np.ndarray
    measured: np.ndarray
    observed: np.ndarray
    confidence: np.ndarray


@dataclass
class Echoes:
    """A sweep's echoes, (E,) per field: the `pulse` each belongs to, its `range` (metres), return
    `strength`, `rep` the sub-ray whose label and normal it takes, and `return_id` (0 the first or
    strongest, 1 a dual return's second)."""

    pulse: np.ndarray
    range: np.ndarray
    strength: np.ndarray
    rep: np.ndarray
    return_id: np.ndarray | None = None

    def __post_init__(self):
        if self.return_id is None:
            self.return_id = np.zeros(self.pulse.shape[0], np.uint8)

    def select(self, keep: np.ndarray) -> "Echoes":
        """The echoes where `keep` (E,) bool is set."""
        return Echoes(self.pulse[keep], self.range[keep], self.strength[keep], self.rep[keep], self.return_id[keep])


class Lidar:
    """A configured LiDAR. `scan` traces one sweep; the pattern is computed once."""

    def __init__(self, config: LidarConfig, pattern: ScanPattern | None = None):
        """pattern: optionally the rays to fire instead of the config's (e.g. `replay_pattern`)."""
        self.config = config
        self.pattern: ScanPattern = make_pattern(config) if pattern is None else pattern
        b = config.beam
        try:
            check_rays_per_sweep(len(self.pattern.time), b.samples, f"{config.name}: {len(self.pattern.time):,} rays")
        except ValueError as exc:
            raise ConfigError(str(exc)) from None
        self._sub_rho, self._sub_phi, self._sub_w = _subray_offsets(b.samples, b.divergence_mrad * 1e-3)
        self._class_reflectivity = class_reflectivity_table(config)
        self._response = Response(config.intensity)
        try:
            self._drop_model = None if config.drop.model is None else DropModel.load(config.drop.model)
        except ConfigError as exc:
            raise ConfigError(f"{config.name}: drop.model: {exc}") from None

    @property
    def mount(self) -> np.ndarray:
        """(4, 4) sensor-to-ego pose."""
        return self.config.mount.matrix()

    def sensor_pose(self, ego_pose: np.ndarray) -> np.ndarray:
        """Sensor-to-world pose for an ego-to-world pose (applies the mounting extrinsic)."""
        return check_pose(ego_pose, "ego_pose") @ self.mount

    def scan(
        self,
        tracer: Tracer | list[Tracer],
        pose_start: np.ndarray,
        pose_end: np.ndarray | None = None,
        *,
        pose_fn: PoseFn | None = None,
        t_start: float = 0.0,
        seed: int = 0,
    ) -> Sweep:
        """Trace one sweep.

        tracer: a Tracer, several (the nearest hit counts), or a scene whose `trace_world` takes
        the rays' absolute fire times (`accepts_times`, e.g. `sim.SimScene` with actors).
        pose_start / pose_end: (4, 4) float64 sensor-to-world poses at the sweep's start and end
        (end defaults to start: a static sensor). pose_fn: alternatively, absolute times (N,) ->
        (N, 4, 4) sensor-to-world poses; asked once for the sweep's ends, then once with the
        distinct fire times (ascending; pulses fired together share a pose). t_start: absolute
        seconds of the first fire.
        """
        cfg, pat = self.config, self.pattern
        t_end = t_start + pat.period_s
        pose_start, pose_end = self._end_poses(pose_start, pose_end, pose_fn, t_start, t_end)
        if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
            raise InputError(f"seed: expected a non-negative integer, got {seed!r}")
        rng = np.random.default_rng(seed)
        d_sub, o_sub, t_sub = self._sub_rays()
        static = pose_fn is None and np.array_equal(pose_start, pose_end)
        o_w, d_w, poses = self._world_rays(d_sub, o_sub, static, pose_start, pose_end, pose_fn, t_start)
        sub = self._trace(tracer, o_w, d_w, o_sub, d_sub, t_start + t_sub)
        refl, inten = self._intensity(sub)
        echoes = self._echoes(sub, inten, len(pat), self._sub_w.shape[0])
        if cfg.beam.return_mode == "dual":
            echoes = self._dual(echoes)
        echoes = self._drop(rng, echoes, sub.cos_incidence[echoes.rep], refl[echoes.rep], sub.label[echoes.rep])
        echoes = replace(echoes, range=self._range_noise(rng, echoes.range))
        ref = pose_start if cfg.motion.reference == "start" else pose_end
        out = self._points(echoes, sub, static, ref, poses, with_provenance=scene_has_provenance(tracer))
        return Sweep(out, float(t_start), float(t_end), pose_start, pose_end, ref, cfg.motion.output,
                     cfg.name, cfg.channels, pat.columns, pat.ring_elevation_deg, len(pat))

    # --- the stages of a sweep, in order (the random draws happen in `_drop`, then `_range_noise`) ---

    @staticmethod
    def _end_poses(pose_start, pose_end, pose_fn, t_start, t_end):
        """(4, 4) sensor-to-world poses at the sweep's start and end, checked rigid."""
        if pose_fn is not None:
            times = np.array([t_start, t_end], np.float64)
            ends = check_poses(pose_fn(times), "pose_fn (asked for the sweep's start and end)", times, count=2)
            return ends[0], ends[1]
        pose_start = check_pose(pose_start, "pose_start")
        return pose_start, (pose_start if pose_end is None else check_pose(pose_end, "pose_end"))

    def _sub_rays(self):
        """Every pulse's sub-rays (beam divergence), sensor frame: unit dirs (P*S, 3), origins
        (P*S, 3) metres, fire times (P*S,) seconds from the sweep's start."""
        pat = self.pattern
        s = self._sub_w.shape[0]
        d_s = pat.directions
        if s > 1:
            u, v = _perp_basis(d_s)
            tan_r = np.tan(self._sub_rho)
            d_sub = (d_s[:, None, :] + tan_r[None, :, None] * (np.cos(self._sub_phi)[None, :, None] * u[:, None, :]
                                                                + np.sin(self._sub_phi)[None, :, None] * v[:, None, :]))
            d_sub = (d_sub / np.linalg.norm(d_sub, axis=2, keepdims=True)).reshape(-1, 3)
        else:
            d_sub = d_s
        if s == 1:  # the pattern's own arrays (read only): no per-sweep copies
            return d_sub, pat.offsets, pat.time
        return d_sub, np.repeat(pat.offsets, s, axis=0), np.repeat(pat.time, s)

    def _distinct_fire_times(self):
        """The pattern's distinct fire times (U,) seconds from the sweep's start, ascending, and
        each pulse's index into them (P,). Pulses that fire together (a spinning LiDAR's blocks)
        share one pose: the pose function is asked once per distinct time."""
        pat = self.pattern
        if getattr(self, "_fire_times_of", None) is not pat:  # computed once per pattern
            t = pat.time
            if t.size and np.all(t[1:] >= t[:-1]):  # patterns come in firing order: no sort needed
                first = np.r_[True, t[1:] != t[:-1]]
                self._fire_times, self._fire_index = t[first], np.cumsum(first) - 1
            else:
                self._fire_times, self._fire_index = np.unique(t, return_inverse=True)
                self._fire_index = self._fire_index.reshape(-1)
            self._offsets_zero = not np.any(pat.offsets)
            self._fire_times_of = pat
        return self._fire_times, self._fire_index

    def _world_rays(self, d_sub, o_sub, static, pose_start, pose_end, pose_fn, t_start):
        """Sub-rays in the world frame at their own fire times: origins, dirs (P*S, 3), and the
        sensor poses (U, 4, 4) at the distinct fire times with each pulse's index into them (P,)
        (None for a static sensor)."""
        pat, s = self.pattern, self._sub_w.shape[0]
        if static:
            return transform_points(pose_start, o_sub), rotate_vectors(pose_start, d_sub), None
        times, of_pulse = self._distinct_fire_times()
        if pose_fn is not None:
            poses = check_poses(pose_fn(t_start + times), "pose_fn (asked for each distinct fire time)",
                                t_start + times, count=times.shape[0])
        else:
            poses = interpolate_poses(pose_start, pose_end, times / pat.period_s)
        # Each sub-ray's pose: a gather of the (3, 4) part only, skipped when every time is distinct.
        of_ray = np.repeat(of_pulse, s) if s > 1 else of_pulse
        per_ray = poses[:, :3, :]
        if times.shape[0] != of_ray.shape[0]:
            per_ray = np.take(np.ascontiguousarray(per_ray), of_ray, axis=0)
        d_w = np.einsum("nij,nj->ni", per_ray[:, :, :3], d_sub)
        if self._offsets_zero:  # every beam starts at the sensor's origin: o_w is the translation
            o_w = np.ascontiguousarray(per_ray[:, :, 3])
        else:
            o_w = np.einsum("nij,nj->ni", per_ray[:, :, :3], o_sub) + per_ray[:, :, 3]
        return o_w, d_w, (poses, of_pulse)

    def _trace(self, tracer, o_w, d_w, o_sub, d_sub, times) -> SubRayHits:
        """The ego body and the scene: what each sub-ray met (`SubRayHits`)."""
        cfg = self.config
        t_far = np.full(o_w.shape[0], cfg.range.max_m, np.float64)
        t_body = np.full(o_w.shape[0], np.inf)
        if cfg.ego_body is not None:
            mount = self.mount
            t_body = _ray_box(transform_points(mount, o_sub), rotate_vectors(mount, d_sub),
                              np.asarray(cfg.ego_body.min), np.asarray(cfg.ego_body.max))
            t_far = np.minimum(t_far, t_body)
        if isinstance(tracer, (list, tuple)):
            hits = nearest_hits(list(tracer), o_w, d_w, 0.0, t_far)
        elif tracer.accepts_times:
            # A scene with moving parts places them at each ray's own fire time.
            hits = tracer.trace_world(o_w, d_w, 0.0, t_far, times=times)
        else:
            hits = tracer.trace_world(o_w, d_w, 0.0, t_far)
        sub_range = hits.t.copy()
        hit = hits.hit.copy()
        label = hits.label.astype(np.int16)
        instance = hits.instance.copy()
        cos_inc = np.abs(np.einsum("ij,ij->i", hits.normals.astype(np.float64), d_w))
        measured = hits.reflectance.astype(np.float64)
        if cfg.ego_body is not None and cfg.ego_body.returns:
            body = np.isfinite(t_body) & (~hit | (t_body < sub_range))
            hit |= body
            sub_range = np.where(body, t_body, sub_range)
            label = np.where(body, 0, label).astype(np.int16)
            instance = np.where(body, 0, instance)
            cos_inc = np.where(body, 1.0, cos_inc)
            measured = np.where(body, np.nan, measured)
            hits.observed[body], hits.confidence[body] = 1, 1.0
        return SubRayHits(hit, sub_range, label, instance, cos_inc, hits.color, measured, hits.observed,
                          hits.confidence)

    def _intensity(self, sub: SubRayHits):
        """Per sub-ray reflectivity and return strength: the sensor's response to the measured
        reflectance where the surface has one, else reflectivity x cos incidence x fall-off."""
        ic = self.config.intensity
        hit, sub_range, label, cos_inc, color, measured = (sub.hit, sub.range, sub.label, sub.cos_incidence, sub.color,
                                                         sub.measured)
        if ic.source == "class":
            refl = self._class_reflectivity[label]
        elif ic.source == "color":
            refl = _luminance(color)
        else:
            refl = np.full(label.shape, ic.constant)
        with np.errstate(divide="ignore", invalid="ignore"):
            fall = np.minimum(1.0, (ic.reference_range_m / np.maximum(sub_range, 1e-6)) ** ic.falloff_exponent)
        strength = np.where(hit, refl * cos_inc * fall, 0.0)
        m = hit & np.isfinite(measured)
        if m.any():
            channel = np.repeat(self.pattern.ring.astype(np.int64), self._sub_w.shape[0])
            refl = np.where(m, measured, refl)
            strength[m] = self._response.forward(measured[m], cos_inc[m], sub_range[m], channel[m])
        return refl, strength

    def _drop(self, rng, echoes: Echoes, cos_rep, refl_rep, label_rep) -> Echoes:
        """Keep the echoes inside the range limits that no drop rule removes (one random draw
        per echo when the random rate is set, then one when a drop model is)."""
        cfg = self.config
        pulse, echo_range, strength = echoes.pulse, echoes.range, echoes.strength
        keep = echo_range >= cfg.range.min_m
        keep &= echo_range <= cfg.range.max_m
        if cfg.drop.random_rate > 0:
            keep &= rng.random(pulse.shape[0]) >= cfg.drop.random_rate
        if cfg.drop.max_incidence_deg < 90:
            keep &= cos_rep >= np.cos(np.deg2rad(cfg.drop.max_incidence_deg))
        if cfg.drop.min_intensity > 0:
            keep &= strength >= cfg.drop.min_intensity
        if cfg.drop.reflectivity_range is not None:
            eff = np.clip(refl_rep * cos_rep / cfg.drop.reflectivity_range, 0.0, 1.0)
            keep &= echo_range <= cfg.range.max_m * np.sqrt(eff)
        if self._drop_model is not None:
            p = self._drop_model.probability(cos_rep, echo_range, refl_rep, label_rep, self.pattern.ring[pulse])
            keep &= rng.random(pulse.shape[0]) >= p
        return echoes.select(keep)

    def _range_noise(self, rng, echo_range):
        """Gaussian range noise (one draw per echo when a sigma is set), quantisation, floor at 0."""
        nz = self.config.noise
        if nz.range_sigma_m > 0 or nz.range_sigma_rel > 0:
            sigma = nz.range_sigma_m + nz.range_sigma_rel * echo_range
            echo_range = echo_range + sigma * rng.standard_normal(echo_range.shape[0])
        if nz.quantization_m > 0:
            echo_range = np.round(echo_range / nz.quantization_m) * nz.quantization_m
        return np.maximum(echo_range, 0.0)

    def _points(self, echoes: Echoes, sub: SubRayHits, static, ref, poses, with_provenance: bool = False):
        """The sweep's records, in the output frame of `motion`: POINT_DTYPE, or with the scene's
        provenance (per sub-ray observed, confidence) CONVERTED_POINT_DTYPE."""
        cfg, pat = self.config, self.pattern
        pulse, echo_range, strength = echoes.pulse, echoes.range, echoes.strength
        rep, rid = echoes.rep, echoes.return_id
        label, instance = sub.label, sub.instance
        self._distinct_fire_times()  # knows whether the pattern has beam offsets
        # offsets + range * direction, in place; np.take: a row gather at a fraction of `[pulse]`'s
        # time. Adding 0.0 where there are no offsets keeps the bytes of the sum (-0.0 + 0.0 = 0.0).
        p_sensor = np.take(pat.directions, pulse, axis=0)
        p_sensor *= echo_range[:, None]
        p_sensor += 0.0 if self._offsets_zero else np.take(pat.offsets, pulse, axis=0)
        if cfg.motion.output == "compensated" and not static:
            at_times, of_pulse = poses  # sensor poses at the distinct fire times, each pulse's index
            rel = np.einsum("ij,njk->nik", invert_pose(ref), at_times)  # einsum: no BLAS threads
            p_out = transform_points(rel[of_pulse[pulse]], p_sensor)
        else:
            p_out = p_sensor
        out = np.empty(pulse.shape[0], point_dtype(with_provenance))  # every field is written below (no padding)
        out["x"], out["y"], out["z"] = p_out[:, 0], p_out[:, 1], p_out[:, 2]
        out["intensity"] = strength * cfg.intensity.output_scale
        out["ring"] = pat.ring[pulse]
        out["time"] = pat.time[pulse]
        out["range"] = echo_range
        out["azimuth"] = pat.azimuth[pulse]
        out["label"] = label[rep]
        out["instance"] = instance[rep]
        out["column"] = pat.column[pulse]
        out["return_id"] = rid
        if with_provenance:
            out["observed"] = sub.observed[rep]
            out["confidence"] = sub.confidence[rep]
        return out

    def _echoes(self, sub: SubRayHits, inten, n_pulse, s) -> Echoes:
        """Group sub-ray hits into echoes (`n_pulse` pulses of `s` sub-rays) and apply the
        single-return modes (dual: every echo, `_dual` picks two)."""
        mode = self.config.beam.return_mode
        hit, sub_range = sub.hit, sub.range
        if s == 1:
            idx = np.nonzero(hit)[0]
            return Echoes(idx, sub_range[idx], inten[idx], idx)
        w = np.tile(self._sub_w, n_pulse)
        r = np.where(hit, sub_range, np.inf).reshape(n_pulse, s)
        order = np.argsort(r, axis=1, kind="stable")
        sub = (order + (np.arange(n_pulse) * s)[:, None]).ravel()  # flat sub-ray ids, by range
        h_sorted = hit[sub].reshape(n_pulse, s)
        r_sorted = np.where(h_sorted, sub_range[sub].reshape(n_pulse, s), 1e30)
        gap = np.diff(r_sorted, axis=1) > self.config.beam.echo_separation_m
        cluster = np.concatenate([np.zeros((n_pulse, 1), np.int64), np.cumsum(gap, axis=1)], axis=1)
        hs = h_sorted.ravel()
        sub, cl = sub[hs], cluster.ravel()[hs]
        pulse_of = sub // s
        if mode == "mean":
            cl = np.zeros_like(cl)  # one echo at the mean range of all sub-ray hits
        key = pulse_of * s + cl
        uk, inv = np.unique(key, return_inverse=True)
        inv = inv.reshape(-1)
        wsum = np.bincount(inv, weights=w[sub])
        echo_r = np.bincount(inv, weights=w[sub] * sub_range[sub]) / wsum
        strength = np.bincount(inv, weights=w[sub] * inten[sub])
        # Representative sub-ray of each echo: the largest weighted intensity (its label/normal).
        score = w[sub] * (inten[sub] + 1e-12)
        o2 = np.lexsort((-score, inv))
        first = np.r_[True, inv[o2][1:] != inv[o2][:-1]]
        rep = np.empty(uk.shape[0], np.int64)
        rep[inv[o2][first]] = sub[o2][first]
        e_pulse = uk // s
        if mode in ("first", "nearest", "mean"):
            pick = np.r_[True, e_pulse[1:] != e_pulse[:-1]]  # lowest cluster id = nearest
        elif mode == "last":
            pick = np.r_[e_pulse[1:] != e_pulse[:-1], True]
        elif mode in ("strongest", "dual"):
            if mode == "dual":
                return Echoes(e_pulse, echo_r, strength, rep)
            o3 = np.lexsort((-strength, e_pulse))
            f3 = np.r_[True, e_pulse[o3][1:] != e_pulse[o3][:-1]]
            pick = np.zeros(uk.shape[0], bool)
            pick[o3[f3]] = True
        else:  # pragma: no cover - validated by the config
            raise InputError(mode)
        return Echoes(e_pulse[pick], echo_r[pick], strength[pick], rep[pick])

    @staticmethod
    def _dual(echoes: Echoes) -> Echoes:
        """Dual return: the strongest and the last echo of each pulse; when they coincide, the
        strongest and the second strongest. Echoes arrive sorted by (pulse, range)."""
        e_pulse, echo_r, strength, rep = echoes.pulse, echoes.range, echoes.strength, echoes.rep
        n = e_pulse.shape[0]
        if n == 0:
            return echoes
        o3 = np.lexsort((-strength, e_pulse))
        starts = np.r_[True, e_pulse[o3][1:] != e_pulse[o3][:-1]]
        strongest = o3[starts]
        rank = np.arange(n) - np.repeat(np.nonzero(starts)[0], np.diff(np.r_[np.nonzero(starts)[0], n]))
        second = np.full(e_pulse.max() + 1, -1, np.int64)
        second[e_pulse[o3[rank == 1]]] = o3[rank == 1]
        last = np.nonzero(np.r_[e_pulse[1:] != e_pulse[:-1], True])[0]
        p_str = e_pulse[strongest]
        other = np.where(last != strongest, last, second[p_str])
        a = strongest
        b = other[other >= 0]
        sel = np.concatenate([a, b])
        rid = np.concatenate([np.zeros(a.shape[0], np.uint8), np.ones(b.shape[0], np.uint8)])
        order = np.lexsort((rid, e_pulse[sel]))
        sel, rid = sel[order], rid[order]
        return Echoes(e_pulse[sel], echo_r[sel], strength[sel], rep[sel], rid)
