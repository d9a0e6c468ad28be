"""The LiDAR model's validated configuration (pydantic) and its YAML load/dump.

A preset is one YAML file in `sensors/lidar/`. Every section is optional except `pattern`;
unknown keys are errors, and an error names the file, the key path and what was expected.
Units are in the key names: *_deg degrees, *_m metres, *_us microseconds, *_hz hertz.
Frames: the sensor frame is x forward, y left, z up; azimuth is measured counter-clockwise from +x
(towards +y), elevation up from the xy-plane.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Literal, Union

import numpy as np
import yaml
from pydantic import Field, field_validator, model_validator

from ..atomic import atomic_path
from ..config import ConfigError, Mount, StrictModel, load_yaml, normalize_name, validate_model
from ..labels import LABEL_IDS
from ..memory import check_fits
from ..resources import sensors_dir


def _finite(v):
    arr = np.asarray(v, dtype=np.float64)
    if not np.all(np.isfinite(arr)):
        raise ValueError("values must be finite numbers")
    return v


class Channels(StrictModel):
    """Per-channel tables of a spinning sensor, one entry per laser, in the vendor's channel order.

    origin_vertical_m / origin_horizontal_m: beam-origin offsets as in Velodyne calibrations
    (`vert_offset_correction`, `horiz_offset_correction`): the beam starts at
    ``h * (-sin az, cos az, 0) + v * (-sin el cos az, -sin el sin az, cos el)`` from the sensor
    origin, i.e. perpendicular to the beam, rotating with the head.
    """

    elevation_deg: list[float] = Field(min_length=1)
    azimuth_offset_deg: list[float] | None = None
    fire_time_us: list[float] | None = None
    origin_vertical_m: list[float] | None = None
    origin_horizontal_m: list[float] | None = None

    _check = field_validator("*")(classmethod(lambda cls, v: v if v is None else _finite(v)))

    @field_validator("elevation_deg")
    @classmethod
    def _elev_range(cls, v):
        if any(abs(x) > 90 for x in v):
            raise ValueError("elevation angles must lie in [-90, 90] degrees")
        return v

    @model_validator(mode="after")
    def _same_length(self):
        n = len(self.elevation_deg)
        for name in ("azimuth_offset_deg", "fire_time_us", "origin_vertical_m", "origin_horizontal_m"):
            v = getattr(self, name)
            if v is not None and len(v) != n:
                raise ValueError(f"{name} has {len(v)} entries but elevation_deg has {n}")
        return self

    @property
    def count(self) -> int:
        return len(self.elevation_deg)

    def table(self, name: str) -> np.ndarray:
        """(C,) float64 array of a per-channel table, zeros where absent."""
        v = getattr(self, name)
        return np.zeros(self.count) if v is None else np.asarray(v, dtype=np.float64)


class SpinningPattern(StrictModel):
    """A rotating multi-beam head: column j fires at ``j / (columns * rotation_hz)`` seconds after
    the sweep start, channel c a further ``fire_time_us[c]`` (relative to the column's encoder
    instant; may be negative, as in Hesai's tables). The beam azimuth is the head angle at that
    instant plus ``azimuth_offset_deg[c]``; the head angle is ``start_azimuth_deg`` at the sweep
    start and turns at ``rotation_hz``, clockwise seen from above for ``cw``."""

    type: Literal["spinning"] = "spinning"
    columns: int = Field(gt=0, le=100_000)
    rotation_hz: float = Field(gt=0, le=100)
    direction: Literal["cw", "ccw"] = "cw"
    start_azimuth_deg: float = Field(default=0.0, ge=-360, le=360)
    channels: Channels

    @property
    def period_s(self) -> float:
        return 1.0 / self.rotation_hz


class EmitterPattern(StrictModel):
    """An explicit emitter table (solid-state / non-repetitive sensors, or replay of a recorded
    sweep's ray directions). Either `file` (.csv with a header naming azimuth_deg, elevation_deg,
    time_s and optionally channel; or .npy with those columns in that order) or inline lists."""

    type: Literal["emitter"] = "emitter"
    file: str | None = None
    azimuth_deg: list[float] | None = None
    elevation_deg: list[float] | None = None
    time_s: list[float] | None = None
    channel: list[int] | None = None
    period_s: float = Field(default=0.1, gt=0)

    @field_validator("azimuth_deg", "elevation_deg", "time_s")
    @classmethod
    def _rays(cls, v, info):
        # Checked here, where the file and key are known, not deep inside the tracer.
        if v is None:
            return v
        if not v:
            raise ValueError("an emitter table needs at least one ray")
        _finite(v)
        if info.field_name == "elevation_deg" and not all(-90.0 <= e <= 90.0 for e in v):
            raise ValueError("elevation angles must lie in [-90, 90] degrees")
        return v

    @model_validator(mode="after")
    def _source(self):
        inline = [self.azimuth_deg, self.elevation_deg]
        if self.file is None and any(v is None for v in inline):
            raise ValueError("give either 'file' or both 'azimuth_deg' and 'elevation_deg'")
        if self.file is None:
            n = len(self.azimuth_deg)
            for name in ("elevation_deg", "time_s", "channel"):
                v = getattr(self, name)
                if v is not None and len(v) != n:
                    raise ValueError(f"{name} has {len(v)} entries but azimuth_deg has {n}")
        return self


Pattern = Annotated[Union[SpinningPattern, EmitterPattern], Field(discriminator="type")]


class RangeLimits(StrictModel):
    min_m: float = Field(default=0.5, ge=0)
    max_m: float = Field(default=120.0, gt=0, le=10_000)

    @model_validator(mode="after")
    def _order(self):
        if self.max_m <= self.min_m:
            raise ValueError(f"max_m ({self.max_m}) must exceed min_m ({self.min_m})")
        return self


class Noise(StrictModel):
    """Range noise: Gaussian with sigma = range_sigma_m + range_sigma_rel * range, then rounding
    to a multiple of quantization_m (0: none)."""

    range_sigma_m: float = Field(default=0.0, ge=0, le=10)
    range_sigma_rel: float = Field(default=0.0, ge=0, le=1)
    quantization_m: float = Field(default=0.0, ge=0, le=10)


class Drop(StrictModel):
    """Which returns are lost. random_rate: independent loss probability; max_incidence_deg:
    returns at a larger angle between beam and surface normal are lost (90 = never);
    min_intensity: returns weaker than this (model units, before output_scale) are lost;
    reflectivity_range: if set, a surface of effective reflectivity rho (reflectivity x cos
    incidence) is detected only up to ``max_m * sqrt(rho / reflectivity_range)`` (the lidar
    equation: received power ~ rho / r^2), i.e. max_m is the range at that reflectivity.
    model: a fitted drop model file (`lidar/drop.py`; relative to the sensor YAML): each echo is
    then also dropped with its modelled probability, drawn from the sweep's seeded generator."""

    random_rate: float = Field(default=0.0, ge=0, le=1)
    max_incidence_deg: float = Field(default=90.0, gt=0, le=90)
    min_intensity: float = Field(default=0.0, ge=0)
    reflectivity_range: float | None = Field(default=None, gt=0, le=1)
    model: str | None = None


class VelodyneIntensity(StrictModel):
    """The ROS velodyne driver's per-laser intensity correction (velodyne_pointcloud rawdata.cc;
    HDL-64E S2/S3 calibration files carry it), in the sensor's 0-255 byte scale:
    ``reported = clamp(raw + focal_slope * |focal_offset - 256 (1 - d / 65535)^2|, min_intensity,
    max_intensity)`` with ``focal_offset = 256 (1 - focal_distance / 13100)^2`` and d the range in
    units of `distance_resolution_m`. The file's numbers are used as the driver uses them. Lists
    per channel, in the pattern's channel order."""

    focal_distance: list[float]
    focal_slope: list[float]
    min_intensity: list[float] | None = None
    max_intensity: list[float] | None = None
    distance_resolution_m: float = Field(default=0.002, gt=0)

    _check = field_validator("focal_distance", "focal_slope", "min_intensity", "max_intensity")(
        classmethod(lambda cls, v: v if v is None else _finite(v)))

    @model_validator(mode="after")
    def _same_length(self):
        n = len(self.focal_distance)
        for name in ("focal_slope", "min_intensity", "max_intensity"):
            v = getattr(self, name)
            if v is not None and len(v) != n:
                raise ValueError(f"{name} has {len(v)} entries but focal_distance has {n}")
        return self


class IntensityResponse(StrictModel):
    """How the sensor reports a surface of *measured* reflectance rho (a VoxSplat's `reflectance`
    channel: Lambertian-equivalent, 1 = a white diffuse target), on the common 0-1 scale (a
    fraction of the sensor's full-scale reading; `output_scale` then gives the sensor's units):

        I = clip(gain * channel_gain[c] * rho * cos(incidence) ** incidence_exponent
                 * min(1, (reference_range_m / r) ** falloff_exponent), 0, 1)

    then, with `velodyne`, the driver's per-laser correction on the byte scale (I * 255). The
    fall-off terms are the section's. The build inverts the same function to turn real returns
    into reflectance (`lidar.response`). The defaults (gain 1, cosine) give the class formula's
    scale. Each preset's `notes` say where its numbers come from."""

    gain: float = Field(default=1.0, gt=0, le=100)
    incidence_exponent: float = Field(default=1.0, ge=0, le=4)
    channel_gain: list[float] | None = None
    velodyne: VelodyneIntensity | None = None

    @field_validator("channel_gain")
    @classmethod
    def _positive(cls, v):
        if v is not None and not all(np.isfinite(g) and g > 0 for g in v):
            raise ValueError("channel gains must be positive finite numbers")
        return v


class Intensity(StrictModel):
    """intensity = reflectivity * cos(incidence) * min(1, (reference_range_m / r) ** falloff_exponent)
    * output_scale. reflectivity from the semantic class (labels.py, overridable per class name),
    from the surface colour's luminance, or a constant. falloff_exponent 0 gives the calibrated
    reflectivity that Velodyne/Ouster drivers report; 2 the raw inverse-square power.
    Where the scene carries measured reflectance (the VoxSplat `reflectance` channel) `response`
    is used instead: the sensor's own scale (see `IntensityResponse`)."""

    source: Literal["class", "color", "constant"] = "class"
    constant: float = Field(default=0.3, ge=0, le=1)
    class_reflectivity: dict[str, float] = Field(default_factory=dict)
    falloff_exponent: float = Field(default=0.0, ge=0, le=4)
    reference_range_m: float = Field(default=10.0, gt=0)
    output_scale: float = Field(default=1.0, gt=0)
    response: IntensityResponse = IntensityResponse()

    @field_validator("class_reflectivity")
    @classmethod
    def _known_classes(cls, v):
        for name, rho in v.items():
            if name not in LABEL_IDS:
                raise ValueError(f"unknown class {name!r}; known: {', '.join(LABEL_IDS)}")
            if not 0 <= rho <= 1:
                raise ValueError(f"reflectivity of {name!r} must be in [0, 1], got {rho}")
        return v


class Beam(StrictModel):
    """Beam divergence by sub-ray supersampling and how echoes become returns.

    divergence_mrad: full-angle divergence; sub-rays sample the footprint (a disc of that angle),
    weighted by a Gaussian profile with the 1/e^2 radius at the edge. samples = 1 traces the
    centre ray only. Sub-ray hits whose ranges lie within echo_separation_m of each other form
    one echo (range = weighted mean, strength = summed weight x intensity).
    return_mode: first (= nearest), strongest, last, mean (one return at the weighted mean range
    of all sub-ray hits: the mixed-pixel effect), or dual (strongest and last; the second-strongest
    when they coincide).
    """

    divergence_mrad: float = Field(default=0.0, ge=0, le=100)
    samples: int = Field(default=1, ge=1, le=64)
    echo_separation_m: float = Field(default=0.5, gt=0)
    return_mode: Literal["first", "nearest", "strongest", "last", "mean", "dual"] = "strongest"


class EgoBody(StrictModel):
    """An axis-aligned box in the ego frame that blocks rays (the car's own body and roof).
    returns: report the box surface as a return (label undefined) instead of dropping the ray."""

    min: tuple[float, float, float]
    max: tuple[float, float, float]
    returns: bool = False

    @model_validator(mode="after")
    def _order(self):
        if any(a >= b for a, b in zip(self.min, self.max)):
            raise ValueError(f"each min must be below max, got min={self.min} max={self.max}")
        return self


class Motion(StrictModel):
    """Output frame of a moving sweep: 'raw' gives each point in the sensor frame at its own fire
    time (what a real sensor reports, skewed by motion); 'compensated' gives every point in the
    sensor frame at the sweep's reference instant (`reference`: sweep start or end)."""

    output: Literal["raw", "compensated"] = "raw"
    reference: Literal["start", "end"] = "start"


class LidarConfig(StrictModel):
    """A complete LiDAR description. `source` says where the numbers come from."""

    name: str
    id: str | None = None
    source: str = ""
    notes: str = ""
    pattern: Pattern
    range: RangeLimits = RangeLimits()
    noise: Noise = Noise()
    drop: Drop = Drop()
    intensity: Intensity = Intensity()
    beam: Beam = Beam()
    mount: Mount = Mount()
    ego_body: EgoBody | None = None
    motion: Motion = Motion()

    @property
    def channels(self) -> int:
        p = self.pattern
        if isinstance(p, SpinningPattern):
            return p.channels.count
        return len(set(p.channel)) if p.channel else 1

    @model_validator(mode="after")
    def _per_channel_response(self):
        r, p = self.intensity.response, self.pattern
        if isinstance(p, SpinningPattern):
            n = p.channels.count
            tables = {"intensity.response.channel_gain": r.channel_gain,
                      "intensity.response.velodyne": None if r.velodyne is None else r.velodyne.focal_distance}
            for name, v in tables.items():
                if v is not None and len(v) != n:
                    raise ValueError(f"{name} has {len(v)} entries but the pattern has {n} channels")
        return self

    @model_validator(mode="after")
    def _rays_fit_in_memory(self):
        p = self.pattern
        if isinstance(p, SpinningPattern):
            rays, what = p.columns * p.channels.count, f"pattern.columns {p.columns} x {p.channels.count} channels"
        elif p.azimuth_deg is not None:
            rays, what = len(p.azimuth_deg), f"{len(p.azimuth_deg)} emitter rays"
        else:
            return self  # a table file: checked when it is read (`Lidar`)
        check_rays_per_sweep(rays, self.beam.samples, what)
        return self


# A sweep's rays, sub-rays included, are traced and held in memory at once (BYTES_PER_TRACED_RAY
# each and more); past this many a sensor file is refused instead of exhausting the machine, and
# below it, where the machine has less memory available than the sweep needs (BYTES_PER_TRACED_RAY).
MAX_RAYS_PER_SWEEP = 1 << 25  # 33.5 M
BYTES_PER_TRACED_RAY = 64


def check_rays_per_sweep(rays: int, samples: int, what: str) -> None:
    """Raise ValueError when rays x beam.samples sub-rays exceed MAX_RAYS_PER_SWEEP or the memory
    the machine has available (`memory.check_fits`)."""
    if rays * samples > MAX_RAYS_PER_SWEEP:
        raise ValueError(f"{what} x beam.samples {samples} = {rays * samples:,} traced rays per sweep; at most "
                         f"{MAX_RAYS_PER_SWEEP:,} fit in memory at once (fewer columns or sub-rays)")
    check_fits(rays * samples * BYTES_PER_TRACED_RAY,
               f"{what} x beam.samples {samples} = {rays * samples:,} traced rays per sweep")


# --- loading ---------------------------------------------------------------------------------


def config_from_dict(data: dict, source: str = "<dict>") -> LidarConfig:
    """Validate a mapping; raises ConfigError naming `source` and the key path."""
    return validate_model(LidarConfig, data, source, "LiDAR settings")


def load_config_file(path: str | Path) -> LidarConfig:
    path = Path(path)
    cfg = config_from_dict(load_yaml(path), str(path))
    p = cfg.pattern
    if isinstance(p, EmitterPattern) and p.file and not Path(p.file).is_absolute():
        p.file = str((path.parent / p.file).resolve())  # relative to the YAML file
    if cfg.drop.model and not Path(cfg.drop.model).is_absolute():
        cfg.drop.model = str((path.parent / cfg.drop.model).resolve())
    return cfg


def preset_paths() -> dict[str, Path]:
    """Normalised id -> YAML path of every shipped preset: `sensors/lidar/<id>.yaml`. Files named
    `<id>.<kind>.yaml` beside a preset are that sensor's profiles (e.g. `hdl32e.drop.yaml`, a
    fitted drop model), not presets."""
    return {normalize_name(p.stem): p for p in sorted((sensors_dir() / "lidar").glob("*.yaml")) if "." not in p.stem}


def list_presets() -> list[LidarConfig]:
    return [load_config_file(p) for p in preset_paths().values()]


def load_lidar_config(name_or_path: str | Path) -> LidarConfig:
    """A preset by name (case and punctuation ignored: 'VLP-16' == 'vlp16') or a YAML path."""
    s = str(name_or_path)
    p = Path(s)
    if p.suffix.lower() in (".yaml", ".yml") or p.is_file():
        return load_config_file(p)
    presets = preset_paths()
    key = normalize_name(s)
    if key in presets:
        return load_config_file(presets[key])
    # Also accept the display name stored in the file (e.g. 'Pandar128E3X' for pandar128).
    for path in presets.values():
        data = load_yaml(path)
        if isinstance(data, dict) and normalize_name(str(data.get("name", ""))) == key:
            return load_config_file(path)
    raise ConfigError(f"unknown sensor {s!r}: not a file and not a preset; presets: "
                      f"{', '.join(sorted(p.stem for p in presets.values()))}")


def dump_config(cfg: LidarConfig, path: str | Path | None = None) -> str:
    """YAML text of a config (written to `path` if given); per-channel lists stay on one line."""
    data = cfg.model_dump(mode="json", exclude_none=True)

    class _Dumper(yaml.SafeDumper):
        pass

    def _repr_list(dumper, value):
        flow = all(isinstance(x, (int, float)) for x in value)
        return dumper.represent_sequence("tag:yaml.org,2002:seq", value, flow_style=flow)

    _Dumper.add_representer(list, _repr_list)
    _Dumper.add_representer(tuple, _repr_list)
    text = yaml.dump(data, Dumper=_Dumper, sort_keys=False, width=100)
    if path is not None:
        with atomic_path(path) as tmp:
            Path(tmp).write_text(text, encoding="utf-8")
    return text
