"""VoxSplat: 3D Gaussians on a sparse voxel scaffold (SCube, NeurIPS 2024).

Each occupied voxel holds M Gaussians with 14 raw values each, in this order:
offset(3), opacity(1), scale(3), quaternion wxyz(4), RGB as the SH degree-0 coefficient(3).
Activations (paper): ``mu = r * tanh(offset) + voxel_center`` with ``r = offset_range * voxel_size``
(paper: 3 voxels), ``alpha = sigmoid(opacity)``, ``s = exp(scale)`` in metres,
``R = quat2rot(normalize(q))``, ``colour = clip(0.5 + C0 * rgb, 0, 1)``. The layout and the
activations have one definition, `splat_params` (numpy; its torch twin is `model.activations`).

Optional channels: anything a later stage adds (observation flags and confidence per voxel,
reflectance per Gaussian, a sky panorama per scene) is a named `Channel` in ``VoxSplat.channels``,
not a new field: one per voxel (leading dim V), per Gaussian (V, M) or per scene (any shape).
`KNOWN_CHANNELS` documents the names the project uses; other names are kept as they are.

File format (.npz, `save` / `load`): version 1 holds the core arrays; version 2 adds the channels
(a JSON manifest under ``channels`` and one array per channel under ``channel.<name>``). A VoxSplat
without channels is written as version 1, so files that need no channel stay readable by older
releases; `load` reads both.

Frames: voxel ``ijk`` has its centre at ``(ijk + 0.5) * voxel_size`` in the *local* frame, whose
origin sits at ``origin`` (float64, metres) in the world frame. All geometry is kept local so that
float32 never has to hold large world coordinates (float32 at 1e6 m resolves only 6 cm).
"""

from __future__ import annotations

import copy
import json
import re
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from . import splat_params as sp
from .atomic import atomic_path
from .config import json_loads
from .errors import InputError, NotFoundError, ScubeSimWarning
from .labels import NUM_LABELS
from .splat_params import NUM_RAW, OFFSET, OPACITY, QUAT, RGB, SCALE, SH_C0  # noqa: F401 (re-exported)
from .transforms import normalize_quat, quat_to_rotmat

FORMAT_NAME = "scube_sim.voxsplat"
FORMAT_VERSION = 2  # the newest version this module reads and writes (see the module doc)
CHANNEL_PER = ("voxel", "gaussian", "scene")
_CHANNEL_NAME = re.compile(r"^[a-z][a-z0-9_]*$")


@dataclass(frozen=True)
class ChannelSpec:
    """A channel name's meaning: `per` voxel, Gaussian or scene; `dtype`; trailing `shape` per
    element (None: any); `bounds` (lo, hi) of the values where they are bounded (NaN allowed
    where `nan_ok`: 'not known')."""

    per: str
    dtype: str
    shape: tuple | None
    doc: str
    bounds: tuple[float, float] | None = None
    nan_ok: bool = False


# The channels the project's stages write (readers use them where present, ignore the rest).
KNOWN_CHANNELS = {
    "observed": ChannelSpec("voxel", "bool", (), "an input camera saw the voxel"),
    "confidence": ChannelSpec("voxel", "float32", (), "the converter's confidence in the voxel, in [0, 1]"),
    "reflectance": ChannelSpec("gaussian", "float32", (),
                               "measured near-infrared (~905 nm) reflectance, Lambertian-equivalent: 0-1 for "
                               "diffuse surfaces (1 = a white target), above 1 for retroreflectors; NaN where "
                               "not measured (the LiDAR model then uses the class reflectivity; "
                               "`lidar.response`)", bounds=(0.0, 100.0), nan_ok=True),
    "sky_panorama": ChannelSpec("scene", "float32", None,
                                "(H, W, 3) equirectangular sky RGB in [0, 1] in the scene's axes (z up): pixel (r, c) "
                                "looks along azimuth 2 pi (c + 0.5) / W - pi from +x towards +y at elevation "
                                "pi / 2 - pi (r + 0.5) / H (row 0 the zenith; `model.sky`)"),
}


