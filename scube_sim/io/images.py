"""Camera images from files: `read_rgb(path)` -> (H, W, 3) uint8, the one reader every dataset
adapter decodes its camera images with.

What it does with what a camera log can hold (decided here, once, for every adapter):

- 8-bit RGB: as stored.
- 16 bits per channel (PNG or TIFF grey ``I;16`` / ``I;16B`` / ``I;16L``, 48-bit RGB PNG, 16-bit
  grey+alpha or RGBA PNG): the high byte, ``value >> 8`` (as libpng's ``png_set_strip_16`` and
  OpenCV do), so 16-bit ``k * 257`` reads back as ``k`` and full scale stays full scale. PIL alone
  clips 16-bit grey to 255 (an all-white image); this reader never does.
- 32-bit integer grey (mode ``I``, how some PIL versions open 16-bit PNGs): as 16-bit when every
  value lies in 0..65535, else refused by name; 32-bit float (mode ``F``): refused by name (no
  known white level).
- grey (``L``) and 1-bit (0 -> 0, 1 -> 255): the grey level in all three channels; palette
  (``P``, ``PA``): the palette's colours; ``CMYK``, ``YCbCr``, ``LAB``, ``HSV``: PIL's conversion
  to RGB (CMYK without colour management: R = (255 - C)(255 - K) / 255).
- alpha (``LA``, ``RGBA``, ``PA``, 16-bit too): dropped; the colour channels are used as stored,
  not composited over a background (a camera has no transparency).
- EXIF orientation: IGNORED. The pixels are used as stored, because a dataset's intrinsics (and
  the image size it states) describe the stored sensor layout; rotating to the display
  orientation would no longer match them.
- several frames (a phone's MPO, an animated file): the first frame.
- huge images: REFUSED, never downscaled (a downscaled image would no longer match the dataset's
  intrinsics): more than `MAX_PIXELS` pixels, decided from the file's header before any pixel
  is decoded, with a message naming the file and its pixel count. PIL's own
  ``DecompressionBombError`` (above twice ``PIL.Image.MAX_IMAGE_PIXELS``) becomes the same message.

Anything else that cannot be decoded (not an image, truncated, corrupt, an unsupported mode) is
one `InputError` line naming the file.
"""

from __future__ import annotations

import re
import warnings
from pathlib import Path

import numpy as np
from PIL import Image

from ..errors import InputError

# 8192 x 8192: above every automotive camera (Waymo 1920 x 1280, nuScenes 1600 x 900, 8 MP
# 3840 x 2160), and an (H, W, 3) uint8 copy of it is 192 MiB.
MAX_PIXELS = 8192 * 8192

_GREY16 = ("I;16", "I;16L", "I;16B", "I;16N")


def _one_line(exc: BaseException) -> str:
    text = " ".join(str(exc).split())
    return text or type(exc).__name__


def _too_big(path: Path, pixels: int, size: tuple[int, int] | None, max_pixels: int) -> str:
    dims = f"{size[0]} x {size[1]} = " if size is not None else ""
    return (f"{path}: image of {dims}{pixels} pixels, more than the {max_pixels} this reader decodes; "
            f"refused before decoding it (downscale the image and its intrinsics together)")


def _open(path: Path, error: type[InputError], max_pixels: int) -> Image.Image:
    """PIL's lazy image (header read, pixels not decoded); sizes above `max_pixels` refused."""
    if not path.is_file():
        raise error(f"{path}: no such image file")
    try:
        with warnings.catch_warnings():  # PIL warns above MAX_IMAGE_PIXELS; we decide ourselves
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)
            im = Image.open(path)
    except Image.DecompressionBombError as exc:  # above 2 x PIL.Image.MAX_IMAGE_PIXELS, header only
        m = re.search(r"\((\d+) pixels\)", str(exc))
        pixels = int(m[1]) if m else 2 * int(Image.MAX_IMAGE_PIXELS or 0) + 1
        raise error(_too_big(path, pixels, None, max_pixels)) from None
    except Exception as exc:  # noqa: BLE001  (PIL raises many kinds for a file that is not an image)
        raise error(f"{path}: not a readable image ({_one_line(exc)})") from None
    w, h = im.size
    if w * h > max_pixels:
        im.close()
        raise error(_too_big(path, w * h, (w, h), max_pixels))
    return im


def read_rgb(path: str | Path, *, max_pixels: int = MAX_PIXELS, error: type[InputError] = InputError) -> np.ndarray:
    """The image file at `path` as (H, W, 3) uint8 (see the module docstring for every mode and
    depth). Refuses images of more than `max_pixels` pixels before decoding them; every failure
    is one `error` (an `InputError` subclass, e.g. a dataset's own) naming the file."""
    path = Path(path)
    if Image.MAX_IMAGE_PIXELS:  # PIL refuses above twice its own limit, before we see the size
        max_pixels = min(int(max_pixels), 2 * int(Image.MAX_IMAGE_PIXELS))
    with _open(path, error, int(max_pixels)) as im:
        mode = im.mode
        try:
            if mode in _GREY16 or mode == "I":
                a = np.asarray(im)
                if mode == "I" and a.size and (int(a.min()) < 0 or int(a.max()) > 65535):
                    raise error(f"{path}: 32-bit integer pixels from {int(a.min())} to {int(a.max())}: not an 8- "
                                f"or 16-bit camera image (values 0..65535); convert it to 8 or 16 bits per channel")
                grey = (a.astype(np.uint32) >> 8).astype(np.uint8)  # any byte order -> native, then the high byte
                return np.repeat(grey[..., None], 3, axis=-1)
            if mode == "F":
                raise error(f"{path}: 32-bit float pixels (PIL mode F) have no white level; "
                            f"convert the image to 8 or 16 bits per channel")
            if mode == "RGB":
                return np.array(im, dtype=np.uint8)
            if mode == "La":  # premultiplied grey+alpha: PIL converts it to LA only
                im = im.convert("LA")
            return np.array(im.convert("RGB"), dtype=np.uint8)
        except InputError:
            raise
        except Exception as exc:  # noqa: BLE001  (a truncated or corrupt file fails while decoding)
            raise error(f"{path}: not a readable image (PIL mode {mode}: {_one_line(exc)})") from None
