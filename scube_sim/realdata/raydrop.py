"""Fit and score a ray-drop model on a real sweep that records its no-returns.

Where a sensor stores its full firing grid (nuScenes: 32 x 1084, a no-return is a placeholder
under 1 m), every ray of the grid is either a return or a drop. The rays are replayed against a
scene (the VoxSplat built from the log) with no drop rule at all: where the simulated ray meets
a surface within the range limits, the real sensor may still have returned nothing, and that
is what the model learns, from the surface the simulation sees (incidence, range, reflectance,
label) and the channel (`lidar.drop`). Rays into the ego body (`RealRays.ego_body`) are left
out; rays that meet no surface in the scene are no-returns for every model and only enter the
scores.

Split: the sweep's azimuth is cut into `sectors` equal sectors; even sectors fit, odd sectors
are held out (neighbouring rays see the same surfaces, so a random split would leak).
Scores, on the held-out rays: the confusion matrix of (real drop, simulated drop), precision
and recall of drops, and hit agreement (the share of rays where simulation and sensor agree
on return or no return), for the preset's hand-set drop rules and for the fitted model, each
replayed through the LiDAR model with the same seed.

Logs that keep returns only store no no-returns. Where each return carries its laser and its
fire time (Argoverse 2: `laser_number`, `offset_ns`), `rebuild_firing_grid` rebuilds the full
grid from the timing (every return sits on the firing-cycle lattice once its laser's fire time
within the cycle is subtracted), and `transfer_study` fits a model on one sensor's grid and
scores it on another's. Where they do not (KITTI: no per-point time), a model can only be scored
by the share of real returns the simulation returns (drops can only lower it).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..datasets.base import LidarSweep
from ..errors import InputError
from ..lidar.config import LidarConfig, SpinningPattern
from ..lidar.drop import CONTINUOUS, DropModel, drop_features
from ..lidar.model import class_reflectivity_table
from ..lidar.pattern import channels_by_elevation
from ..raytrace.tracer import Tracer
from ..transforms import invert_pose, rotate_vectors, transform_points
from .fidelity import RealRays, real_rays, simulate_rays

SECTORS = 12  # 30 degrees each
L2_CANDIDATES = (0.1, 1.0, 10.0, 100.0)  # chosen by leave-one-sector-out within the fitting sectors


@dataclass
class RayFeatures:
    """What the scene shows each real ray when nothing is dropped: meets (N,) bool a surface
    within the range limits; range (N,) metres; cos_inc (N,); reflectance (N,) measured, else
    class; label (N,) int16; channel (N,) int the sensor's channel (-1 unknown)."""

    meets: np.ndarray
    range: np.ndarray
    cos_inc: np.ndarray
    reflectance: np.ndarray
    label: np.ndarray
    channel: np.ndarray

    def terms(self, mask: np.ndarray) -> dict[str, np.ndarray]:
        return drop_features(self.cos_inc[mask], self.range[mask], self.reflectance[mask], self.label[mask],
                             self.channel[mask])


def ray_features(tracer: Tracer, config: LidarConfig, rays: RealRays, sweep: LidarSweep) -> RayFeatures:
    """Trace the real rays (from the sweep pose, or each from its own pose for a raw sweep) with
    no drop rule and read the surface each meets."""
    if sweep.motion_compensated:
        poses = np.broadcast_to(sweep.sensor_to_world, (len(rays), 4, 4))
    else:
        poses = np.asarray(sweep.pose_fn(sweep.timestamp + rays.time), np.float64)
    d = rotate_vectors(poses, rays.directions)
    h = tracer.trace_world(poses[:, :3, 3], d, 0.0, config.range.max_m)
    meets = h.hit & (h.t >= config.range.min_m)
    cos = np.abs(np.einsum("ij,ij->i", h.normals.astype(np.float64), d))
    refl = np.where(np.isfinite(h.reflectance), h.reflectance, class_reflectivity_table(config)[h.label])
    channel = channels_by_elevation(rays.directions, rays.ring, config, valid=rays.hit)
    return RayFeatures(meets, np.where(meets, h.t, np.inf), cos, refl, h.label.astype(np.int16), channel)