@dataclass
class Channel:
    """One optional named array of a VoxSplat: `per` 'voxel' (V, ...), 'gaussian' (V, M, ...) or
    'scene' (any shape)."""

    per: str
    data: np.ndarray


def voxel_keys(ijk: np.ndarray) -> np.ndarray:
    """(N, 3) integer voxel indices -> (N,) int64 keys that sort like (i, j, k); |index| < 2^20."""
    ijk = np.asarray(ijk, np.int64)
    if ijk.size and np.abs(ijk).max() >= 1 << 20:
        raise InputError("voxel indices beyond +-2^20: the scene is too large for this voxel size")
    b = ijk + (1 << 20)
    return (b[:, 0] << 42) | (b[:, 1] << 21) | b[:, 2]


def unique_voxels(ijk: np.ndarray):
    """Unique voxels of (N, 3) indices: (unique (V, 3) int64, inverse (N,), counts (V,))."""
    keys = voxel_keys(ijk)
    uk, inv, counts = np.unique(keys, return_inverse=True, return_counts=True)
    mask = (1 << 21) - 1
    uniq = np.stack([(uk >> 42) & mask, (uk >> 21) & mask, uk & mask], 1) - (1 << 20)
    return uniq, inv.reshape(-1), counts


@dataclass
class Gaussians:
    """Activated Gaussians, flat. Positions are in the local frame of `origin`.

    means (N, 3) float64 m; scales (N, 3) float64 m (std-devs along the rotated axes);
    quats (N, 4) float64 unit wxyz; opacities (N,) float64 in [0, 1]; sh_dc (N, 3) float32;
    voxel (N,) int64 index of the owning voxel (-1 when not on a scaffold); slot (N,) int16.
    """

    means: np.ndarray
    scales: np.ndarray
    quats: np.ndarray
    opacities: np.ndarray
    sh_dc: np.ndarray
    voxel: np.ndarray | None = None
    slot: np.ndarray | None = None
    origin: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def __len__(self) -> int:
        return int(self.means.shape[0])

    @property
    def colors(self) -> np.ndarray:
        """(N, 3) float32 RGB in [0, 1] from the SH degree-0 term."""
        return np.clip(0.5 + SH_C0 * self.sh_dc, 0.0, 1.0).astype(np.float32)

    def rotations(self) -> np.ndarray:
        """(N, 3, 3) float64 rotation matrices."""
        return quat_to_rotmat(self.quats)

    def subset(self, mask_or_index) -> "Gaussians":
        sel = mask_or_index
        return Gaussians(
            self.means[sel], self.scales[sel], self.quats[sel], self.opacities[sel], self.sh_dc[sel],
            None if self.voxel is None else self.voxel[sel],
            None if self.slot is None else self.slot[sel],
            self.origin.copy(),
        )

    def strongest(self, n: int) -> "Gaussians":
        """The `n` Gaussians that cover the most surface, in their original order: ranked by opacity
        times the area of their two largest std-devs (alpha * s1 * s2, m^2), ties to the lower
        index, so a 3DGS trainer starts from the surfaces rather than from faint or tiny splats.
        All of them when n >= N."""
        if n < 0:
            raise InputError(f"max Gaussians: expected a count >= 0, got {n}")
        if n >= len(self):
            return self
        s = np.sort(self.scales, axis=1)
        score = self.opacities * s[:, 1] * s[:, 2]
        keep = np.sort(np.argsort(-score, kind="stable")[:n])
        return self.subset(keep)

    def check_finite(self, source: str = "gaussians") -> None:
        """Raise ValueError naming the field if any value is NaN or Inf."""
        for name in ("means", "scales", "quats", "opacities", "sh_dc"):
            a = getattr(self, name)
            bad = ~np.isfinite(a)
            if np.any(bad):
                idx = int(np.argwhere(bad)[0][0])
                raise InputError(f"{source}: {name} contains NaN or Inf (first at Gaussian {idx})")
        if not np.all(np.isfinite(self.origin)):
            raise InputError(f"{source}: origin contains NaN or Inf")


