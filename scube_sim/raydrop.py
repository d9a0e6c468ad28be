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

Logs that keep returns only (KITTI, Argoverse 2) have no no-returns to fit on: there a fitted
model can only be scored by the share of real returns the simulation returns (drops can only
lower it), and the firing grid is not rebuilt.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .datasets.base import LidarSweep
from .errors import InputError
from .fidelity import RealRays, real_rays, simulate_rays
from .lidar.config import LidarConfig
from .lidar.drop import CONTINUOUS, DropModel, drop_features
from .lidar.model import class_reflectivity_table
from .lidar.pattern import channels_by_elevation
from .raytrace.tracer import Tracer
from .transforms import rotate_vectors

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