def fit_logistic(x: np.ndarray, y: np.ndarray, *, l2: float = 1.0, iterations: int = 50) -> np.ndarray:
    """Weights (K + 1,) (intercept first) of a logistic regression of y (N,) bool on x (N, K),
    by Newton's method (IRLS) with an L2 penalty `l2` on all weights but the intercept; the
    columns are standardised inside and the weights returned on the raw scale."""
    x = np.asarray(x, np.float64)
    mu, sd = x.mean(0), x.std(0)
    sd = np.where(sd > 0, sd, 1.0)
    a = np.c_[np.ones(x.shape[0]), (x - mu) / sd]
    yv = np.asarray(y, np.float64)
    w = np.zeros(a.shape[1])
    w[0] = np.log((yv.mean() + 1e-6) / (1 - yv.mean() + 1e-6))
    pen = np.full(a.shape[1], float(l2))
    pen[0] = 0.0
    for _ in range(iterations):
        p = 0.5 * (1.0 + np.tanh(0.5 * (a @ w)))
        grad = a.T @ (p - yv) + pen * w
        hess = (a * (p * (1 - p))[:, None]).T @ a + np.diag(pen + 1e-9)
        step = np.linalg.solve(hess, grad)
        w -= step
        if np.max(np.abs(step)) < 1e-8:
            break
    raw = w[1:] / sd
    return np.r_[w[0] - np.sum(raw * mu), raw]


def fit_drop_model(features: dict[str, np.ndarray], dropped: np.ndarray, *, l2: float = 1.0, **meta) -> DropModel:
    """A `DropModel` from the terms of `drop_features` (N,) each and whether each ray was
    dropped (N,) bool; `meta` fills sensor, source and notes."""
    terms = [t for t in CONTINUOUS if t in features] + sorted(t for t in features if t not in CONTINUOUS)
    w = fit_logistic(np.stack([features[t] for t in terms], 1), dropped, l2=l2)
    return DropModel(float(w[0]), {t: float(v) for t, v in zip(terms, w[1:])}, **meta)


def log_loss(p: np.ndarray, y: np.ndarray) -> float:
    """Mean negative log-likelihood (nats) of outcomes y (N,) bool under probabilities p (N,)."""
    p = np.clip(np.asarray(p, np.float64), 1e-9, 1 - 1e-9)
    y = np.asarray(y, bool)
    return float(-np.mean(np.where(y, np.log(p), np.log1p(-p))))


def auc(score: np.ndarray, y: np.ndarray) -> float:
    """Area under the ROC curve of `score` (N,) for outcomes y (N,) bool (ties count half)."""
    y = np.asarray(y, bool)
    n1, n0 = int(y.sum()), int((~y).sum())
    if n1 == 0 or n0 == 0:
        return float("nan")
    order = np.argsort(score, kind="stable")
    s = np.asarray(score, np.float64)[order]
    rank = np.empty(len(s))
    rank[order] = np.arange(1, len(s) + 1, dtype=np.float64)
    # Average ranks over ties.
    uniq, inv, cnt = np.unique(s, return_inverse=True, return_counts=True)
    first = np.cumsum(cnt) - cnt + 1
    rank[order] = (first + (cnt - 1) / 2.0)[inv]
    return float((rank[y].sum() - n1 * (n1 + 1) / 2.0) / (n1 * n0))


def choose_l2(f: "RayFeatures", dropped: np.ndarray, train: np.ndarray, sector: np.ndarray,
              candidates=L2_CANDIDATES) -> tuple[float, dict]:
    """The L2 penalty of the lowest mean log loss when each fitting sector in turn is predicted
    from the others. Returns it and candidate -> mean log loss."""
    losses = {}
    for l2 in candidates:
        out = []
        for k in np.unique(sector[train]):
            tr, te = train & (sector != k), train & (sector == k)
            if not dropped[tr].any() or not te.any():
                continue
            m = fit_drop_model(f.terms(tr), dropped[tr], l2=l2)
            out.append(log_loss(m.probability(f.cos_inc[te], f.range[te], f.reflectance[te], f.label[te],
                                              f.channel[te]), dropped[te]))
        losses[l2] = float(np.mean(out)) if out else float("inf")
    return min(losses, key=losses.get), losses