@dataclass
class VoxSplat:
    """Sparse voxels with M Gaussians each (raw parameters) and per-voxel semantics.

    ijk (V, 3) int32; params (V, M, 14) float32 raw; valid (V, M) bool (False marks an empty
    slot, e.g. a voxel that held fewer than M Gaussians); labels (V,) int16 ids of `labels.py`;
    logits (V, C) float32 or None; voxel_size metres; origin (3,) float64 world position of the
    local frame; offset_range in voxels (r = offset_range * voxel_size).
    """

    ijk: np.ndarray
    params: np.ndarray
    voxel_size: float
    origin: np.ndarray = field(default_factory=lambda: np.zeros(3))
    valid: np.ndarray | None = None
    labels: np.ndarray | None = None
    logits: np.ndarray | None = None
    offset_range: float = 3.0
    metadata: dict = field(default_factory=dict)
    channels: dict[str, Channel] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.ijk = np.ascontiguousarray(self.ijk, dtype=np.int32).reshape(-1, 3)
        self.params = np.ascontiguousarray(self.params, dtype=np.float32)
        if self.params.ndim != 3 or self.params.shape[2] != NUM_RAW:
            raise InputError(f"params: expected shape (V, M, {NUM_RAW}), got {self.params.shape}")
        if self.params.shape[0] != self.ijk.shape[0]:
            raise InputError(f"params has {self.params.shape[0]} voxels but ijk has {self.ijk.shape[0]}")
        self.origin = np.asarray(self.origin, dtype=np.float64).reshape(3)
        self.voxel_size = float(self.voxel_size)
        if not (np.isfinite(self.voxel_size) and self.voxel_size > 0):
            raise InputError(f"voxel_size: expected a positive number of metres, got {self.voxel_size}")
        if not np.all(np.isfinite(self.origin)):
            raise InputError("origin: contains NaN or Inf")
        v, m = self.params.shape[:2]
        self.valid = np.ones((v, m), bool) if self.valid is None else np.asarray(self.valid, bool).reshape(v, m)
        self.labels = np.zeros(v, np.int16) if self.labels is None else np.asarray(self.labels, np.int16).reshape(v)
        if self.logits is not None:
            self.logits = np.asarray(self.logits, np.float32).reshape(v, -1)
        given, self.channels = dict(self.channels), {}
        for name, ch in given.items():
            self.set_channel(name, ch.data, ch.per)

    # --- optional channels -------------------------------------------------------------------
    def set_channel(self, name: str, data, per: str | None = None) -> None:
        """Add or replace channel `name`; `per` defaults to the known channel's (KNOWN_CHANNELS)."""
        if not isinstance(name, str) or not _CHANNEL_NAME.match(name):
            raise InputError(f"channel name {name!r}: expected lower-case letters, digits and '_'")
        spec = KNOWN_CHANNELS.get(name)
        per = per or (spec.per if spec else None)
        if per not in CHANNEL_PER:
            raise InputError(f"channel {name!r}: per must be one of {', '.join(CHANNEL_PER)}, got {per!r}")
        if spec is not None and per != spec.per:
            raise InputError(f"channel {name!r} is per {spec.per}, got per {per}")
        arr = np.asarray(data) if spec is None else np.asarray(data, dtype=spec.dtype)
        lead = {"voxel": (self.num_voxels,), "gaussian": self.valid.shape, "scene": ()}[per]
        if arr.shape[:len(lead)] != lead:
            raise InputError(f"channel {name!r} (per {per}): expected leading shape {lead}, got {arr.shape}")
        if spec is not None and spec.shape is not None and arr.shape[len(lead):] != spec.shape:
            raise InputError(f"channel {name!r}: expected shape {lead + spec.shape}, got {arr.shape}")
        if arr.dtype == object:
            raise InputError(f"channel {name!r}: object arrays cannot be stored")
        if spec is not None and spec.bounds is not None:
            lo, hi = spec.bounds
            known = ~np.isnan(arr) if spec.nan_ok else np.ones(arr.shape, bool)
            bad = known & ~((arr >= lo) & (arr <= hi))
            if bad.any():
                raise InputError(f"channel {name!r}: values must lie in [{lo:g}, {hi:g}]"
                                 f"{' (or be NaN: not known)' if spec.nan_ok else ''}, got {arr[bad].flat[0]!r} "
                                 f"({int(bad.sum())} value(s) outside)")
        self.channels[name] = Channel(per, np.ascontiguousarray(arr))

    def channel(self, name: str) -> np.ndarray:
        """The array of channel `name`; NotFoundError lists the channels present."""
        if name not in self.channels:
            raise NotFoundError(f"VoxSplat has no channel {name!r}; it has: {', '.join(sorted(self.channels)) or 'none'}")
        return self.channels[name].data

    # --- sizes -------------------------------------------------------------------------------
    @property
    def num_voxels(self) -> int:
        return int(self.ijk.shape[0])

    @property
    def gaussians_per_voxel(self) -> int:
        return int(self.params.shape[1])

    @property
    def num_gaussians(self) -> int:
        return int(self.valid.sum())

    def __repr__(self) -> str:
        return (f"VoxSplat({self.num_voxels} voxels x M={self.gaussians_per_voxel}, "
                f"{self.num_gaussians} Gaussians, voxel {self.voxel_size:g} m, origin {self.origin.tolist()})")

    # --- activations (paper) -----------------------------------------------------------------
    def voxel_centers(self) -> np.ndarray:
        """(V, 3) float64 voxel centres, local frame, metres."""
        return (self.ijk.astype(np.float64) + 0.5) * self.voxel_size

    def keep_slots(self, m: int) -> "VoxSplat":
        """A new VoxSplat with the `m` most opaque valid Gaussians of each voxel (M = m; ties to
        the lower slot; slots beyond a voxel's valid ones stay invalid), their per-Gaussian
        channels with them. Fewer Gaussians trace faster; `m` >= M returns this one."""
        if not isinstance(m, (int, np.integer)) or m < 1:
            raise InputError(f"keep_slots: expected a number of Gaussians per voxel >= 1, got {m!r}")
        if m >= self.gaussians_per_voxel:
            return self
        score = np.where(self.valid, self.opacities(), -1.0)
        order = np.argsort(-score, axis=1, kind="stable")[:, :m]
        rows = np.arange(self.num_voxels)[:, None]
        channels = {name: Channel(ch.per, ch.data[rows, order] if ch.per == "gaussian" else ch.data)
                    for name, ch in self.channels.items()}
        return VoxSplat(self.ijk.copy(), self.params[rows, order], self.voxel_size, self.origin.copy(),
                        self.valid[rows, order], self.labels.copy(),
                        None if self.logits is None else self.logits.copy(), self.offset_range,
                        copy.deepcopy(self.metadata), channels)

    def select_voxels(self, keep) -> "VoxSplat":
        """A new VoxSplat of the voxels `keep` ((V,) bool mask or indices, in order): their
        parameters, labels, logits and per-voxel / per-Gaussian channels; scene channels and
        metadata as they are (copied)."""
        keep = np.asarray(keep)
        idx = np.flatnonzero(keep) if keep.dtype == bool else keep.astype(np.int64)
        if keep.dtype == bool and keep.shape != (self.num_voxels,):
            raise InputError(f"select_voxels: expected a ({self.num_voxels},) mask, got shape {keep.shape}")
        channels = {name: Channel(ch.per, ch.data if ch.per == "scene" else ch.data[idx])
                    for name, ch in self.channels.items()}
        return VoxSplat(self.ijk[idx], self.params[idx], self.voxel_size, self.origin.copy(), self.valid[idx],
                        self.labels[idx], None if self.logits is None else self.logits[idx], self.offset_range,
                        copy.deepcopy(self.metadata), channels)

    def means(self) -> np.ndarray:
        """(V, M, 3) float64 activated means, local frame."""
        return sp.offsets(self.params[..., OFFSET], self.offset_range * self.voxel_size) + self.voxel_centers()[:, None, :]

    def scales(self) -> np.ndarray:
        """(V, M, 3) float64 metres."""
        return sp.scales(self.params[..., SCALE])

    def quats(self) -> np.ndarray:
        """(V, M, 4) float64 unit wxyz (zero-norm raw quaternions become the identity)."""
        return normalize_quat(self.params[..., QUAT])

    def rotations(self) -> np.ndarray:
        """(V, M, 3, 3) float64."""
        return quat_to_rotmat(self.params[..., QUAT])

    def opacities(self) -> np.ndarray:
        """(V, M) float64 in [0, 1]."""
        return sp.opacities(self.params[..., 3])

    def colors(self) -> np.ndarray:
        """(V, M, 3) float32 RGB in [0, 1]."""
        return sp.colors(self.params[..., RGB])

    def gaussians(self, min_opacity: float | None = None) -> Gaussians:
        """The valid Gaussians, activated and flattened, with their voxel index and slot; with
        `min_opacity`, only those at least that opaque. The kept slots' raw values are gathered
        first and only they are activated (the activations work value by value, so the numbers
        are those of `means()` etc.): no (V, M) float64 temporaries, whose first-touch pages
        dominated building a tracer for millions of Gaussians."""
        vi, si = np.nonzero(self.valid)
        opacities = sp.opacities(self.params[vi, si, 3])
        if min_opacity is not None:
            keep = opacities >= min_opacity
            if not keep.all():
                vi, si, opacities = vi[keep], si[keep], opacities[keep]
        raw = self.params[vi, si]  # (N, 14) float32, one gather of the kept slots
        centres = (self.ijk[vi].astype(np.float64) + 0.5) * self.voxel_size  # voxel_centers()[vi]
        return Gaussians(
            means=sp.offsets(raw[:, OFFSET], self.offset_range * self.voxel_size) + centres,
            scales=sp.scales(raw[:, SCALE]),
            quats=normalize_quat(raw[:, QUAT]),
            opacities=opacities,
            sh_dc=np.ascontiguousarray(raw[:, RGB]),
            voxel=vi.astype(np.int64),
            slot=si.astype(np.int16),
            origin=self.origin.copy(),
        )

    def world_means(self) -> np.ndarray:
        """(N, 3) float64 means of the valid Gaussians in the world frame."""
        return self.gaussians().means + self.origin

    def check_finite(self, source: str = "VoxSplat") -> None:
        """Raise ValueError naming the parameter group if a raw value is NaN or Inf."""
        names = {"offset": OFFSET, "opacity": OPACITY, "scale": SCALE, "quaternion": QUAT, "rgb": RGB}
        for name, sl in names.items():
            bad = ~np.isfinite(self.params[..., sl])
            if np.any(bad):
                v, m = np.argwhere(bad)[0][:2]
                raise InputError(f"{source}: raw {name} contains NaN or Inf (voxel {v}, slot {m})")

    # --- construction ------------------------------------------------------------------------
    @classmethod
    def from_gaussians(
        cls,
        g: Gaussians,
        voxel_size: float,
        *,
        max_per_voxel: int | None = None,
        labels: np.ndarray | None = None,
        offset_range: float = 3.0,
        origin: np.ndarray | None = None,
    ) -> "VoxSplat":
        """Voxelize Gaussians by their centres.

        `g.means` are taken relative to `g.origin`; the result's origin is `origin` (default: a
        voxel-aligned point near the centre of the data, so local coordinates stay small).
        M is the largest number of Gaussians that share a voxel, capped at `max_per_voxel`
        (the extra Gaussians of a crowded voxel are dropped, lowest opacity first).
        labels: optional (N,) per-Gaussian label; a voxel takes its most frequent label.
        """
        g.check_finite("from_gaussians")
        voxel_size = float(voxel_size)
        if not voxel_size > 0:
            raise InputError(f"voxel_size: expected > 0, got {voxel_size}")
        world = g.means + g.origin
        if origin is None:
            if len(g):
                mid = 0.5 * (world.min(0) + world.max(0))
                origin = np.round(mid / voxel_size) * voxel_size
            else:
                origin = g.origin
        origin = np.asarray(origin, dtype=np.float64)
        local = world - origin
        uniq, inv, counts = unique_voxels(np.floor(local / voxel_size))
        m = int(counts.max()) if len(g) else 1
        if max_per_voxel is not None:
            m = min(m, int(max_per_voxel))
        # Order by voxel, then by decreasing opacity, so that a cap drops the faintest first.
        order = np.lexsort((-g.opacities, inv))
        inv_sorted = inv[order]
        starts = np.r_[0, np.cumsum(counts)[:-1]]
        slot = np.arange(len(g)) - starts[inv_sorted]
        keep = slot < m
        order, inv_sorted, slot = order[keep], inv_sorted[keep], slot[keep]

        v = uniq.shape[0]
        params = np.zeros((v, m, NUM_RAW), np.float32)
        params[..., 7] = 1.0  # identity quaternion in empty slots
        params[..., 3] = sp.EMPTY_OPACITY_RAW  # empty slots are transparent as well as invalid
        valid = np.zeros((v, m), bool)
        centers = (uniq.astype(np.float64) + 0.5) * voxel_size
        r = offset_range * voxel_size
        raw = np.empty((order.shape[0], NUM_RAW), np.float64)
        raw[:, OFFSET] = sp.offsets_to_raw(local[order] - centers[inv_sorted], r)
        raw[:, 3] = sp.opacities_to_raw(g.opacities[order])
        raw[:, SCALE] = sp.scales_to_raw(g.scales[order])
        raw[:, QUAT] = normalize_quat(g.quats[order])
        raw[:, RGB] = g.sh_dc[order]
        params[inv_sorted, slot] = raw
        valid[inv_sorted, slot] = True

        vox_labels = None
        if labels is not None:
            labels = np.asarray(labels, np.int64)
            pairs = inv * 1024 + labels
            up, pc = np.unique(pairs, return_counts=True)
            pv, pl = up // 1024, up % 1024
            best = np.lexsort((-pc, pv))  # per voxel, most frequent first
            first = np.r_[True, pv[best][1:] != pv[best][:-1]]
            vox_labels = np.zeros(v, np.int16)
            vox_labels[pv[best][first]] = pl[best][first]
        return cls(uniq.astype(np.int32), params, voxel_size, origin, valid, vox_labels,
                   offset_range=offset_range)

    # --- file format -------------------------------------------------------------------------
    def save(self, path: str | Path) -> Path:
        """Write the versioned .npz (atomically: temporary name, then rename); version 1 when
        there are no channels, else 2."""
        path = Path(path)
        arrays = dict(
            format=np.array(FORMAT_NAME), version=np.array(2 if self.channels else 1, np.int32),
            ijk=self.ijk, params=self.params, valid=self.valid, labels=self.labels,
            voxel_size=np.array(self.voxel_size), origin=self.origin,
            offset_range=np.array(self.offset_range),
            metadata=np.array(json.dumps(self.metadata, sort_keys=True)),
        )
        if self.logits is not None:
            arrays["logits"] = self.logits
        if self.channels:
            arrays["channels"] = np.array(json.dumps({n: c.per for n, c in sorted(self.channels.items())}))
            for name, ch in sorted(self.channels.items()):
                arrays[f"channel.{name}"] = ch.data
        with atomic_path(path) as tmp:
            with open(tmp, "wb") as fh:
                np.savez_compressed(fh, **arrays)
        return path

    @classmethod
    def load(cls, path: str | Path) -> "VoxSplat":
        """Read a .npz written by `save`; errors name the file and the key."""
        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"{path}: no such VoxSplat file")
        try:
            z = np.load(path, allow_pickle=False)
        except Exception as exc:  # zipfile/format errors
            raise InputError(f"{path}: not a readable .npz ({exc})") from None
        with z:
            def need(key):
                if key not in z.files:
                    raise InputError(f"{path}: missing key {key!r} (is this a scube_sim VoxSplat .npz?)")
                return _npz_member(z, path, key)

            fmt = str(need("format"))
            if fmt != FORMAT_NAME:
                raise InputError(f"{path}: key 'format' is {fmt!r}, expected {FORMAT_NAME!r}")
            version = _file_version(path, need("version"))
            a = {k: need(k) for k in ("ijk", "params", "valid", "labels", "voxel_size", "origin", "offset_range",
                                      "metadata")}
            if "logits" in z.files:
                a["logits"] = need("logits")
            channels = {}
            if version >= 2 and "channels" in z.files:
                try:
                    manifest = json_loads(str(need("channels")), f"{path}: key 'channels'", InputError)
                    assert isinstance(manifest, dict)
                except InputError:  # a channel named twice
                    raise
                except (ValueError, AssertionError):
                    raise InputError(f"{path}: key 'channels' is not a JSON mapping of channel name to kind") from None
                channels = {n: Channel(str(per), need(f"channel.{n}")) for n, per in manifest.items()}
        _check_arrays(path, a)
        try:
            vs = cls(ijk=a["ijk"], params=a["params"], voxel_size=float(a["voxel_size"]), origin=a["origin"],
                     valid=a["valid"], labels=a["labels"], logits=a.get("logits"),
                     offset_range=float(a["offset_range"]), metadata=json.loads(str(a["metadata"])),
                     channels={})
        except ValueError as exc:
            raise InputError(f"{path}: {exc}") from None
        for name, ch in channels.items():
            try:
                vs.set_channel(name, ch.data, ch.per)
            except InputError as exc:
                raise InputError(f"{path}: key 'channel.{name}': {exc}") from None
        vs.check_finite(str(path))
        vs.clamp_scales(str(path))
        return vs

    def clamp_scales(self, source: str = "VoxSplat") -> int:
        """Clamp raw scales of the valid Gaussians above MAX_SCALE_VOXELS voxels to that size,
        with a ScubeSimWarning that counts them; returns the count."""
        limit = float(np.log(sp.MAX_SCALE_VOXELS * self.voxel_size))
        big = (self.params[..., SCALE] > limit).any(axis=-1) & self.valid
        n = int(big.sum())
        if n:
            s = self.params[..., SCALE]
            self.params[..., SCALE] = np.where(big[..., None], np.minimum(s, np.float32(limit)), s)
            warnings.warn(f"{source}: {n} of {self.num_gaussians} Gaussians are wider than "
                          f"{sp.MAX_SCALE_VOXELS:g} voxels ({sp.MAX_SCALE_VOXELS * self.voxel_size:g} m); "
                          f"clamped to that", ScubeSimWarning, stacklevel=2)
        return n


