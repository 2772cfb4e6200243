"""Camera image messages -> network input (decode, validate, resize/crop, intrinsics).

Decoding: ``sensor_msgs/CompressedImage`` payloads in JPEG or PNG (Pillow), and raw
``sensor_msgs/Image`` buffers in rgb8, bgr8, rgba8, bgra8 and mono8. Every failure is a
``BadInput`` with a specific kind (corrupt data, an encoding we do not decode, a size that
disagrees with the CameraInfo), never a crash and never a silently wrong image.
The resize/crop and the intrinsics adjustment are preprocess.py's, shared with training.

The size of a compressed image is read from its header (JPEG SOF, PNG IHDR: Pillow's open
reads no pixel data) and checked against the CameraInfo and ``max_pixels`` before anything
is decoded: a small PNG of a huge blank image costs no memory.
"""
from __future__ import annotations

import io
from dataclasses import dataclass

import numpy as np
from PIL import Image, UnidentifiedImageError

from ..preprocess import adjust_intrinsics, draft_jpeg, resize_crop
from .errors import BadInput

# Decoded images larger than this are refused unread (16 MP: a 4K camera fits twice).
DEFAULT_MAX_PIXELS = 4096 * 4096

# raw encoding -> (channels, channel order to take RGB from)
RAW_ENCODINGS = {
    "rgb8": (3, (0, 1, 2)),
    "bgr8": (3, (2, 1, 0)),
    "rgba8": (4, (0, 1, 2)),
    "bgra8": (4, (2, 1, 0)),
    "mono8": (1, (0, 0, 0)),
}


@dataclass
class EncodedImage:
    """The fields of an image message that decoding needs (no ROS types).

    compressed  True for CompressedImage, False for a raw Image
    format      CompressedImage.format (e.g. 'jpeg', 'png', 'bgr8; jpeg compressed bgr8')
                or Image.encoding (e.g. 'rgb8')
    data        the payload bytes
    height, width, step   raw images only (Image.height/width/step)
    """

    compressed: bool
    format: str
    data: bytes
    height: int = 0
    width: int = 0
    step: int = 0


def _check_size(height: int, width: int, expected_hw, max_pixels: int) -> None:
    if height * width > max_pixels:
        raise BadInput("image_too_large", f"image header declares {height}x{width} (HxW) "
                       f"= {height * width} pixels > max_image_pixels {max_pixels}")
    if expected_hw is not None and (height, width) != tuple(expected_hw):
        raise BadInput("wrong_image_size", f"image is {height}x{width} (HxW) but its "
                       f"CameraInfo says {expected_hw[0]}x{expected_hw[1]}")


def _decode_pillow(data: bytes, fmt: str, reduce_for=None, expected_hw=None,
                   max_pixels: int = DEFAULT_MAX_PIXELS) -> tuple[np.ndarray, tuple[int, int]]:
    """-> (RGB array, original (H, W)). See decode_compressed / decode_for_input."""
    lowered = fmt.lower()
    if "compresseddepth" in lowered or "16uc" in lowered or "32fc" in lowered:
        raise BadInput("unsupported_encoding", f"compressed format {fmt!r} is not a colour "
                       "JPEG/PNG image")
    if len(data) == 0:
        raise BadInput("corrupt_image", "empty compressed image")
    try:
        with Image.open(io.BytesIO(data), formats=("JPEG", "PNG")) as image:
            width, height = image.size
            _check_size(height, width, expected_hw, max_pixels)     # before any decoding
            if reduce_for is not None:
                try:
                    draft_jpeg(image, reduce_for)
                except ValueError as err:   # e.g. a corrupt size header: 25472 x 72
                    raise _NoInputSize(str(err)) from None
            image.load()     # decode now: truncated data raises here, not later
            mode = image.mode
            if mode in ("I", "I;16", "I;16B", "I;16L", "F"):
                raise BadInput("unsupported_encoding", f"{image.format} with {mode} pixels "
                               "(16-bit/float); expected 8-bit colour or grey")
            rgb = image if mode == "RGB" else image.convert("RGB")
            array = np.asarray(rgb, dtype=np.uint8)
    except BadInput:
        raise
    except UnidentifiedImageError as error:
        raise BadInput("corrupt_image", f"not a decodable JPEG/PNG ({fmt!r}, {len(data)} "
                       f"bytes): {error}") from None
    except (OSError, SyntaxError, ValueError, Image.DecompressionBombError) as error:
        raise BadInput("corrupt_image", f"corrupt or truncated image ({fmt!r}, {len(data)} "
                       f"bytes): {error}") from None
    if array.ndim != 3 or array.shape[2] != 3 or array.size == 0:
        raise BadInput("corrupt_image", f"decoded to an unusable array {array.shape}")
    return array, (height, width)


