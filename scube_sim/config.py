"""The configuration room: one strict pydantic base, YAML loading, validation-error messages.

Every validated file (LiDAR presets, camera rigs, scenarios, dataset folders, the converter's
configs) uses these, so an unknown key or a bad value reads the same everywhere:
`sensor.yaml: pattern.columns: Input should be a valid integer`.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import yaml
from pydantic import BaseModel, ConfigDict, ValidationError

from .errors import InputError
from .transforms import pose_from_xyz_rpy


class ConfigError(InputError):
    """A sensor, rig or scenario file that cannot be used; the message names the file and key."""


class StrictModel(BaseModel):
    """Unknown keys are errors and assignments are validated."""

    model_config = ConfigDict(extra="forbid", validate_assignment=True)


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


def format_validation_error(exc: ValidationError, source: str) -> str:
    """One line per error: `SOURCE: key.path: message`."""
    lines = []
    for err in exc.errors():
        msg = err["msg"]
        if err["type"] == "extra_forbidden":
            msg = "unknown key"
        elif err["type"] == "value_error":  # our validators' own messages, without pydantic's prefix
            msg = msg.removeprefix("Value error, ")
        lines.append(f"{source}: {_format_loc(err['loc'])}: {msg}")
    return "\n".join(lines)


def validate_model(model_cls, data, source: str, what: str = "settings", error: type[Exception] = ConfigError):
    """Validate a mapping into a pydantic model; `error` (ConfigError) names `source` and each key path."""
    if not isinstance(data, dict):
        raise error(f"{source}: expected a mapping of {what}, got {type(data).__name__}")
    try:
        return model_cls.model_validate(data)
    except ValidationError as exc:
        raise error(format_validation_error(exc, source)) from None


def load_yaml(path: str | Path, error: type[Exception] = ConfigError) -> object:
    """The parsed YAML of `path`; `error` (ConfigError) names the file, and line and column of a syntax error."""
    path = Path(path)
    if path.is_dir():
        raise error(f"{path}: is a folder; expected a YAML file")
    if not path.is_file():
        raise error(f"{path}: no such file")
    try:
        with open(path, encoding="utf-8") as fh:
            return yaml.safe_load(fh)
    except UnicodeDecodeError as exc:
        raise error(f"{path}: not UTF-8 text (byte 0x{exc.object[exc.start]:02x} at offset {exc.start}); "
                    f"YAML files must be UTF-8") from None
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" (line {mark.line + 1}, column {mark.column + 1})" if mark else ""
        raise error(f"{path}: not valid YAML{where}: {getattr(exc, 'problem', exc)}") from None


def parse_key_values(items: list[str], flag: str) -> dict:
    """`KEY=VALUE` items (VALUE is YAML) -> {KEY: value}, later items over earlier ones; a ConfigError
    names `flag` and the item: `--set 'x': expected KEY=VALUE`."""
    out = {}
    for item in items:
        key, eq, value = item.partition("=")
        if not eq or not key.strip():
            raise ConfigError(f"{flag} {item!r}: expected KEY=VALUE")
        try:
            out[key.strip()] = yaml.safe_load(value)
        except yaml.YAMLError as exc:
            raise ConfigError(f"{flag} {item!r}: VALUE is not YAML ({exc})") from None
    return out


def normalize_name(name: str) -> str:
    """Lower case, letters and digits only: 'VLP-16', 'vlp_16' and 'vlp16' are one name."""
    return re.sub(r"[^a-z0-9]", "", name.lower())