# --- load-time checks: every key of a VoxSplat .npz, named when it is wrong ------------------------

def _npz_member(z, path: Path, key: str) -> np.ndarray:
    """Array `key` of the open .npz `z`, or one InputError naming the file and the array: an array
    of Python objects (it would need unpickling, which is never done) or a truncated or corrupt
    member."""
    try:
        return z[key]
    except ValueError as exc:
        if "allow_pickle" in str(exc):
            raise InputError(f"{path}: key {key!r} is an array of Python objects (dtype object), which a VoxSplat "
                             f"never holds; refused without unpickling it") from None
        raise InputError(f"{path}: key {key!r} is not a readable array ({' '.join(str(exc).split())})") from None
    except Exception as exc:  # noqa: BLE001  (zipfile, zlib and EOF errors of a damaged member)
        reason = " ".join(str(exc).split()) or type(exc).__name__
        raise InputError(f"{path}: key {key!r} is truncated or corrupt ({reason})") from None


def _file_version(path: Path, raw) -> int:
    if raw.shape != () or raw.dtype.kind not in "iu":
        raise InputError(f"{path}: key 'version': expected an integer scalar, got {raw.dtype} of shape {raw.shape}")
    version = int(raw)
    if version < 1:
        raise InputError(f"{path}: key 'version' is {version}: VoxSplat format versions start at 1")
    if version > FORMAT_VERSION:
        raise InputError(f"{path}: VoxSplat format version {version} is newer than this "
                         f"scube_sim reads ({FORMAT_VERSION})")
    return version


