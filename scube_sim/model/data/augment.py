"""Augmentation for the gap between rendered and real photographs, and rig randomisation.

Images are (3, H, W) float32 torch tensors of 8-bit-style sRGB values in [0, 1] (what
`scube_sim.model.data` returns); every function returns a new tensor of that kind, clipped to
[0, 1], and never touches depth, semantics or poses (none of these change the geometry).
Randomness comes only from the explicit `torch.Generator` argument, so a seeded generator gives
bit-identical output.

- `adjust_color` / `color_jitter`: brightness, contrast, saturation (on sRGB values) and hue (a
  rotation about the grey axis);
- `adjust_exposure` / `random_exposure`: a gain in linear light (the sensor's exposure time);
- `gaussian_blur` / `random_blur`: defocus and motion smear, in linear light;
- `sensor_noise`: shot noise (variance proportional to the linear signal) plus read noise;
- `jpeg` / `random_jpeg`: compression artefacts, an encode/decode through PIL;
- `photometric`: all of these with the probabilities and ranges of an `AugmentConfig`;
- `choose_cameras`: which cameras of a rig to keep (`CameraSelection`: all, the front one, or
  randomly dropped ones, at least one).
"""

from __future__ import annotations

import io
import math
from typing import Literal

import numpy as np
import torch
import torch.nn.functional as F
from PIL import Image
from pydantic import Field, model_validator

from ...config import StrictModel
from ...errors import InputError

# Rec. 601 luma weights: the grey an image's saturation and contrast are measured against.
LUMA = (0.299, 0.587, 0.114)
# The front camera of the shipped rigs (waymo-5: FRONT, nuscenes-6: CAM_FRONT).
FRONT_NAMES = ("FRONT", "CAM_FRONT")


def _check_image(img: torch.Tensor, what: str = "image") -> None:
    if not isinstance(img, torch.Tensor) or img.ndim != 3 or img.shape[0] != 3 or not img.is_floating_point():
        shape = tuple(img.shape) if isinstance(img, torch.Tensor) else type(img).__name__
        raise InputError(f"{what}: expected a (3, H, W) float tensor of sRGB values in [0, 1], got {shape}")


def _uniform(gen: torch.Generator, lo: float, hi: float) -> float:
    return lo + (hi - lo) * float(torch.rand((), generator=gen, dtype=torch.float64))


def srgb_to_linear(x: torch.Tensor) -> torch.Tensor:
    """sRGB values in [0, 1] -> linear light in [0, 1] (the IEC 61966-2-1 curve)."""
    x = x.clamp(0.0, 1.0)
    return torch.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4)


def linear_to_srgb(x: torch.Tensor) -> torch.Tensor:
    """Linear light -> sRGB values, clipped to [0, 1]."""
    x = x.clamp(0.0, 1.0)
    return torch.where(x <= 0.0031308, x * 12.92, 1.055 * x ** (1 / 2.4) - 0.055).clamp(0.0, 1.0)


# --- colour -----------------------------------------------------------------------------------


def _grey(img: torch.Tensor) -> torch.Tensor:
    w = torch.tensor(LUMA, dtype=img.dtype).view(3, 1, 1)
    return (img * w).sum(0, keepdim=True)


def _hue_rotation(turns: float) -> torch.Tensor:
    """(3, 3) rotation by `turns` of a full turn about the grey axis (1, 1, 1) / sqrt(3)
    (Rodrigues): greys stay, and 1/3 turn maps red to green to blue."""
    a = 2 * math.pi * turns
    c, s = math.cos(a), math.sin(a)
    k = torch.tensor([[0.0, -1.0, 1.0], [1.0, 0.0, -1.0], [-1.0, 1.0, 0.0]], dtype=torch.float64) / math.sqrt(3)
    return torch.eye(3, dtype=torch.float64) + s * k + (1 - c) * (k @ k)


def adjust_color(img: torch.Tensor, brightness: float = 1.0, contrast: float = 1.0, saturation: float = 1.0,
                 hue: float = 0.0) -> torch.Tensor:
    """Scale the sRGB values by `brightness`, their distance from the image's mean grey by
    `contrast`, from each pixel's grey by `saturation`, and rotate the hue by `hue` turns (in
    that order). Factors of 1 and a hue of 0 leave the image as it is, bit for bit."""
    _check_image(img)
    out = img
    if brightness != 1.0:
        out = out * brightness
    if contrast != 1.0:
        mean = _grey(out).mean()
        out = mean + (out - mean) * contrast
    if saturation != 1.0:
        g = _grey(out)
        out = g + (out - g) * saturation
    if hue != 0.0:
        r = _hue_rotation(hue).to(out.dtype)
        out = torch.einsum("ij,jhw->ihw", r, out)
    return out.clamp(0.0, 1.0) if out is not img else img.clone()


