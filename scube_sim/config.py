"""The configuration room: one strict pydantic base, YAML loading, validation-error messages.

Every validated file (LiDAR presets, camera rigs, scenarios, dataset folders, the converter's
configs) uses these, so an unknown key or a bad value reads the same everywhere:
`sensor.yaml: pattern.columns: Input should be a valid integer`.
"""

from __future__ import annotations

import copy
import json
import re
from dataclasses import dataclass
from pathlib import Path
from types import UnionType
from typing import Annotated, Union, get_args, get_origin

import numpy as np
import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from .errors import InputError
from .transforms import pose_from_xyz_rpy


class ConfigError(InputError):
    """A sensor, rig or scenario file that cannot be used; the message names the file and key."""


class StrictModel(BaseModel):
    """Unknown keys are errors, assignments are validated, and every float (nested lists and
    tuples too) must be finite: NaN and infinity are refused where they enter, naming the key."""

    model_config = ConfigDict(extra="forbid", validate_assignment=True, allow_inf_nan=False)


@dataclass(frozen=True)
class Range:
    """A number's valid range, kept in one place per concept and used both by the command line's
    options (`cli._common.bounded`) and by the schemas (`Range.field`: pydantic's ge/gt/le/lt).
    Floats must be finite; `integer` numbers must be integers (not bools)."""

    ge: float | None = None
    gt: float | None = None
    le: float | None = None
    lt: float | None = None
    integer: bool = False
    unit: str = ""

    def describe(self) -> str:
        """'an integer from 1 to 1000', 'a finite number > 0 and <= 100 (metres)', ..."""
        def num(x) -> str:
            return str(int(x)) if float(x).is_integer() and abs(x) < 1e15 else f"{x:g}"

        lo = f">= {num(self.ge)}" if self.ge is not None else f"> {num(self.gt)}" if self.gt is not None else ""
        hi = f"<= {num(self.le)}" if self.le is not None else f"< {num(self.lt)}" if self.lt is not None else ""
        kind = "an integer" if self.integer else "a finite number"
        if self.integer and self.ge is not None and self.le is not None:
            text = f"{kind} from {num(self.ge)} to {num(self.le)}"
        else:
            text = f"{kind} {' and '.join(b for b in (lo, hi) if b)}".rstrip()
        return text + (f" ({self.unit})" if self.unit else "")

    def contains(self, value) -> bool:
        if isinstance(value, bool):
            return False
        if self.integer:
            if not isinstance(value, (int, np.integer)):
                return False
        elif not isinstance(value, (int, float, np.integer, np.floating)) or not np.isfinite(value):
            return False
        return ((self.ge is None or value >= self.ge) and (self.gt is None or value > self.gt)
                and (self.le is None or value <= self.le) and (self.lt is None or value < self.lt))

    def check(self, value, name: str, error: type[Exception] = InputError):
        """`value` (None passes) or `error`: '--steps: expected an integer from 1 to 1000, got 0'."""
        if value is not None and not self.contains(value):
            raise error(f"{name}: expected {self.describe()}, got {value!r}")
        return value

    def field(self, default=..., **kw):
        """A pydantic Field with these bounds."""
        bounds = {k: getattr(self, k) for k in ("ge", "gt", "le", "lt") if getattr(self, k) is not None}
        return Field(default, **bounds, **kw)

    def annotated(self):
        """The type `int` or `float` with these bounds (for list items: `list[SEED.annotated()]`)."""
        return Annotated[int if self.integer else float, self.field()]


# Numbers that enter in several places (options, settings, profiles): their ranges, once.
SEED = Range(ge=0, le=2**32 - 1, integer=True)  # numpy's and torch's seeds alike
SAMPLE_INDEX = Range(ge=0, integer=True)
DDIM_STEPS = Range(ge=1, le=1000, integer=True)  # the geometry stage's sampler (its training schedule: 1000 steps)
FIT_STEPS = Range(ge=0, le=10_000, integer=True)  # the test-time fit: each step renders; the cap keeps a run to hours
CONTEXT_INSTANTS = Range(ge=0, le=100, integer=True)
CONFIDENCE_SAMPLES = Range(ge=0, le=64, integer=True)  # K (0: off; 1 is refused where it is read)
MAX_RANGE_M = Range(gt=0, le=10_000, unit="metres")  # as a LiDAR's range.max_m
THREADS = Range(ge=1, le=1024, integer=True)
COMMAND_THREADS = Range(ge=0, le=1024, integer=True)  # a command's --threads (0: `cpus.resolve_threads`)
WORKERS = Range(ge=1, le=1024, integer=True)
VOXEL_SIZE_M = Range(ge=0.001, le=100, unit="metres")  # a VoxSplat fitted to points or Gaussians
SCENE_VOXEL_M = Range(gt=0.01, le=5.0, unit="metres")  # a VoxSplat fitted to a mesh (`SceneSpec`, the demo)
SCALE_FACTOR = Range(gt=0, le=1)  # of a camera's resolution
FINE_VOXEL_M = Range(ge=0.05, le=1.6, unit="metres")  # the worlds' ground truth (`DatasetConfig`)
COARSE_FACTOR = Range(ge=1, le=16, integer=True)


