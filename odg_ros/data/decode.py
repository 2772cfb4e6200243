"""Camera image files -> network input uint8 [H, W, 3] (the loader's decoder).

JPEGs are decoded by simplejpeg (libjpeg-turbo in a PyPI wheel, no system library) where it
is installed, else by Pillow. Both decode at the reduced scale of
``preprocess.jpeg_reduction`` and give the same pixels (libjpeg-turbo in both, same DCT
and upsampling); simplejpeg skips Pillow's file and image objects. Other formats (PNG) and
JPEGs simplejpeg refuses (CMYK, say) go to Pillow. ``tools/bench_jpeg.py`` measures them.
"""
from __future__ import annotations

import io
from pathlib import Path

import numpy as np
from PIL import Image

from .. import preprocess

try:
    import simplejpeg
except ImportError:           # optional: Pillow decodes every image without it
    simplejpeg = None

JPEG_MAGIC = b"\xff\xd8"


def decode_resized(im: Image.Image, dst_hw) -> np.ndarray:
    """An opened image -> network input uint8 [H, W, 3] (reduced JPEG decode where exact,
    see preprocess.draft_jpeg, then preprocess.resize_crop)."""
    preprocess.draft_jpeg(im, dst_hw)
    return preprocess.resize_crop(np.asarray(im.convert("RGB")), dst_hw)


def decode_jpeg_reduced(data: bytes, dst_hw, expected_hw=None) -> np.ndarray | None:
    """A JPEG's bytes -> RGB uint8 at the scale of preprocess.jpeg_reduction, by simplejpeg;
    None when simplejpeg is not installed or cannot decode this JPEG (Pillow's turn)."""
    if simplejpeg is None or not data.startswith(JPEG_MAGIC):
        return None
    try:
        height, width, _, _ = simplejpeg.decode_jpeg_header(data)
    except ValueError:
        return None
    if expected_hw is not None and (height, width) != tuple(expected_hw):
        raise ValueError(f"image is {height}x{width}, infos say {tuple(expected_hw)}")
    factor = preprocess.jpeg_reduction((height, width), dst_hw)
    try:
        rgb = simplejpeg.decode_jpeg(data, "RGB", min_height=height // factor,
                                     min_width=width // factor, min_factor=factor)
    except ValueError:
        return None
    if rgb.shape != (height // factor, width // factor, 3):
        raise RuntimeError(f"simplejpeg gave {rgb.shape}, asked {height // factor}x"
                           f"{width // factor}")
    return rgb


def read_image(path: Path, dst_hw, expected_hw=None) -> np.ndarray:
    """An image file -> network input uint8 [H, W, 3]; ``expected_hw`` (the infos' size) is
    checked before decoding."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"image not found: {path}")
    data = path.read_bytes()
    try:
        rgb = decode_jpeg_reduced(data, dst_hw, expected_hw)
    except ValueError as error:
        raise ValueError(f"{path}: {error}") from None
    if rgb is not None:
        return preprocess.resize_crop(rgb, dst_hw)
    with Image.open(io.BytesIO(data)) as im:
        if expected_hw is not None and (im.height, im.width) != tuple(expected_hw):
            raise ValueError(f"{path}: image is {im.height}x{im.width}, infos say "
                             f"{tuple(expected_hw)}")
        return decode_resized(im, dst_hw)