def color_jitter(img: torch.Tensor, gen: torch.Generator, brightness: float = 0.0, contrast: float = 0.0,
                 saturation: float = 0.0, hue: float = 0.0) -> torch.Tensor:
    """`adjust_color` with factors drawn uniformly from [1 - b, 1 + b] (b: brightness, contrast,
    saturation) and a hue shift from [-hue, hue] turns; a range of 0 draws nothing and keeps the
    image as it is."""
    for name, v in (("brightness", brightness), ("contrast", contrast), ("saturation", saturation)):
        if not 0.0 <= v <= 1.0:
            raise InputError(f"color_jitter: {name} must be in [0, 1], got {v}")
    if not 0.0 <= hue <= 0.5:
        raise InputError(f"color_jitter: hue must be in [0, 0.5] turns, got {hue}")
    f = [_uniform(gen, 1 - v, 1 + v) if v > 0 else 1.0 for v in (brightness, contrast, saturation)]
    h = _uniform(gen, -hue, hue) if hue > 0 else 0.0
    return adjust_color(img, f[0], f[1], f[2], h)


# --- exposure, blur, noise: in linear light -------------------------------------------------------


def adjust_exposure(img: torch.Tensor, gain: float) -> torch.Tensor:
    """Multiply the linear light by `gain` (> 0; 2 is one stop brighter), clip, back to sRGB."""
    _check_image(img)
    if not gain > 0:
        raise InputError(f"exposure: gain must be > 0, got {gain}")
    return linear_to_srgb(srgb_to_linear(img) * gain)


def random_exposure(img: torch.Tensor, gen: torch.Generator, stops: float) -> torch.Tensor:
    """`adjust_exposure` with gain 2^s, s uniform in [-stops, stops]."""
    if stops < 0:
        raise InputError(f"exposure: stops must be >= 0, got {stops}")
    return adjust_exposure(img, 2.0 ** _uniform(gen, -stops, stops))


def gaussian_blur(img: torch.Tensor, sigma: float) -> torch.Tensor:
    """Separable Gaussian blur of standard deviation `sigma` pixels (kernel radius ceil(3 sigma),
    borders replicated) in linear light; sigma 0 returns a copy."""
    _check_image(img)
    if sigma < 0:
        raise InputError(f"blur: sigma must be >= 0, got {sigma}")
    if sigma == 0:
        return img.clone()
    r = max(1, math.ceil(3 * sigma))
    x = torch.arange(-r, r + 1, dtype=torch.float64)
    k = torch.exp(-0.5 * (x / sigma) ** 2)
    k = (k / k.sum()).to(img.dtype)
    lin = srgb_to_linear(img)[None]  # (1, 3, H, W)
    lin = F.conv2d(F.pad(lin, (r, r, 0, 0), mode="replicate"), k.view(1, 1, 1, -1).repeat(3, 1, 1, 1), groups=3)
    lin = F.conv2d(F.pad(lin, (0, 0, r, r), mode="replicate"), k.view(1, 1, -1, 1).repeat(3, 1, 1, 1), groups=3)
    return linear_to_srgb(lin[0])


def random_blur(img: torch.Tensor, gen: torch.Generator, sigma: tuple[float, float]) -> torch.Tensor:
    """`gaussian_blur` with sigma uniform in [sigma[0], sigma[1]] pixels."""
    return gaussian_blur(img, _uniform(gen, *sigma))


def sensor_noise(img: torch.Tensor, gen: torch.Generator, shot: float, read: float) -> torch.Tensor:
    """Add zero-mean Gaussian noise of variance ``shot * x + read**2`` to each linear-light value x
    (shot: the shot-noise variance per unit of signal, i.e. 1 / the full-well charge in units of
    full scale; read: the read-noise standard deviation, full scale), clip, back to sRGB."""
    _check_image(img)
    if shot < 0 or read < 0:
        raise InputError(f"sensor noise: shot and read must be >= 0, got {shot}, {read}")
    lin = srgb_to_linear(img)
    std = torch.sqrt(shot * lin + read * read)
    return linear_to_srgb(lin + std * torch.randn(lin.shape, generator=gen, dtype=lin.dtype))