class Mount(StrictModel):
    """A sensor's pose in the ego (vehicle) frame: metres and degrees (roll, pitch, yaw)."""

    xyz: tuple[float, float, float] = (0.0, 0.0, 0.0)
    rpy_deg: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def matrix(self) -> np.ndarray:
        """(4, 4) float64 sensor-to-ego."""
        return pose_from_xyz_rpy(self.xyz, self.rpy_deg)


def _format_loc(loc) -> str:
    out = ""
    for part in loc:
        if isinstance(part, int):
            out += f"[{part}]"
        elif part in ("spinning", "emitter") and out.endswith("pattern"):
            continue  # the discriminator tag pydantic inserts
        else:
            out += ("." if out else "") + str(part)
    return out or "(top level)"


BOUND_ERRORS = {"greater_than", "greater_than_equal", "less_than", "less_than_equal", "finite_number"}


def _unwrap(tp, metadata: list):
    """Strip Annotated (collecting its constraints) and Optional from a type."""
    while True:
        if get_origin(tp) is Annotated:
            args = get_args(tp)
            tp = args[0]
            for m in args[1:]:
                metadata.extend(getattr(m, "metadata", None) or [m])
        elif get_origin(tp) in (Union, UnionType) and sum(a is not type(None) for a in get_args(tp)) == 1:
            tp = next(a for a in get_args(tp) if a is not type(None))
        else:
            return tp, metadata


def field_range(model_cls, loc) -> Range | None:
    """The whole valid range of the number at key path `loc` of `model_cls` (its Field's ge/gt/le/lt),
    or None where the path leads to no number."""
    tp, metadata = model_cls, []
    for part in loc:
        tp, metadata = _unwrap(tp, [])
        if isinstance(part, str):
            if get_origin(tp) in (Union, UnionType):  # a discriminated union: the tag names the member
                members = [a for a in get_args(tp) if isinstance(a, type) and issubclass(a, BaseModel)
                           and getattr(a.model_fields.get("type"), "default", None) == part]
                if len(members) != 1:
                    return None
                tp = members[0]
                continue
            if isinstance(tp, type) and issubclass(tp, BaseModel):
                if part not in tp.model_fields:
                    return None
                info = tp.model_fields[part]
                tp, metadata = info.annotation, list(info.metadata)
            elif get_origin(tp) is dict:
                tp, metadata = get_args(tp)[1], []
            else:
                return None
        else:
            args = get_args(tp)
            if get_origin(tp) is tuple and args and args[-1] is not Ellipsis:
                tp = args[part] if part < len(args) else None
            elif get_origin(tp) in (list, tuple) and args:
                tp = args[0]
            else:
                return None
            metadata = []
    tp, metadata = _unwrap(tp, metadata)
    if tp not in (int, float):
        return None
    bounds = {k: getattr(m, k) for m in metadata for k in ("ge", "gt", "le", "lt") if getattr(m, k, None) is not None}
    return Range(**bounds, integer=tp is int)


def format_validation_error(exc: ValidationError, source: str, model=None) -> str:
    """One line per error: `SOURCE: key.path: message`. With `model` (the class validated), a
    number out of its range (NaN and infinity too) names the whole range:
    `s.yaml: pattern.columns: expected an integer from 1 to 100000, got 0`."""
    lines = []
    for err in exc.errors():
        msg = err["msg"]
        if err["type"] == "extra_forbidden":
            msg = "unknown key"
        elif err["type"] == "value_error":  # our validators' own messages, without pydantic's prefix
            msg = msg.removeprefix("Value error, ")
        elif err["type"] in BOUND_ERRORS and model is not None:
            try:
                rng = field_range(model, err["loc"])
            except Exception:  # noqa: BLE001 - a type this walk does not know: pydantic's own message
                rng = None
            if rng is not None:
                msg = f"expected {rng.describe()}, got {err['input']!r}"
        lines.append(f"{source}: {_format_loc(err['loc'])}: {msg}")
    return "\n".join(lines)