def _expect(path: Path, key: str, arr: np.ndarray, kinds: str, shape: tuple, what: str) -> None:
    """arr's dtype kind in `kinds` (numpy kind letters) and its shape `shape` (None: any length)."""
    if arr.dtype.kind not in kinds:
        raise InputError(f"{path}: key {key!r}: expected {what}, got dtype {arr.dtype}")
    if arr.ndim != len(shape) or any(s is not None and s != n for s, n in zip(shape, arr.shape)):
        want = "(" + ", ".join("N" if s is None else str(s) for s in shape) + ")"
        raise InputError(f"{path}: key {key!r}: expected shape {want}, got {arr.shape}")


def _check_arrays(path: Path, a: dict) -> None:
    """Dtypes, shapes, ranges and finiteness of a loaded .npz's arrays (the raw parameters'
    finiteness is `VoxSplat.check_finite`'s, which names the group, voxel and slot)."""
    _expect(path, "ijk", a["ijk"], "iu", (None, 3), "integer voxel indices")
    v = a["ijk"].shape[0]
    if v and int(np.abs(a["ijk"].astype(np.int64)).max()) >= 1 << 20:
        raise InputError(f"{path}: key 'ijk': voxel indices beyond +-2^20 (expected |i|, |j|, |k| < 1048576)")
    dup = v - len(np.unique(voxel_keys(a["ijk"]))) if v else 0
    if dup:
        raise InputError(f"{path}: key 'ijk': {dup} duplicate voxel(s); each voxel appears once")
    _expect(path, "params", a["params"], "f", (v, None, NUM_RAW), f"float raw values (V, M, {NUM_RAW})")
    if a["params"].shape[1] < 1:
        raise InputError(f"{path}: key 'params': expected at least one Gaussian slot per voxel, got M = 0")
    m = a["params"].shape[1]
    _expect(path, "valid", a["valid"], "b", (v, m), "a bool mask (V, M)")
    _expect(path, "labels", a["labels"], "iu", (v,), "integer label ids (V,)")
    if v and (int(a["labels"].min()) < 0 or int(a["labels"].max()) >= NUM_LABELS):
        raise InputError(f"{path}: key 'labels': ids must lie in [0, {NUM_LABELS}) (labels.py), got "
                         f"[{int(a['labels'].min())}, {int(a['labels'].max())}]")
    if "logits" in a:
        _expect(path, "logits", a["logits"], "f", (v, None), "float logits (V, C)")
        if not np.all(np.isfinite(a["logits"])):
            raise InputError(f"{path}: key 'logits' contains NaN or Inf")
    for key in ("voxel_size", "offset_range"):
        _expect(path, key, a[key], "fiu", (), "a number")
        if not (np.isfinite(a[key]) and float(a[key]) > 0):
            raise InputError(f"{path}: key {key!r}: expected a positive finite number, got {float(a[key])}")
    _expect(path, "origin", a["origin"], "fiu", (3,), "a float (3,) world position")
    if not np.all(np.isfinite(a["origin"])):
        raise InputError(f"{path}: key 'origin' contains NaN or Inf")
    if a["metadata"].dtype.kind != "U" or a["metadata"].shape != ():
        raise InputError(f"{path}: key 'metadata': expected a JSON string, got {a['metadata'].dtype}")
    try:
        meta = json_loads(str(a["metadata"]), f"{path}: key 'metadata'", InputError)
    except InputError:  # a key twice
        raise
    except ValueError:
        raise InputError(f"{path}: key 'metadata': not valid JSON") from None
    if not isinstance(meta, dict):
        raise InputError(f"{path}: key 'metadata': expected a JSON object, got {type(meta).__name__}")