def random_sensor_noise(img: torch.Tensor, gen: torch.Generator, shot: tuple[float, float],
                        read: tuple[float, float]) -> torch.Tensor:
    """`sensor_noise` with shot and read drawn uniformly from their ranges."""
    return sensor_noise(img, gen, _uniform(gen, *shot), _uniform(gen, *read))


# --- JPEG ----------------------------------------------------------------------------------------


def to_uint8(img: torch.Tensor) -> np.ndarray:
    """(3, H, W) float in [0, 1] -> (H, W, 3) uint8 (rounded)."""
    _check_image(img)
    return (img.clamp(0, 1) * 255.0).round().to(torch.uint8).permute(1, 2, 0).contiguous().numpy()


def from_uint8(rgb: np.ndarray) -> torch.Tensor:
    """(H, W, 3) uint8 -> (3, H, W) float32 in [0, 1]."""
    return torch.from_numpy(np.array(rgb, np.uint8)).permute(2, 0, 1).to(torch.float32) / 255.0


def jpeg(img: torch.Tensor, quality: int) -> torch.Tensor:
    """Encode as JPEG at `quality` (1..95, PIL's scale; 4:2:0 chroma subsampling, PIL's default)
    and decode again: blocking, ringing and chroma bleeding of a compressed camera stream."""
    if not 1 <= int(quality) <= 95:
        raise InputError(f"jpeg: quality must be in 1..95, got {quality}")
    buf = io.BytesIO()
    Image.fromarray(to_uint8(img)).save(buf, format="JPEG", quality=int(quality))
    buf.seek(0)
    with Image.open(buf) as im:
        return from_uint8(np.asarray(im.convert("RGB"), np.uint8))


def random_jpeg(img: torch.Tensor, gen: torch.Generator, quality: tuple[int, int]) -> torch.Tensor:
    """`jpeg` at a quality drawn uniformly from the integers quality[0]..quality[1]."""
    lo, hi = int(quality[0]), int(quality[1])
    return jpeg(img, int(torch.randint(lo, hi + 1, (), generator=gen)))


# --- configuration ---------------------------------------------------------------------------------


def _ordered(name: str, pair: tuple[float, float]) -> None:
    if pair[0] > pair[1]:
        raise ValueError(f"{name}: expected (low, high) with low <= high, got {tuple(pair)}")


class ColorJitterConfig(StrictModel):
    """Probability and ranges of `color_jitter` (factors 1 +- b, hue +- turns)."""

    p: float = Field(default=0.8, ge=0, le=1)
    brightness: float = Field(default=0.2, ge=0, le=1)
    contrast: float = Field(default=0.2, ge=0, le=1)
    saturation: float = Field(default=0.2, ge=0, le=1)
    hue: float = Field(default=0.02, ge=0, le=0.5)


class ExposureConfig(StrictModel):
    """Probability and range (+- stops) of `random_exposure`."""

    p: float = Field(default=0.5, ge=0, le=1)
    stops: float = Field(default=0.5, ge=0)


class BlurConfig(StrictModel):
    """Probability and sigma range (pixels of the returned image) of `random_blur`."""

    p: float = Field(default=0.2, ge=0, le=1)
    sigma: tuple[float, float] = (0.3, 1.0)

    @model_validator(mode="after")
    def _check(self):
        _ordered("sigma", self.sigma)
        if self.sigma[0] < 0:
            raise ValueError(f"sigma: must be >= 0, got {self.sigma}")
        return self


class NoiseConfig(StrictModel):
    """Probability and ranges of `random_sensor_noise` (shot: variance per unit linear signal;
    read: standard deviation, linear full scale)."""

    p: float = Field(default=0.5, ge=0, le=1)
    shot: tuple[float, float] = (0.0, 0.002)
    read: tuple[float, float] = (0.0, 0.005)

    @model_validator(mode="after")
    def _check(self):
        for name in ("shot", "read"):
            _ordered(name, getattr(self, name))
            if getattr(self, name)[0] < 0:
                raise ValueError(f"{name}: must be >= 0, got {getattr(self, name)}")
        return self


