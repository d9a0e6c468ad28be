"""Converter profiles: a route and its settings (`ConverterProfile`), read from a shipped profile's
name (`profiles/<name>.yaml`) or a user's YAML file. `DEFAULT_PROFILE` is the one `convert`, the
CLI and the demo use unless told. No torch: a profile validates before any network loads.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Literal

import yaml
from pydantic import Field, ValidationError, model_validator

from ..config import CONTEXT_INSTANTS, DDIM_STEPS, FIT_STEPS, StrictModel, format_validation_error, laid_over, load_yaml
from ..errors import InputError
from ..memory import check_fits
from ..reconstruct.config import EvidenceConfig
from .merge import CompletionConfig

PROFILE_DIR = Path(__file__).resolve().parent / "profiles"


# the profile `convert`, the CLI, the demo, batches and scenarios use unless told (docs/profiles.md)
DEFAULT_PROFILE = "evidence-complete"
# the paper's route, whose networks `eval stage` and `eval depth --method mono` default to
PAPER_PROFILE = "cpu"
# the checkpoint-bearing sections of a profile, in the order provenance lists them
CHECKPOINT_KEYS = ("geometry", "fine", "appearance", "completion")


class StageProfile(StrictModel):
    """One stage: its checkpoint (path or shipped name) and the focal length, in pixels, each input
    image is resized to (the training images'); `max_side` caps the resized image's longer side
    (a camera with a very long focal length over a wide image)."""

    checkpoint: str
    focal_px: float = Field(gt=0, le=100_000)
    max_side: int = Field(default=1024, ge=16, le=8192)


class GeometryProfile(StageProfile):
    """sample_steps: DDIM steps (None: the checkpoint's own)."""

    sample_steps: int | None = DDIM_STEPS.field(None)


class FineProfile(StageProfile):
    """The fine geometry level, run on the coarse level's prediction (each coarse voxel
    subdivided and pruned by the fine checkpoint). output_voxel_size: the voxels handed to the
    appearance stage, metres; a multiple of the fine level's that divides the coarse level's
    (the fine voxels grouped into it: a voxel where any child is, its children's most common
    label); None: the fine level's own."""

    output_voxel_size: float | None = Field(default=None, gt=0)


class AppearanceProfile(StageProfile):
    """sky_size: (rows, columns) of the sky panorama channel. gaussians_per_voxel: keep only the
    M most opaque Gaussians of each voxel (`VoxSplat.keep_slots`; None: all the checkpoint's).
    max_scale_voxels: each Gaussian's
    standard deviations are capped at this many voxels (None: as predicted). The camera loss
    tolerates a few wide, faint Gaussians that fill background; a LiDAR tracing at hard opacity
    sees each as a wall k standard deviations out, and one around the sensor hides everything.
    fit_steps: Adam steps of a test-time fit after the network (`appearance.fit_input_views`: the
    Gaussians and the panorama fitted to the input views themselves, each step a render of every
    view; 0: the network's prediction as it is, the paper's method)."""

    sky_size: tuple[Annotated[int, Field(ge=8, le=8192)], Annotated[int, Field(ge=8, le=16384)]] = (128, 256)
    fit_steps: int = FIT_STEPS.field(0)  # a test-time fit on the input views (`appearance.fit_input_views`)
    max_scale_voxels: float | None = Field(default=1.0, gt=0, le=100)
    gaussians_per_voxel: int | None = Field(default=None, ge=1, le=64)  # keep the M most opaque (None: all)

    @model_validator(mode="after")
    def _sky_fits_in_memory(self):
        rows, cols = self.sky_size
        check_fits(rows * cols * SKY_BYTES_PER_PIXEL, f"sky_size [{rows}, {cols}] = {rows * cols:,} panorama pixels "
                   f"(~{SKY_BYTES_PER_PIXEL} bytes each while decoded)")
        return self


# The sky decoder's working memory per panorama pixel: directions (float64), sampled features,
# the decoder's layers and the colours (float32), rounded up.
SKY_BYTES_PER_PIXEL = 384


class ConverterProfile(StrictModel):
    """A route and its settings. route `scube` (the paper's): both stages' checkpoints and
    settings (module docstring); confidence_samples: K, the geometry samples per-voxel confidence
    is counted over when a caller asks for confidence. route `evidence` (`reconstruct.evidence`: stereo
    depth fused into a grid, no learning): its `evidence` settings (default `EvidenceConfig()`),
    no checkpoints; per-voxel confidence is the fused occupancy probability whatever K; with a
    `completion` section, the completion network's checkpoint and merge (`model.completion`) fill
    what no camera saw. context: the instants before and after the sample the route reads when
    the caller names none."""

    name: str
    description: str = ""
    route: Literal["scube", "evidence"] = "scube"
    geometry: GeometryProfile | None = None
    fine: FineProfile | None = None
    appearance: AppearanceProfile | None = None
    evidence: EvidenceConfig | None = None
    completion: CompletionConfig | None = None
    context: int = CONTEXT_INSTANTS.field(0)
    confidence_samples: int = Field(default=4, ge=2, le=64)

    @model_validator(mode="after")
    def _route_keys(self):
        if self.route == "scube":
            missing = [k for k in ("geometry", "appearance") if getattr(self, k) is None]
            if missing or self.evidence is not None or self.completion is not None:
                raise ValueError(f"route scube needs geometry and appearance (missing: {', '.join(missing) or 'none'}) "
                                 f"and takes no evidence or completion key")
        else:
            given = [k for k in ("geometry", "fine", "appearance") if getattr(self, k) is not None]
            if given:
                raise ValueError(f"route evidence uses no checkpoints: remove {', '.join(given)}")
            if self.evidence is None:
                self.evidence = EvidenceConfig()
        return self

    def checkpoints(self) -> dict[str, str]:
        """Every checkpoint the profile names, section -> path or shipped name (`CHECKPOINT_KEYS`):
        what a conversion depends on besides the profile's values."""
        return {k: getattr(self, k).checkpoint for k in CHECKPOINT_KEYS if getattr(self, k) is not None}


def shipped_profiles() -> list[str]:
    return sorted(p.stem for p in PROFILE_DIR.glob("*.yaml"))


def load_profile(profile: str | Path | ConverterProfile = DEFAULT_PROFILE) -> ConverterProfile:
    """A profile: a `ConverterProfile`, a YAML file's path, or a shipped profile's name. A YAML file
    may name a `base:` profile (a shipped name, or a path relative to the file): its keys are read
    first and the file's own laid over them, section by section."""
    if isinstance(profile, ConverterProfile):
        return profile
    path = _profile_path(profile)
    data = _profile_data(path, ())
    data.setdefault("name", path.stem)
    try:
        return ConverterProfile(**data)
    except ValidationError as exc:  # each key at fault: `p.yaml: appearance.sky_size[0]: Input should be ...`
        raise InputError(format_validation_error(exc, str(path), ConverterProfile)) from None


def _profile_path(profile: str | Path, relative_to: Path | None = None) -> Path:
    path = Path(profile)
    if relative_to is not None and not path.is_absolute() and (relative_to / path).is_file():
        return relative_to / path
    if path.is_file():
        return path
    if str(profile) not in shipped_profiles():
        raise InputError(f"profile {str(profile)!r}: no such file, nor a shipped profile "
                         f"(shipped: {', '.join(shipped_profiles())})")
    return PROFILE_DIR / f"{profile}.yaml"


def _profile_data(path: Path, seen: tuple[Path, ...]) -> dict:
    """The keys of the profile file at `path` over those of its `base:` (recursively)."""
    if path.resolve() in seen:
        chain = " -> ".join(str(p) for p in (*seen, path.resolve()))
        raise InputError(f"{path}: base: the profiles base each other in a circle ({chain})")
    try:
        data = load_yaml(path, error=InputError)  # a duplicate key: file, line and key path
    except yaml.YAMLError as exc:
        raise InputError(f"{path}: not YAML ({exc})") from None
    if not isinstance(data, dict):
        raise InputError(f"{path}: expected a mapping of profile keys, got {type(data).__name__}")
    base = data.pop("base", None)
    if base is None:
        return data
    if not isinstance(base, str) or not base:
        raise InputError(f"{path}: base: expected a shipped profile's name or a profile file's path, got {base!r}")
    inherited = _profile_data(_profile_path(base, path.parent), (*seen, path.resolve()))
    inherited.pop("name", None)  # a profile's name and description are its own
    inherited.pop("description", None)
    return laid_over(inherited, data)