class _NoInputSize(Exception):
    """The image has a size no network input can be made of."""


def decode_compressed(data: bytes, fmt: str = "",
                      max_pixels: int = DEFAULT_MAX_PIXELS) -> np.ndarray:
    """JPEG/PNG bytes -> HxWx3 uint8 RGB. Raises BadInput on corrupt or unsupported data."""
    return _decode_pillow(data, fmt, max_pixels=max_pixels)[0]


def decode_raw(data: bytes, encoding: str, height: int, width: int, step: int,
               max_pixels: int = DEFAULT_MAX_PIXELS) -> np.ndarray:
    """Raw ``sensor_msgs/Image`` buffer -> HxWx3 uint8 RGB."""
    if encoding not in RAW_ENCODINGS:
        raise BadInput("unsupported_encoding", f"raw encoding {encoding!r} is not supported; "
                       f"use one of {sorted(RAW_ENCODINGS)}")
    channels, order = RAW_ENCODINGS[encoding]
    if height <= 0 or width <= 0:
        raise BadInput("corrupt_image", f"raw image of size {height}x{width}")
    _check_size(height, width, None, max_pixels)
    if step < width * channels:
        raise BadInput("corrupt_image", f"raw {encoding} step {step} < width*channels "
                       f"{width * channels}")
    if len(data) < step * height:
        raise BadInput("corrupt_image", f"raw {encoding} buffer has {len(data)} bytes, "
                       f"{step * height} expected (step {step} x height {height})")
    rows = np.frombuffer(data, dtype=np.uint8, count=step * height).reshape(height, step)
    pixels = rows[:, :width * channels].reshape(height, width, channels)
    return np.ascontiguousarray(pixels[:, :, list(order)])


def decode(image: EncodedImage) -> np.ndarray:
    """Either kind of image message -> HxWx3 uint8 RGB (full resolution)."""
    if image.compressed:
        return decode_compressed(image.data, image.format)
    return decode_raw(image.data, image.format, image.height, image.width, image.step)


def decode_for_input(image: EncodedImage, input_hw, expected_hw=None,
                     max_pixels: int = DEFAULT_MAX_PIXELS) -> tuple[np.ndarray, tuple[int, int]]:
    """Decode for a network input of size ``input_hw``: (RGB array, original (H, W)).

    JPEGs may come back reduced (preprocess.draft_jpeg) when that leaves the network input
    unchanged up to JPEG-level noise; pass the result to ``to_network_input`` with
    ``original_hw``. ``expected_hw`` (the CameraInfo's size) and ``max_pixels`` are checked
    on the encoded header, before decoding.
    """
    if image.compressed:
        try:
            return _decode_pillow(image.data, image.format, reduce_for=tuple(input_hw),
                                  expected_hw=expected_hw, max_pixels=max_pixels)
        except _NoInputSize as err:
            raise BadInput("wrong_image_size", str(err)) from None
    rgb = decode_raw(image.data, image.format, image.height, image.width, image.step,
                     max_pixels)
    return rgb, tuple(rgb.shape[:2])


def to_network_input(rgb: np.ndarray, expected_hw, intrinsics, input_hw, original_hw=None):
    """Check the size against the CameraInfo, then resize/crop to the network input.

    rgb [H, W, 3] uint8 (possibly a reduced decode of an ``original_hw`` image);
    expected_hw (H, W) of the CameraInfo; intrinsics 3x3 of the original image
    -> (uint8 [H', W', 3], float64 3x3 intrinsics of the network input).
    """
    expected_hw = tuple(int(v) for v in expected_hw)
    original_hw = tuple(rgb.shape[:2]) if original_hw is None else tuple(original_hw)
    if original_hw != expected_hw:
        raise BadInput("wrong_image_size", f"image is {original_hw[0]}x{original_hw[1]} (HxW) "
                       f"but its CameraInfo says {expected_hw[0]}x{expected_hw[1]}")
    try:
        return resize_crop(rgb, input_hw), adjust_intrinsics(intrinsics, expected_hw, input_hw)
    except ValueError as err:
        raise BadInput("wrong_image_size", str(err)) from None