class JpegConfig(StrictModel):
    """Probability and quality range (PIL's 1..95) of `random_jpeg`."""

    p: float = Field(default=0.3, ge=0, le=1)
    quality: tuple[int, int] = (40, 95)

    @model_validator(mode="after")
    def _check(self):
        _ordered("quality", self.quality)
        if self.quality[0] < 1 or self.quality[1] > 95:
            raise ValueError(f"quality: must lie in 1..95, got {self.quality}")
        return self


class AugmentConfig(StrictModel):
    """The photometric augmentations `photometric` applies, each with its own probability."""

    color_jitter: ColorJitterConfig = Field(default_factory=ColorJitterConfig)
    exposure: ExposureConfig = Field(default_factory=ExposureConfig)
    blur: BlurConfig = Field(default_factory=BlurConfig)
    noise: NoiseConfig = Field(default_factory=NoiseConfig)
    jpeg: JpegConfig = Field(default_factory=JpegConfig)


def photometric(img: torch.Tensor, gen: torch.Generator, cfg: AugmentConfig) -> torch.Tensor:
    """Apply the augmentations of `cfg` in the order a camera makes a picture: blur (optics),
    exposure gain, sensor noise, colour processing, JPEG; each with its probability p. One
    uniform draw per augmentation decides whether it runs (drawn even when p is 0 or 1, so the
    draws of one do not shift with another's p)."""
    _check_image(img)
    out = img
    if float(torch.rand((), generator=gen, dtype=torch.float64)) < cfg.blur.p:
        out = random_blur(out, gen, cfg.blur.sigma)
    if float(torch.rand((), generator=gen, dtype=torch.float64)) < cfg.exposure.p:
        out = random_exposure(out, gen, cfg.exposure.stops)
    if float(torch.rand((), generator=gen, dtype=torch.float64)) < cfg.noise.p:
        out = random_sensor_noise(out, gen, cfg.noise.shot, cfg.noise.read)
    cj = cfg.color_jitter
    if float(torch.rand((), generator=gen, dtype=torch.float64)) < cj.p:
        out = color_jitter(out, gen, cj.brightness, cj.contrast, cj.saturation, cj.hue)
    if float(torch.rand((), generator=gen, dtype=torch.float64)) < cfg.jpeg.p:
        out = random_jpeg(out, gen, cfg.jpeg.quality)
    return out


# --- rig randomisation -------------------------------------------------------------------------------


class CameraSelection(StrictModel):
    """Which cameras of a sample a training item keeps.

    mode: ``all`` every camera; ``front`` only the front camera (`front_camera`); ``drop`` each
    camera dropped independently with probability `drop_p`, the front one never if `keep_front`,
    and one camera chosen uniformly kept if all were dropped."""

    mode: Literal["all", "front", "drop"] = "all"
    drop_p: float = Field(default=0.3, ge=0, le=1)
    keep_front: bool = True


def front_camera(names: list[str]) -> int:
    """Index of the front camera: the one named FRONT or CAM_FRONT (any case)."""
    hits = [i for i, n in enumerate(names) if n.upper() in FRONT_NAMES]
    if len(hits) != 1:
        raise InputError(f"cameras {', '.join(names)}: expected exactly one front camera named "
                         f"{' or '.join(FRONT_NAMES)}, found {len(hits)}")
    return hits[0]


def choose_cameras(names: list[str], gen: torch.Generator, sel: CameraSelection) -> list[int]:
    """Indices (ascending, at least one) into `names` of the cameras to keep under `sel`."""
    if not names:
        raise InputError("cameras: a sample needs at least one camera")
    if sel.mode == "all":
        return list(range(len(names)))
    if sel.mode == "front":
        return [front_camera(names)]
    front = front_camera(names) if sel.keep_front else -1
    drop = torch.rand(len(names), generator=gen, dtype=torch.float64) < sel.drop_p
    keep = [i for i in range(len(names)) if i == front or not bool(drop[i])]
    if not keep:
        keep = [int(torch.randint(len(names), (), generator=gen))]
    return keep


__all__ = ["FRONT_NAMES", "LUMA", "AugmentConfig", "BlurConfig", "CameraSelection", "ColorJitterConfig",
           "ExposureConfig", "JpegConfig", "NoiseConfig", "adjust_color", "adjust_exposure", "choose_cameras",
           "color_jitter", "from_uint8", "front_camera", "gaussian_blur", "jpeg", "linear_to_srgb", "photometric",
           "random_blur", "random_exposure", "random_jpeg", "random_sensor_noise", "sensor_noise", "srgb_to_linear",
           "to_uint8"]
