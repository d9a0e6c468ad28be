"""A sink that records a whole run as one animated USD stage.

Layout (upAxis Z, metersPerUnit 1, default prim ``/World``)::

    /World                       Xform
      Scene                      ParticleField3DGaussianSplat (run.scene, static; optional)
      Ego                        Xform   xformOp:transform (matrix4d) sampled at each tick time,
                                         scube_sim:frameIndex (int) sampled likewise
      Sensors                    Scope
        <name>                   Xform   xformOp:transform = SensorFrame.pose (sensor-to-world at
                                         t_ref) sampled at each sweep's t_end; scube_sim:tStart,
                                         scube_sim:tRef (double), scube_sim:sweepIndex (int) likewise
          Points                 Points  points (float3[], sensor frame), extent, and vertex
                                         primvars intensity ring label time instance (and observed
                                         confidence where the sensor's first sweep has them: a
                                         converted scene's), sampled at the same times; widths
                                         constant (not sampled)

Time base: one for all sensors, time code = (t - run.start_time) * run.time_codes_per_second
(the stage's timeCodesPerSecond; framesPerSecond is set the same); startTimeCode / endTimeCode
= the first / last sample written. The root layer's customLayerData holds
``scube_sim:startTime`` (host seconds at time code 0) and ``scube_sim:origin``.

Precision: poses are float64 matrices (``matrix4d`` ops are always double), so a sensor at 1e6 m
keeps sub-millimetre placement; only the sensor-frame points are float32.

Between samples USD interpolates linearly (e.g. two sweeps with the same point count are
blended at an in-between time code); read values at the authored time codes.

Value clips (``clips=True``): samples go into an in-memory chunk layer; every
`frames_per_clip` frames it is written atomically to ``<stem>_clips/clip_NNNNN.usdc`` beside the
root and dropped, so memory stays flat. The root layer holds only definitions and, per track
(``/World/Ego`` and each ``/World/Sensors/<name>``), a ``default`` clip set: assetPaths (the
chunks in which the track has samples), primPath (the track itself), active (each chunk from the
track's first sample in it), times (identity, at the track's first and last sample in each
chunk), and a manifest (``<stem>_clips/manifest.usda``) declaring every sampled attribute. Clip
boundaries are at the track's own samples because USD reports every clipActive / clipTimes
entry as a time sample; anchored this way the composed stage has exactly the samples of a flat
one. The root is rewritten (atomically) after each chunk, so even a hard kill leaves a stage
covering the chunks completed; `close()` adds the last, partial chunk.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from ...errors import InputError
from ...io.usd import (
    add_points_prim,
    add_scene,
    check_usd_suffix,
    matrix4d,
    points_extent,
    primvar_type,
    set_stage_metadata,
    vec3f,
    write_layer,
)
from ...lidar.model import CONVERTED_POINT_DTYPE, PROVENANCE_FIELDS
from ...transforms import check_pose
from ..frame import Frame
from .base import RunInfo, Sink

__all__ = ["UsdSink", "SCENE_PATH", "EGO_PATH", "SENSORS_PATH", "POINTS_NAME", "DEFAULT_PRIMVARS"]

SCENE_PATH = "/World/Scene"
EGO_PATH = "/World/Ego"
SENSORS_PATH = "/World/Sensors"
POINTS_NAME = "Points"
DEFAULT_PRIMVARS = ("intensity", "ring", "label", "time", "instance")
CLIP_SET = "default"


def _pxr() -> SimpleNamespace:
    """pxr's modules, imported on first use (slow to import): `scube_sim.sim` imports this sink, and only a run that
    writes a stage needs USD."""
    from pxr import Gf, Sdf, Tf, Usd, UsdGeom, Vt

    return SimpleNamespace(Gf=Gf, Sdf=Sdf, Tf=Tf, Usd=Usd, UsdGeom=UsdGeom, Vt=Vt)


@dataclass
class _Sampled:
    """One time-sampled attribute: where, its type, and (for primvars) the numpy storage type."""

    prim: str
    name: str
    type_name: object
    custom: bool


@dataclass
class _Track:
    """A prim subtree sampled at its own times: the ego or one sensor (one clip set each)."""

    path: str
    name: str = ""
    last_tc: float | None = None
    chunk_first: float | None = None
    chunk_last: float | None = None
    clips: list = field(default_factory=list)  # (asset path, first tc, last tc)
    primvars: tuple = ()  # the point fields written as primvars on this sensor's Points


class UsdSink(Sink):
    """Writes the run into one USD stage at `path` (.usda / .usdc / .usd); see the module doc.

    clips: write time samples into value-clip layers of `frames_per_clip` frames each (flat
    memory for long runs) instead of one layer held until `close()`. write_scene: author
    run.scene (VoxSplat / Gaussians) under /World/Scene. point_width: metres, constant.
    primvars: point fields written as vertex primvars. clip_suffix: the clip layers' format.
    Opening removes stale clip files of an earlier run at the same path."""

    def __init__(self, path: str | Path, *, clips: bool = False, frames_per_clip: int = 100,
                 write_scene: bool = True, point_width: float = 0.05, primvars=DEFAULT_PRIMVARS,
                 clip_suffix: str = ".usdc"):
        self.path = Path(path)
        self.suffix = check_usd_suffix(self.path)
        check_usd_suffix(Path("clip" + clip_suffix))
        if int(frames_per_clip) < 1:
            raise InputError(f"UsdSink: frames_per_clip must be >= 1, got {frames_per_clip}")
        unknown = set(primvars) - set(CONVERTED_POINT_DTYPE.names) | set(primvars) & {"x", "y", "z"}
        if unknown:
            raise InputError(f"UsdSink: primvars {sorted(unknown)} are not LiDAR point fields (besides x y z)")
        self.clips = bool(clips)
        self.frames_per_clip = int(frames_per_clip)
        self.write_scene = bool(write_scene)
        self.point_width = float(point_width)
        self.primvars = tuple(primvars)
        self.clip_suffix = clip_suffix.lower()
        self.clip_dir = self.path.with_name(f"{self.path.stem}_clips")
        self.manifest_path = self.clip_dir / "manifest.usda"
        self.clip_paths: list[Path] = []
        self.frames_written = 0
        self.held_frames = 0  # frames whose samples are in memory (the current chunk, or all)
        self.held_samples = 0  # time samples in memory
        self._stage = None
        self._chunk = None
        self._sampled: list[_Sampled] = []
        self._tracks: dict[str, _Track] = {}
        self._prim_names: dict[str, str] = {}
        self._first_tc: float | None = None
        self._last_tc: float | None = None

    # ---------------------------------------------------------------- setup
    def open(self, run: RunInfo) -> None:
        pxr = _pxr()
        Gf, Usd, UsdGeom = pxr.Gf, pxr.Usd, pxr.UsdGeom

        self._tcps = float(run.time_codes_per_second)
        self._start = float(run.start_time)
        if not np.isfinite(self._start):
            raise InputError(f"UsdSink: start_time must be finite, got {run.start_time!r}")
        self._stage = stage = Usd.Stage.CreateInMemory(f"scube_sim_run{self.suffix}")
        set_stage_metadata(stage, documentation="scube_sim simulation run", time_codes_per_second=self._tcps)
        origin = np.asarray(run.origin, np.float64).reshape(3)
        stage.GetRootLayer().customLayerData = {"scube_sim:startTime": self._start,
                                                "scube_sim:origin": Gf.Vec3d(*map(float, origin))}
        if self.write_scene and run.scene is not None:
            add_scene(stage, SCENE_PATH, run.scene)
        ego = UsdGeom.Xform.Define(stage, EGO_PATH)
        ego.AddTransformOp(UsdGeom.XformOp.PrecisionDouble)
        self._declare(ego.GetPrim(), "scube_sim:frameIndex", "Int")
        self._register(EGO_PATH, "xformOp:transform", "Matrix4d", custom=False)
        self._tracks[EGO_PATH] = _Track(EGO_PATH, "ego")
        UsdGeom.Scope.Define(stage, SENSORS_PATH)
        for name, info in (run.sensors or {}).items():
            if not isinstance(info, dict) or info.get("kind", "lidar") == "lidar":
                self._define_sensor(str(name), info if isinstance(info, dict) else {})
        if self.clips:
            self.clip_dir.mkdir(parents=True, exist_ok=True)
            for old in self.clip_dir.glob("clip_*.usd*"):
                old.unlink()
            self._save_root()  # a valid (empty) stage from the start

    def _declare(self, prim, name: str, type_name: str):
        prim.CreateAttribute(name, getattr(_pxr().Sdf.ValueTypeNames, type_name), custom=True)
        self._register(prim.GetPath().pathString, name, type_name, custom=True)

    def _register(self, prim: str, name: str, type_name, custom: bool) -> None:
        if isinstance(type_name, str):
            type_name = getattr(_pxr().Sdf.ValueTypeNames, type_name)
        entry = _Sampled(prim, name, type_name, custom)
        self._sampled.append(entry)
        if self._chunk is not None:
            _add_specs(self._chunk, [entry])

    def _define_sensor(self, name: str, info: dict, fields=()) -> _Track:
        """The sensor's prims; `fields`: the first sweep's point fields (a converted scene's
        observed / confidence become primvars where present; later sweeps without them write 1)."""
        pxr = _pxr()
        Tf, UsdGeom = pxr.Tf, pxr.UsdGeom

        prim_name = Tf.MakeValidIdentifier(name)
        if prim_name in self._prim_names:
            raise InputError(f"UsdSink: sensors {self._prim_names[prim_name]!r} and {name!r} map to the "
                             f"same prim name {prim_name!r}")
        self._prim_names[prim_name] = name
        path = f"{SENSORS_PATH}/{prim_name}"
        xf = UsdGeom.Xform.Define(self._stage, path)
        xf.AddTransformOp(UsdGeom.XformOp.PrecisionDouble)
        prim = xf.GetPrim()
        if prim_name != name:
            prim.SetCustomDataByKey("scube_sim:name", name)
        for key, value in info.items():
            if isinstance(value, (bool, int, float, str, np.integer, np.floating)):
                prim.SetCustomDataByKey(f"scube_sim:{key}", value.item() if isinstance(value, np.generic) else value)
            elif key == "mount" and np.shape(value) == (4, 4):
                prim.SetCustomDataByKey("scube_sim:mount", matrix4d(value))
        self._register(path, "xformOp:transform", "Matrix4d", custom=False)
        for attr, type_name in (("scube_sim:tStart", "Double"), ("scube_sim:tRef", "Double"),
                                ("scube_sim:sweepIndex", "Int")):
            self._declare(prim, attr, type_name)
        pts_path = f"{path}/{POINTS_NAME}"
        primvars = self.primvars + tuple(f for f, _ in PROVENANCE_FIELDS if f in fields and f not in self.primvars)
        add_points_prim(self._stage, pts_path, width=self.point_width,
                        primvars={f: CONVERTED_POINT_DTYPE[f] for f in primvars}, who="UsdSink")
        self._register(pts_path, "points", "Point3fArray", custom=False)
        self._register(pts_path, "extent", "Float3Array", custom=False)
        for f in primvars:
            self._register(pts_path, f"primvars:{Tf.MakeValidIdentifier(f)}",
                           primvar_type(CONVERTED_POINT_DTYPE[f])[0], custom=False)
        track = self._tracks[path] = _Track(path, name, primvars=primvars)
        return track

    # ---------------------------------------------------------------- writing
    def _tc(self, t: float) -> float:
        return (float(t) - self._start) * self._tcps

    def write(self, frame: Frame) -> None:
        pxr = _pxr()
        Sdf, Tf = pxr.Sdf, pxr.Tf

        if self._stage is None:
            raise RuntimeError("UsdSink.write before open()")
        ops = []  # (attribute path, time code, value): everything checked before anything is authored
        last = {}  # track path -> last time code, including this frame's pending samples

        def advance(track: _Track, tc: float, what: str) -> None:
            prev = last.get(track.path, track.last_tc)
            if not np.isfinite(tc) or (prev is not None and tc <= prev):
                raise InputError(f"UsdSink: {what}: time code {tc} is not after the previous sample {prev}")
            last[track.path] = tc

        tc = self._tc(frame.time)
        ego = self._tracks[EGO_PATH]
        advance(ego, tc, f"frame {frame.index}")
        ops.append((ego, f"{EGO_PATH}.xformOp:transform", tc, matrix4d(check_pose(frame.ego_pose, "ego_pose"))))
        ops.append((ego, f"{EGO_PATH}.scube_sim:frameIndex", tc, int(frame.index)))
        for s in frame.sweeps():
            if s.kind != "lidar":
                continue
            path = f"{SENSORS_PATH}/{Tf.MakeValidIdentifier(s.name)}"
            track = self._tracks.get(path)
            if track is None:
                track = self._define_sensor(s.name, {"kind": s.kind}, np.asarray(s.points).dtype.names or ())
            elif track.name != s.name:
                raise InputError(f"UsdSink: sensors {track.name!r} and {s.name!r} map to the same prim {path}")
            stc = self._tc(s.t_end)
            advance(track, stc, f"sensor {s.name!r} sweep {s.sweep_index}")
            pts = np.asarray(s.points)
            missing = {"x", "y", "z", *self.primvars} - set(pts.dtype.names or ())
            if missing:
                raise InputError(f"UsdSink: sensor {s.name!r}: points lack fields {sorted(missing)}")
            xyz = np.stack([pts["x"], pts["y"], pts["z"]], axis=1).astype(np.float32, copy=False)
            if not np.all(np.isfinite(xyz)):
                raise InputError(f"UsdSink: sensor {s.name!r} sweep {s.sweep_index}: NaN or Inf points")
            ops.append((track, f"{path}.xformOp:transform", stc, matrix4d(check_pose(s.pose, f"{s.name} pose"))))
            ops.append((track, f"{path}.scube_sim:tStart", stc, float(s.t_start)))
            ops.append((track, f"{path}.scube_sim:tRef", stc, float(s.t_ref)))
            ops.append((track, f"{path}.scube_sim:sweepIndex", stc, int(s.sweep_index)))
            pp = f"{path}/{POINTS_NAME}"
            ops.append((track, f"{pp}.points", stc, vec3f(xyz)))
            ops.append((track, f"{pp}.extent", stc, vec3f(points_extent(xyz, self.point_width))))
            for f in track.primvars:
                _, vt_array, np_type = primvar_type(CONVERTED_POINT_DTYPE[f])
                col = pts[f] if f in pts.dtype.names else np.ones(len(pts), np_type)  # nothing inferred
                value = vt_array.FromNumpy(np.ascontiguousarray(col, dtype=np_type))
                ops.append((track, f"{pp}.primvars:{Tf.MakeValidIdentifier(f)}", stc, value))

        layer = self._target_layer()
        with Sdf.ChangeBlock():
            for _, attr, t, value in ops:
                layer.SetTimeSample(Sdf.Path(attr), t, value)
        for track, _, t, _ in ops:
            track.last_tc = t
            track.chunk_first = t if track.chunk_first is None else track.chunk_first
            track.chunk_last = t
            self._first_tc = t if self._first_tc is None else min(self._first_tc, t)
            self._last_tc = t if self._last_tc is None else max(self._last_tc, t)
        self.frames_written += 1
        self.held_frames += 1
        self.held_samples += len(ops)
        if self.clips and self.held_frames >= self.frames_per_clip:
            self._flush_clip()

    def _target_layer(self):
        if not self.clips:
            return self._stage.GetRootLayer()
        if self._chunk is None:
            self._chunk = _pxr().Sdf.Layer.CreateAnonymous(f"scube_sim_clip{self.clip_suffix}")
            _add_specs(self._chunk, self._sampled)
        return self._chunk

    # ---------------------------------------------------------------- clips and saving
    def _flush_clip(self) -> bool:
        """Write the current chunk as the next clip and the root; False if there was none."""
        if self._chunk is None or self.held_frames == 0:
            return False
        name = f"clip_{len(self.clip_paths):05d}{self.clip_suffix}"
        write_layer(self._chunk, self.clip_dir / name)
        self.clip_paths.append(self.clip_dir / name)
        asset = f"./{self.clip_dir.name}/{name}"
        for track in self._tracks.values():
            if track.chunk_first is not None:
                track.clips.append((asset, track.chunk_first, track.chunk_last))
            track.chunk_first = track.chunk_last = None
        self._chunk = None  # dropped: memory stays flat
        self.held_frames = self.held_samples = 0
        self._save_root()
        return True

    def _save_root(self) -> None:
        pxr = _pxr()
        Gf, Sdf, Vt = pxr.Gf, pxr.Sdf, pxr.Vt

        root = self._stage.GetRootLayer()
        if self.clips:
            write_layer(_manifest(self._sampled), self.manifest_path)
            layer = Sdf.Layer.CreateAnonymous(f"scube_sim_run{self.suffix}")
            layer.TransferContent(root)
            manifest = Sdf.AssetPath(f"./{self.clip_dir.name}/{self.manifest_path.name}")
            for track in self._tracks.values():
                if not track.clips:
                    continue
                times = []
                for _, first, last in track.clips:
                    times.append(Gf.Vec2d(first, first))
                    if last > first:
                        times.append(Gf.Vec2d(last, last))
                layer.GetPrimAtPath(track.path).SetInfo("clips", {CLIP_SET: {
                    "assetPaths": Sdf.AssetPathArray([Sdf.AssetPath(a) for a, _, _ in track.clips]),
                    "primPath": track.path,
                    "active": Vt.Vec2dArray([Gf.Vec2d(first, k) for k, (_, first, _) in enumerate(track.clips)]),
                    "times": Vt.Vec2dArray(times),
                    "manifestAssetPath": manifest,
                }})
            # the range the clips written so far cover
            covered = [t for tr in self._tracks.values() for _, a, b in tr.clips for t in (a, b)]
            first, last = (min(covered), max(covered)) if covered else (None, None)
        else:
            layer, first, last = root, self._first_tc, self._last_tc
        if first is not None:
            layer.startTimeCode, layer.endTimeCode = first, last
        write_layer(layer, self.path)

    def close(self) -> None:
        """Write what is held (the last chunk, or the whole single layer) and the root layer."""
        if self._stage is None:
            return
        try:
            if self.clips:
                if not self._flush_clip():
                    self._save_root()
            else:
                self._save_root()
        finally:
            self._stage = self._chunk = None
            self.held_frames = self.held_samples = 0


def _add_specs(layer, entries) -> None:
    """`over` prim specs with the sampled attributes declared (type only) in `layer`."""
    Sdf = _pxr().Sdf

    for e in entries:
        prim = layer.GetPrimAtPath(e.prim) or Sdf.CreatePrimInLayer(layer, e.prim)
        prim.specifier = Sdf.SpecifierOver
        if e.name not in prim.attributes:
            Sdf.AttributeSpec(prim, e.name, e.type_name, Sdf.VariabilityVarying, declaresCustom=e.custom)


def _manifest(entries):
    """The value-clip manifest: every sampled attribute, declared, without values."""
    layer = _pxr().Sdf.Layer.CreateAnonymous("scube_sim_manifest.usda")
    _add_specs(layer, entries)
    return layer