def drop_scores(real_hit: np.ndarray, sim_hit: np.ndarray) -> dict:
    """Confusion matrix of drops (a drop = no return) and what it gives, on (N,) bool arrays."""
    rd, sd = ~np.asarray(real_hit, bool), ~np.asarray(sim_hit, bool)
    tp, fn = int((rd & sd).sum()), int((rd & ~sd).sum())
    fp, tn = int((~rd & sd).sum()), int((~rd & ~sd).sum())
    return {"rays": int(rd.size), "real drop, sim drop": tp, "real drop, sim return": fn,
            "real return, sim drop": fp, "real return, sim return": tn,
            "drop precision": tp / (tp + fp) if tp + fp else float("nan"),
            "drop recall": tp / (tp + fn) if tp + fn else float("nan"),
            "hit agreement": (tp + tn) / rd.size if rd.size else float("nan")}


@dataclass
class DropStudy:
    """model: the fitted model; scores: row name -> `drop_scores` on the held-out rays;
    probabilistic: on the held-out rays that meet a surface, log loss and AUC of each predictor
    of drops; notes."""

    model: DropModel
    scores: dict[str, dict]
    notes: list[str] = field(default_factory=list)
    probabilistic: dict[str, dict] = field(default_factory=dict)

    def markdown(self) -> str:
        keys = ["real drop, sim drop", "real drop, sim return", "real return, sim drop", "real return, sim return",
                "drop precision", "drop recall", "hit agreement"]
        lines = ["| drops | " + " | ".join(keys) + " |", "|" + "---|" * (len(keys) + 1)]
        for name, s in self.scores.items():
            cells = [f"{s[k]:.3f}" if isinstance(s[k], float) else str(s[k]) for k in keys]
            lines.append(f"| {name} | " + " | ".join(cells) + " |")
        prob = ["| predictor (held-out rays meeting a surface) | log loss [nats] | AUC |", "|---|---|---|"]
        for name, s in self.probabilistic.items():
            prob.append(f"| {name} | {s['log_loss']:.4f} | {s['auc']:.3f} |")
        return "\n".join(["# Ray drop, held-out sectors", "", *lines, "", *prob, "",
                          *[f"- {n}" for n in self.notes], ""])


def azimuth_sector(rays: RealRays, sectors: int = SECTORS) -> np.ndarray:
    """(N,) int azimuth sector of each ray (sensor frame), 0 .. sectors - 1; even ones fit, odd
    ones are held out."""
    az = np.arctan2(rays.directions[:, 1], rays.directions[:, 0])
    return np.minimum((az + np.pi) / (2 * np.pi) * sectors, sectors - 1).astype(np.int64)