def validate_model(model_cls, data, source: str, what: str = "settings", error: type[Exception] = ConfigError):
    """Validate a mapping into a pydantic model; `error` (ConfigError) names `source` and each key path."""
    if not isinstance(data, dict):
        raise error(f"{source}: expected a mapping of {what}, got {type(data).__name__}")
    try:
        return model_cls.model_validate(data)
    except ValidationError as exc:
        raise error(format_validation_error(exc, source, model_cls)) from None


class DuplicateKeyError(yaml.YAMLError):
    """A YAML mapping that holds one key twice (PyYAML would keep the last value silently)."""

    def __init__(self, key_path: str, line: int, first_line: int):
        super().__init__(key_path, line, first_line)
        self.key_path, self.line, self.first_line = key_path, line, first_line

    def __str__(self) -> str:
        return f"line {self.line}: {self.key_path}: duplicate key (first at line {self.first_line})"


def _key_path(parent: str, key) -> str:
    return f"{parent}.{key}" if parent else str(key)


def _duplicate_keys(loader: yaml.SafeLoader, root: yaml.Node) -> DuplicateKeyError | None:
    """The first (by line) key that a mapping under `root` holds twice, or None. Keys compare as
    their values (`1` and `0x1` are one key, `1` and `'1'` two); a merge (`<<: *base`) may be
    overridden by the mapping's own keys, as YAML defines."""
    found: list[DuplicateKeyError] = []
    seen: set[int] = set()
    stack = [(root, "")]
    while stack:
        node, path = stack.pop()
        if id(node) in seen:  # an alias: checked where its anchor is
            continue
        seen.add(id(node))
        if isinstance(node, yaml.MappingNode):
            first: dict = {}
            for k, v in node.value:
                if k.tag == "tag:yaml.org,2002:merge":
                    continue
                key = k.value
                if isinstance(k, yaml.ScalarNode):
                    try:
                        key = loader.construct_object(k)
                        hash(key)
                    except Exception:  # construct_mapping reports a bad key itself
                        key = (k.tag, k.value)
                    if key in first:
                        found.append(DuplicateKeyError(_key_path(path, k.value), k.start_mark.line + 1,
                                                       first[key].start_mark.line + 1))
                    else:
                        first[key] = k
                stack.append((v, _key_path(path, k.value if isinstance(k, yaml.ScalarNode) else "?")))
        elif isinstance(node, yaml.SequenceNode):
            stack.extend((v, f"{path}[{i}]") for i, v in enumerate(node.value))
    return min(found, key=lambda e: e.line) if found else None


class UniqueKeyLoader(yaml.SafeLoader):
    """`yaml.SafeLoader` that refuses a mapping holding one key twice (`DuplicateKeyError`, with
    the line and key path): every YAML the project reads goes through it (`load_yaml`,
    `yaml_loads`)."""

    def construct_document(self, node):
        dup = _duplicate_keys(self, node)
        if dup is not None:
            raise dup
        return super().construct_document(node)


def yaml_loads(text: str):
    """`yaml.safe_load` through `UniqueKeyLoader` (a duplicate key raises `DuplicateKeyError`)."""
    return yaml.load(text, Loader=UniqueKeyLoader)


class _JsonPairs(list):
    """A JSON object as its (key, value) pairs, in file order."""


def _json_duplicate(node, path: str = "") -> str | None:
    """The key path of the first key that an object under `node` (of `_JsonPairs`) holds twice."""
    if isinstance(node, _JsonPairs):
        keys: set = set()
        for k, v in node:
            if k in keys:
                return _key_path(path, k)
            keys.add(k)
        for k, v in node:
            hit = _json_duplicate(v, _key_path(path, k))
            if hit:
                return hit
    elif isinstance(node, list):
        for i, v in enumerate(node):
            hit = _json_duplicate(v, f"{path}[{i}]")
            if hit:
                return hit
    return None


class _JsonDuplicate(ValueError):
    pass


