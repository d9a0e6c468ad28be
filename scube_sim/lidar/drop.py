"""A fitted ray-drop model: the probability that a pulse which meets a surface returns nothing.

A logistic model (`raydrop.fit_drop_model` fits it to real sweeps):
``p(drop) = 1 / (1 + exp(-(intercept + sum_k w_k x_k)))`` over the terms of `drop_features`:

- ``cos_incidence``: |cos| of the angle between beam and surface normal;
- ``log_range``, ``log_range_sq``: ln(r / 1 m) and its square;
- ``reflectance``: the surface's measured reflectance (class reflectivity where it has none);
- ``log_signal``: ln(reflectance x cos / (r / 10 m)^2), the lidar equation's received power;
- ``label.<name>``: 1 on a surface of that semantic class (`labels.py`);
- ``ring.<c>``: 1 for the sensor's channel c (its per-channel table order).

Why logistic and not a small MLP: one real sweep gives about 10^4 informative rays, too few to
train a network's interactions without overfitting a single scene; the logistic fit is convex
(one answer, no seed), its weights read as effects (grazing, range, dark surfaces, rings), it is
calibrated where the features are, and it evaluates in NumPy with no new dependency.

File format (a sensor profile beside the preset, e.g. `sensors/lidar/hdl32e.drop.yaml`; a sensor
YAML selects it with ``drop: {model: PATH}``, PATH relative to that YAML): ``format:
scube_sim.drop_model``, ``version: 1``, ``sensor``, ``source`` (what it was fitted on),
``intercept``, ``coefficients`` (term -> weight; a term the file lacks weighs 0, so an unseen
label or ring falls back to the reference), and optional ``notes`` and ``scores``.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml

from ..atomic import atomic_path
from ..config import ConfigError, load_yaml
from ..labels import LABEL_IDS, LABEL_NAMES

FORMAT = "scube_sim.drop_model"
VERSION = 1
CONTINUOUS = ("cos_incidence", "log_range", "log_range_sq", "reflectance", "log_signal")
_TERM = re.compile(r"^(cos_incidence|log_range|log_range_sq|reflectance|log_signal|label\.[a-z_]+|ring\.\d+)$")


def drop_features(cos_inc, rng, reflectance, label, channel) -> dict[str, np.ndarray]:
    """The model's terms for N echoes: |cos incidence| (N,), range (N,) metres, reflectance (N,),
    label ids (N,), channel (N,) int. Returns term -> (N,) float64 (categorical terms one-hot,
    only those present)."""
    cos_inc = np.clip(np.asarray(cos_inc, np.float64), 0.0, 1.0)
    lr = np.log(np.maximum(np.asarray(rng, np.float64), 0.1))
    refl = np.maximum(np.asarray(reflectance, np.float64), 0.0)
    out = {"cos_incidence": cos_inc, "log_range": lr, "log_range_sq": lr ** 2, "reflectance": refl,
           "log_signal": np.log(np.maximum(refl * cos_inc, 1e-4)) - 2.0 * (lr - np.log(10.0))}
    label = np.asarray(label, np.int64)
    for k in np.unique(label):
        if 0 <= k < len(LABEL_NAMES):
            out[f"label.{LABEL_NAMES[k]}"] = (label == k).astype(np.float64)
    channel = np.asarray(channel, np.int64)
    for c in np.unique(channel[channel >= 0]):
        out[f"ring.{c}"] = (channel == c).astype(np.float64)
    return out


@dataclass
class DropModel:
    """A logistic drop model (see the module doc). coefficients: term -> weight."""

    intercept: float
    coefficients: dict[str, float]
    sensor: str = ""
    source: str = ""
    notes: str = ""
    scores: dict = field(default_factory=dict)

    def logit(self, features: dict[str, np.ndarray]) -> np.ndarray:
        n = len(next(iter(features.values())))
        z = np.full(n, float(self.intercept))
        for term, w in self.coefficients.items():
            x = features.get(term)
            if x is not None:
                z += w * x
        return z

    def probability(self, cos_inc, rng, reflectance, label, channel) -> np.ndarray:
        """p(drop) (N,) in [0, 1] for echoes described as in `drop_features`."""
        z = self.logit(drop_features(cos_inc, rng, reflectance, label, channel))
        return 0.5 * (1.0 + np.tanh(0.5 * z))  # the logistic function, without overflow

    def save(self, path: str | Path) -> Path:
        data = {"format": FORMAT, "version": VERSION, "sensor": self.sensor, "source": self.source,
                "notes": self.notes, "intercept": round(float(self.intercept), 6),
                "coefficients": {k: round(float(v), 6) for k, v in self.coefficients.items()}}
        if self.scores:
            data["scores"] = self.scores
        path = Path(path)
        with atomic_path(path) as tmp:
            Path(tmp).write_text(yaml.safe_dump(data, sort_keys=False, width=100), encoding="utf-8")
        return path

    @classmethod
    def load(cls, path: str | Path) -> "DropModel":
        """Read a drop-model file; ConfigError names the file and the key."""
        path = Path(path)
        data = load_yaml(path)
        if not isinstance(data, dict) or data.get("format") != FORMAT:
            raise ConfigError(f"{path}: key 'format': expected {FORMAT!r} (a drop-model file)")
        if data.get("version") != VERSION:
            raise ConfigError(f"{path}: key 'version': expected {VERSION}, got {data.get('version')!r}")
        try:
            intercept = float(data["intercept"])
        except (KeyError, TypeError, ValueError):
            raise ConfigError(f"{path}: key 'intercept': expected a number") from None
        coef = data.get("coefficients")
        if not isinstance(coef, dict):
            raise ConfigError(f"{path}: key 'coefficients': expected a mapping of term to weight")
        out = {}
        for term, w in coef.items():
            if not isinstance(term, str) or not _TERM.match(term):
                raise ConfigError(f"{path}: coefficients: unknown term {term!r}; terms: {', '.join(CONTINUOUS)}, "
                                  f"label.<name>, ring.<channel>")
            if term.startswith("label.") and term[6:] not in LABEL_IDS:
                raise ConfigError(f"{path}: coefficients: {term!r} names no label of labels.py")
            if isinstance(w, bool) or not isinstance(w, (int, float)) or not np.isfinite(w):
                raise ConfigError(f"{path}: coefficients.{term}: expected a finite number, got {w!r}")
            out[term] = float(w)
        if not np.isfinite(intercept):
            raise ConfigError(f"{path}: key 'intercept': expected a finite number")
        return cls(intercept, out, str(data.get("sensor", "")), str(data.get("source", "")),
                   str(data.get("notes", "")), data.get("scores") or {})