def drop_study(scene, config: LidarConfig, sweep: LidarSweep, model_path: str | Path, *, sensor_name: str = "",
               source: str = "", sectors: int = SECTORS, l2: float | None = None, seed: int = 0,
               min_range: float = 1.0) -> DropStudy:
    """Fit a drop model on the even sectors of `sweep` (a full firing grid) against `scene` (a
    VoxSplat), write it to `model_path`, and score it and the preset's own drop rules on the
    odd sectors. l2: the penalty (default: `choose_l2` over the fitting sectors)."""
    rays = real_rays(sweep, min_range=min_range)
    if not rays.no_returns_known:
        raise InputError(f"sweep {sweep.sensor!r}: a drop model is fitted where the sensor records its "
                         f"no-returns (a full firing grid, as nuScenes stores it); this sweep keeps returns only")
    tracer = Tracer(scene, mode="max_response")
    f = ray_features(tracer, config, rays, sweep)
    usable = ~rays.ego_body
    sector = azimuth_sector(rays, sectors)
    fit = sector % 2 == 0
    train = usable & fit & f.meets
    dropped = ~rays.hit
    losses = {}
    if l2 is None:
        l2, losses = choose_l2(f, dropped, train, sector)
    model = fit_drop_model(f.terms(train), dropped[train], l2=l2, sensor=sensor_name or config.name, source=source)
    held = usable & ~fit
    notes = [f"{int(rays.ego_body.sum())} rays into the ego body left out; {sectors} azimuth sectors of "
             f"{360 / sectors:g} degrees, even ones fit ({int(train.sum())} rays meeting a surface, "
             f"{int((~rays.hit[train]).sum())} of them dropped), odd ones held out ({int(held.sum())} rays)",
             "'sim drop' = no simulated return: the scene shows no surface or the drop rule/model removed it; "
             f"drops sampled with seed {seed}",
             "the scene is built from this sweep: a drop in the middle of returns is bridged by the range-image "
             "mesh, but a run of drops leaves a hole the simulation also sees through",
             f"L2 penalty {l2:g}" + (" (leave-one-sector-out log loss: " + ", ".join(
                 f"{k:g}: {v:.4f}" for k, v in losses.items()) + ")" if losses else "")]
    # The model's own expected counts over the held-out rays, before sampling.
    p = np.zeros(len(rays))
    p[f.meets] = model.probability(f.cos_inc[f.meets], f.range[f.meets], f.reflectance[f.meets],
                                   f.label[f.meets], f.channel[f.meets])
    model.save(model_path)
    rows = {}
    for name, drop in (("no drops (fidelity replay)", None),
                       ("hand-set rules (preset)", config.drop),
                       # The model replaces the hand-set rules (the preset has no others but the grazing cut).
                       ("fitted model", config.drop.model_copy(update={"max_incidence_deg": 90.0,
                                                                      "model": str(Path(model_path).resolve())}))):
        sim = simulate_rays(tracer, config, rays, sweep, seed=seed, drop=drop)
        rows[name] = drop_scores(rays.hit[held], sim.hit[held])
    real_drop = ~rays.hit[held]
    ph = p[held]
    rows["fitted model, expected"] = {
        "rays": int(held.sum()), "real drop, sim drop": float(((1 - f.meets[held]) + ph)[real_drop].sum()),
        "real drop, sim return": float((f.meets[held] * (1 - ph))[real_drop].sum()),
        "real return, sim drop": float(((1 - f.meets[held]) + ph)[~real_drop].sum()),
        "real return, sim return": float((f.meets[held] * (1 - ph))[~real_drop].sum())}
    e = rows["fitted model, expected"]
    e["drop precision"] = e["real drop, sim drop"] / (e["real drop, sim drop"] + e["real return, sim drop"])
    e["drop recall"] = e["real drop, sim drop"] / (e["real drop, sim drop"] + e["real drop, sim return"])
    e["hit agreement"] = (e["real drop, sim drop"] + e["real return, sim return"]) / e["rays"]
    hm = held & f.meets
    grazing = f.cos_inc < np.cos(np.deg2rad(config.drop.max_incidence_deg))
    prob = {"fitted model": {"log_loss": log_loss(p[hm], dropped[hm]), "auc": auc(p[hm], dropped[hm])},
            "constant (the fitting sectors' drop rate)": {
                "log_loss": log_loss(np.full(hm.sum(), dropped[train].mean()), dropped[hm]), "auc": 0.5},
            "range alone": {"log_loss": float("nan"), "auc": auc(f.range[hm], dropped[hm])},
            "hand-set grazing rule": {"log_loss": float("nan"), "auc": auc(grazing[hm].astype(float), dropped[hm])}}
    model.scores = {k: {m: (round(v, 4) if isinstance(v, float) else v) for m, v in s.items()} for k, s in rows.items()}
    model.scores["held-out log loss and AUC"] = {k: {m: round(v, 4) for m, v in s.items()} for k, s in prob.items()}
    model.notes = "; ".join(notes)
    model.save(model_path)
    return DropStudy(model, rows, notes, prob)


# --- Rebuilding the firing grid of a log that keeps returns only (Argoverse 2) ------------------

@dataclass
class FiringGrid:
    """The firing grid of a spinning sweep stored as returns only, rebuilt from its timing.

    rays: every (firing cycle, channel) cell as a `RealRays` with ``no_returns_known`` True, in
    cycle-major order (cell = cycle * channels + channel): returns with their measured direction
    and range, empty cells (no return: a drop) with range inf, the channel's median elevation and
    the cycle's azimuth plus the channel's measured azimuth offset; directions in the sensor frame
    at each ray's own fire time (`sweep` is that raw form). sweep: the returns, raw (each in the
    sensor frame at its fire time, ``motion_compensated`` False), with `pose_fn`.
    cycle (N,) int: each return's firing cycle; occupancy (cycles, channels) int: returns per
    cell; cycle_us: the measured cycle period; timing_residual_us (N,): each return's time minus
    its lattice time; azimuth_offset_deg (channels,): each channel's measured azimuth relative to
    the cycle's; azimuth_residual_deg (N,): each return's azimuth minus its cell's; notes."""

    rays: RealRays
    sweep: LidarSweep
    cycle: np.ndarray
    occupancy: np.ndarray
    cycle_us: float
    timing_residual_us: np.ndarray
    azimuth_offset_deg: np.ndarray
    azimuth_residual_deg: np.ndarray
    notes: list[str] = field(default_factory=list)

    @property
    def cycles(self) -> int:
        return int(self.occupancy.shape[0])

    @property
    def channels(self) -> int:
        return int(self.occupancy.shape[1])