def _unique_object(pairs: list) -> dict:
    out = dict(pairs)
    if len(out) != len(pairs):
        raise _JsonDuplicate()
    return out


def json_loads(text: str | bytes, source: str | Path, error: type[Exception] = ConfigError):
    """`json.loads` for a file the user gives: an object holding one key twice (which `json` would
    resolve silently, last value wins) raises `error` naming `source` and the key path
    (`meta.json: calib.FRONT: duplicate key`); text that is not JSON raises `json.JSONDecodeError`
    as `json.loads` does (each caller words that)."""
    try:
        return json.loads(text, object_pairs_hook=_unique_object)
    except _JsonDuplicate:
        where = _json_duplicate(json.loads(text, object_pairs_hook=_JsonPairs)) or "(top level)"
        raise error(f"{source}: {where}: duplicate key") from None


def repeated(items, key=None) -> tuple[int, int] | None:
    """(first index, later index) of the first item that `items` holds twice (compared as
    `key(item)` when given), or None: a list that names one thing twice is an error wherever a name
    picks one entry (sensors, cameras, outputs, samples)."""
    first: dict = {}
    for i, item in enumerate(items):
        k = item if key is None else key(item)
        if k in first:
            return first[k], i
        first[k] = i
    return None


def listed_twice(items, key=None) -> str | None:
    """"'x' is listed twice (at [0] and [2])" for the first item `items` holds twice, or None."""
    hit = repeated(items, key)
    if hit is None:
        return None
    i, j = hit
    return f"{items[j]!r} is listed twice (at [{i}] and [{j}])"


def unique_names(items, key=None):
    """A pydantic field validator: `items`, or a ValueError naming the item listed twice and where
    (`s.yaml: outputs.files: 'pcd' is listed twice (at [0] and [1])`)."""
    if items is not None:
        msg = listed_twice(items, key)
        if msg:
            raise ValueError(msg)
    return items


def laid_over(base: dict, over: dict) -> dict:
    """`over`'s keys over `base`'s, a new mapping: a mapping merged key by key, any other value
    replaced (a profile's keys over its base's, a scenario's overrides over a preset)."""
    out = copy.deepcopy(base)
    for k, v in over.items():
        out[k] = laid_over(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def load_yaml(path: str | Path, error: type[Exception] = ConfigError) -> object:
    """The parsed YAML of `path`; `error` (ConfigError) names the file, and line and column of a syntax error."""
    path = Path(path)
    if path.is_dir():
        raise error(f"{path}: is a folder; expected a YAML file")
    if not path.is_file():
        raise error(f"{path}: no such file")
    try:
        with open(path, encoding="utf-8") as fh:
            return yaml.load(fh, Loader=UniqueKeyLoader)
    except UnicodeDecodeError as exc:
        raise error(f"{path}: not UTF-8 text (byte 0x{exc.object[exc.start]:02x} at offset {exc.start}); "
                    f"YAML files must be UTF-8") from None
    except DuplicateKeyError as exc:
        raise error(f"{path}: {exc}") from None
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" (line {mark.line + 1}, column {mark.column + 1})" if mark else ""
        raise error(f"{path}: not valid YAML{where}: {getattr(exc, 'problem', exc)}") from None


def parse_key_values(items: list[str], flag: str) -> dict:
    """`KEY=VALUE` items (VALUE is YAML) -> {KEY: value}, later items over earlier ones; a ConfigError
    names `flag` and the item: `--set 'x': expected KEY=VALUE`; a mapping in VALUE that holds a key
    twice is refused (`--set 'x={a: 1, a: 2}': x.a: duplicate key in VALUE`)."""
    out = {}
    for item in items:
        key, eq, value = item.partition("=")
        if not eq or not key.strip():
            raise ConfigError(f"{flag} {item!r}: expected KEY=VALUE")
        try:
            out[key.strip()] = yaml_loads(value)
        except DuplicateKeyError as exc:
            raise ConfigError(f"{flag} {item!r}: {key.strip()}.{exc.key_path}: duplicate key in VALUE") from None
        except yaml.YAMLError as exc:
            raise ConfigError(f"{flag} {item!r}: VALUE is not YAML ({exc})") from None
    return out


def normalize_name(name: str) -> str:
    """Lower case, letters and digits only: 'VLP-16', 'vlp_16' and 'vlp16' are one name."""
    return re.sub(r"[^a-z0-9]", "", name.lower())