def _wrap(a: np.ndarray) -> np.ndarray:
    """Angles (radians) wrapped to [-pi, pi)."""
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


def _circ_mean_by(angles: np.ndarray, group: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    s = np.bincount(group, weights=np.sin(angles), minlength=n)
    c = np.bincount(group, weights=np.cos(angles), minlength=n)
    return np.arctan2(s, c), np.bincount(group, minlength=n) > 0


def _fill_azimuth(az: np.ndarray, seen: np.ndarray) -> np.ndarray:
    """Per-cycle azimuth (n,) radians known where `seen`; the others interpolated along the
    unwrapped known ones (extrapolated linearly at the ends)."""
    idx = np.arange(az.size)
    k = idx[seen]
    u = np.unwrap(az[seen])
    if k.size < 2:
        return np.where(seen, az, az[seen][0] if k.size else 0.0)
    out = np.interp(idx, k, u)
    lo, hi = idx < k[0], idx > k[-1]
    out[lo] = u[0] + (idx[lo] - k[0]) * (u[1] - u[0]) / (k[1] - k[0])
    out[hi] = u[-1] + (idx[hi] - k[-1]) * (u[-1] - u[-2]) / (k[-1] - k[-2])
    return _wrap(out)


def measure_cycle_us(time_us: np.ndarray, channel: np.ndarray, nominal_us: float) -> float:
    """The firing-cycle period (us) of a spinning sensor from its returns' times: per channel,
    the gaps between consecutive returns are whole cycles (a gap of n cycles = n - 1 drops in
    between); the period is the least-squares ratio of gaps to cycle counts over gaps of at most
    8 cycles (counted against `nominal_us`, then against the first estimate)."""
    gaps = []
    for c in np.unique(channel):
        t = np.sort(time_us[channel == c])
        gaps.append(np.diff(t))
    d = np.concatenate(gaps) if gaps else np.zeros(0)
    period = float(nominal_us)
    for _ in range(2):
        n = np.round(d / period)
        ok = (n >= 1) & (n <= 8) & (np.abs(d - n * period) < 0.25 * period)
        if not ok.any():
            raise InputError("no two returns of one channel are a whole number of firing cycles apart: "
                             "the times do not follow a firing-cycle lattice")
        period = float(d[ok].sum() / n[ok].sum())
    return period


def rebuild_firing_grid(sweep: LidarSweep, config: LidarConfig, *, cycle_us: float | None = None,
                        min_range: float = 1.0, max_timing_residual_us: float = 5.0,
                        ego_body: "callable | None" = None) -> FiringGrid:
    """Rebuild the full firing grid of a spinning sweep that stores returns only, from each
    return's time and channel.

    A Velodyne fires all its lasers once per firing cycle, laser c ``fire_time_us[c]`` after the
    cycle starts (the preset's table). So ``time - fire_time_us[channel]`` of every return is a
    cycle start, and cycle starts lie on one lattice of the cycle period (measured:
    `measure_cycle_us`); the lattice index is the return's firing cycle, the grid's column.
    A (cycle, channel) cell with no return is a no-return: the log dropped nothing else there.
    `sweep.ring` must hold the preset's channel index (Argoverse 2: `AV2_LASER_TO_VLP32C_CHANNEL`).
    InputError when returns sit more than `max_timing_residual_us` off the lattice (the times are
    not fire times).

    Directions of empty cells: the channel's median elevation, and the cycle's azimuth (circular
    mean over the cycle's returns of azimuth minus each channel's measured offset, interpolated
    over cycles with none) plus the channel's offset. A compensated sweep is first moved back to
    the sensor frame at each return's fire time (`pose_fn`), so directions are raw.
    Returns under `min_range` count as no-returns. Two returns in one cell (dual-return logs)
    keep the nearer. ego_body: optional function of (directions (M, 3) sensor frame) -> (M,) bool,
    the rays that would meet the vehicle itself (flagged ``ego_body``)."""
    if sweep.time_offset is None or sweep.ring is None:
        raise InputError(f"sweep {sweep.sensor!r}: rebuilding the firing grid needs per-return times and channels")
    if not isinstance(config.pattern, SpinningPattern) or config.pattern.channels.fire_time_us is None:
        raise InputError(f"sensor {config.name!r}: rebuilding the firing grid needs a spinning pattern with "
                         f"per-channel fire times")
    ch = np.asarray(sweep.ring, np.int64)
    nch = len(config.pattern.channels.elevation_deg)
    if ch.min(initial=0) < 0 or ch.max(initial=0) >= nch:
        raise InputError(f"sweep {sweep.sensor!r}: ring ids must be the preset's channels 0-{nch - 1}")
    fire = np.asarray(config.pattern.channels.fire_time_us, np.float64)
    t_us = np.asarray(sweep.time_offset, np.float64) * 1e6
    start = t_us - fire[ch]
    nominal = 1e6 / (config.pattern.rotation_hz * config.pattern.columns)
    period = float(cycle_us) if cycle_us else measure_cycle_us(start, ch, nominal)
    k = np.round((start - start.min()) / period).astype(np.int64)
    # Refine the lattice (phase and period) by least squares, then re-index.
    a = np.c_[np.ones(k.size), k]
    (c0, period_fit), *_ = np.linalg.lstsq(a, start, rcond=None)
    if not cycle_us:
        period = float(period_fit)
    k = np.round((start - c0) / period).astype(np.int64)
    k -= k.min()
    c0 = float(np.median(start - k * period))
    resid = start - c0 - k * period
    if np.max(np.abs(resid), initial=0.0) > max_timing_residual_us:
        bad = float(np.mean(np.abs(resid) > max_timing_residual_us))
        raise InputError(f"sweep {sweep.sensor!r}: {100 * bad:.1f} % of returns lie over {max_timing_residual_us} us "
                         f"off a {period:.3f} us firing-cycle lattice: the times are not the lasers' fire times")
    cycles = int(k.max()) + 1 if k.size else 0
    occupancy = np.zeros((cycles, nch), np.int64)
    np.add.at(occupancy, (k, ch), 1)

    # Raw directions: each return in the sensor frame at its own fire time.
    p = np.asarray(sweep.points, np.float64)
    if sweep.motion_compensated and sweep.pose_fn is not None and len(p):
        poses = np.asarray(sweep.pose_fn(sweep.timestamp + np.asarray(sweep.time_offset, np.float64)))
        p = transform_points(invert_pose(poses) @ sweep.sensor_to_world, p)
    r = np.linalg.norm(p, axis=1)
    d = p / np.maximum(r, 1e-12)[:, None]
    az = np.arctan2(d[:, 1], d[:, 0])
    el = np.arcsin(np.clip(d[:, 2], -1.0, 1.0))
    # Cycle azimuth and per-channel offsets, alternately (two rounds settle them).
    col_az, seen = _circ_mean_by(az, k, cycles)
    col_az = _fill_azimuth(col_az, seen)
    offset = np.zeros(nch)
    for _ in range(3):
        offset, _ = _circ_mean_by(_wrap(az - col_az[k]), ch, nch)
        col_az, seen = _circ_mean_by(_wrap(az - offset[ch]), k, cycles)
        col_az = _fill_azimuth(col_az, seen)
    az_resid = _wrap(az - col_az[k] - offset[ch])
    ch_el = np.zeros(nch)
    table = np.deg2rad(np.asarray(config.pattern.channels.elevation_deg, np.float64))
    for c in range(nch):
        m = ch == c
        ch_el[c] = np.median(el[m]) if m.any() else table[c]

    # The grid: cell = cycle * nch + channel.
    ncell = cycles * nch
    cell = k * nch + ch
    ret = r >= min_range
    order = np.lexsort((r, cell))  # nearer first within a cell
    first = np.ones(order.size, bool)
    first[1:] = cell[order][1:] != cell[order][:-1]
    keep = order[first & ret[order]]
    rng = np.full(ncell, np.inf)
    rng[cell[keep]] = r[keep]
    gk, gc = np.divmod(np.arange(ncell), nch)
    e, a_ = ch_el[gc], col_az[gk] + offset[gc]
    dirs = np.stack([np.cos(e) * np.cos(a_), np.cos(e) * np.sin(a_), np.sin(e)], axis=1)
    dirs[cell[keep]] = d[keep]
    time = (c0 + gk * period + fire[gc]) * 1e-6
    time[cell[keep]] = np.asarray(sweep.time_offset, np.float64)[keep]
    inten = np.full(ncell, np.nan)
    if sweep.intensity is not None:
        inten[cell[keep]] = np.asarray(sweep.intensity, np.float64)[keep] / sweep.intensity_max
    rank = np.empty(nch, np.int64)
    rank[np.argsort(-ch_el)] = np.arange(nch)
    body = np.zeros(ncell, bool) if ego_body is None else np.asarray(ego_body(dirs), bool)
    doubles = int((occupancy >= 2).sum())
    empty = ~np.isfinite(rng)
    notes = [f"firing grid rebuilt from timing: {cycles} cycles x {nch} channels, cycle {period:.4f} us "
             f"(returns within {np.max(np.abs(resid), initial=0):.3f} us of the lattice); {int(empty.sum())} of "
             f"{ncell} cells ({100 * empty.mean():.1f} %) hold no return, {doubles} hold two or more"
             + (f"; {int(body.sum())} cells look into the ego body" if ego_body is not None else "")]
    rays = RealRays(dirs, rng, time, inten, rank[gc], gk, nch, cycles, True, notes, gc.astype(np.int64), body)
    raw = LidarSweep(sweep.sensor, p, sweep.sensor_to_world, sweep.timestamp, sweep.intensity, sweep.intensity_max,
                     sweep.ring, sweep.time_offset, motion_compensated=sweep.motion_compensated and sweep.pose_fn is None,
                     pose_fn=sweep.pose_fn,
                     source=sweep.source)
    return FiringGrid(rays, raw, k, occupancy, period, resid, np.rad2deg(offset), np.rad2deg(az_resid), notes)


def blind_sector(mount: np.ndarray, azimuth_deg: tuple[float, float], max_elevation_deg: float = 90.0):
    """An `ego_body` test for `rebuild_firing_grid`: rays whose direction in the vehicle frame
    (mount (4, 4) sensor -> vehicle) has azimuth within ``azimuth_deg`` = (from, to) degrees,
    counter-clockwise from `from` to `to` (so (170, -160) is the 30 degrees behind), and elevation
    at most `max_elevation_deg`: where the vehicle or its sensor rig hides the scene."""
    rot = np.asarray(mount, np.float64)[:3, :3]
    lo, hi = (float(a) for a in azimuth_deg)
    width = (hi - lo) % 360.0

    def test(directions: np.ndarray) -> np.ndarray:
        d = np.asarray(directions, np.float64) @ rot.T
        az = np.rad2deg(np.arctan2(d[:, 1], d[:, 0]))
        el = np.rad2deg(np.arcsin(np.clip(d[:, 2], -1.0, 1.0)))
        return ((az - lo) % 360.0 <= width) & (el <= max_elevation_deg)

    return test


def transfer_study(fit: tuple, apply: tuple, model_path: str | Path, *, source: str = "", seed: int = 0,
                   l2: float | None = None, sectors: int = SECTORS) -> DropStudy:
    """Fit a drop model on one sensor's full firing grid and score it on another's.

    fit, apply: (scene, config, rays, sweep) each: the VoxSplat (or Tracer) the rays are replayed
    against, the sensor model, the full grid (`RealRays` with ``no_returns_known``, e.g.
    `FiringGrid.rays`) and the sweep giving poses (`FiringGrid.sweep`). The model is fitted on
    every usable fitting ray that meets a surface (L2 by leave-one-sector-out over `sectors`
    azimuth sectors, unless given), written to `model_path`, and the applied sensor's rays are
    scored with no drop rule, its preset's hand-set rules and the fitted model (all its rays
    but the ego body's)."""
    scene_f, cfg_f, rays_f, sweep_f = fit
    scene_a, cfg_a, rays_a, sweep_a = apply
    for r, s in ((rays_f, sweep_f), (rays_a, sweep_a)):
        if not r.no_returns_known:
            raise InputError(f"sweep {s.sensor!r}: a drop model is fitted and scored where every ray of the "
                             f"firing grid is known (returns and no-returns)")
    tr_f = scene_f if isinstance(scene_f, Tracer) else Tracer(scene_f, mode="max_response")
    tr_a = scene_a if isinstance(scene_a, Tracer) else Tracer(scene_a, mode="max_response")
    ff = ray_features(tr_f, cfg_f, rays_f, sweep_f)
    train = ~rays_f.ego_body & ff.meets
    dropped_f = ~rays_f.hit
    losses = {}
    if l2 is None:
        l2, losses = choose_l2(ff, dropped_f, train, azimuth_sector(rays_f, sectors))
    model = fit_drop_model(ff.terms(train), dropped_f[train], l2=l2, sensor=cfg_f.name, source=source)
    model.save(model_path)
    fa = ray_features(tr_a, cfg_a, rays_a, sweep_a)
    held = ~rays_a.ego_body
    dropped_a = ~rays_a.hit
    p = np.zeros(len(rays_a))
    p[fa.meets] = model.probability(fa.cos_inc[fa.meets], fa.range[fa.meets], fa.reflectance[fa.meets],
                                    fa.label[fa.meets], fa.channel[fa.meets])
    rows = {}
    for name, drop in (("no drops (fidelity replay)", None),
                       ("hand-set rules (preset)", cfg_a.drop),
                       (f"model fitted on {sweep_f.sensor}", cfg_a.drop.model_copy(update={
                           "max_incidence_deg": 90.0, "model": str(Path(model_path).resolve())}))):
        sim = simulate_rays(tr_a, cfg_a, rays_a, sweep_a, seed=seed, drop=drop)
        rows[name] = drop_scores(rays_a.hit[held], sim.hit[held])
    hm = held & fa.meets
    grazing = fa.cos_inc < np.cos(np.deg2rad(cfg_a.drop.max_incidence_deg))
    prob = {f"model fitted on {sweep_f.sensor}": {"log_loss": log_loss(p[hm], dropped_a[hm]),
                                                   "auc": auc(p[hm], dropped_a[hm])},
            f"constant ({sweep_f.sensor}'s drop rate where a surface is)": {
                "log_loss": log_loss(np.full(hm.sum(), dropped_f[train].mean()), dropped_a[hm]), "auc": 0.5},
            "range alone": {"log_loss": float("nan"), "auc": auc(fa.range[hm], dropped_a[hm])},
            "hand-set grazing rule": {"log_loss": float("nan"), "auc": auc(grazing[hm].astype(float), dropped_a[hm])}}
    notes = [f"fitted on {sweep_f.sensor}: {int(train.sum())} rays meeting a surface, {int(dropped_f[train].sum())} "
             f"of them dropped ({int(rays_f.ego_body.sum())} ego-body rays left out); L2 {l2:g}"
             + (" (leave-one-sector-out log loss: " + ", ".join(f"{k:g}: {v:.4f}" for k, v in losses.items()) + ")"
                if losses else ""),
             f"scored on {sweep_a.sensor}: {int(held.sum())} rays ({int(dropped_a[held].sum())} real drops; "
             f"{int(hm.sum())} meet a surface, {int(dropped_a[hm].sum())} of those dropped; "
             f"{int(rays_a.ego_body.sum())} ego-body rays left out); drops sampled with seed {seed}",
             f"expected drops where a surface is: model {p[hm].sum():.0f}, real {int(dropped_a[hm].sum())}"]
    model.scores = {k: {m: (round(v, 4) if isinstance(v, float) else v) for m, v in s.items()} for k, s in rows.items()}
    model.scores["applied: log loss and AUC"] = {k: {m: round(v, 4) for m, v in s.items()} for k, s in prob.items()}
    model.notes = "; ".join(notes)
    model.save(model_path)
    return DropStudy(model, rows, notes, prob)
