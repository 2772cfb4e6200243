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
from contextlib import nullcontext
from dataclasses import dataclass

import numpy as np
from PIL import Image, UnidentifiedImageError

from ..preprocess import adjust_intrinsics, draft_jpeg, resize_crop, resize_crop_params
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


# ------------------------------------------------------------------ JPEG sets on the GPU
def resize_crop_tensor(image: "torch.Tensor", dst_hw) -> "torch.Tensor":
    """uint8 [3, H, W] (any device) -> uint8 [H', W', 3]: preprocess.resize_crop's
    geometry, with PyTorch's antialiased bilinear resize (made to match Pillow's;
    within a grey level or two of it)."""
    import torch
    scale, crop_top, (rh, rw) = resize_crop_params(tuple(image.shape[1:]), dst_hw)
    x = image
    if (rh, rw) != tuple(image.shape[1:]):
        x = torch.nn.functional.interpolate(image[None].float(), size=(rh, rw),
                                            mode="bilinear", antialias=True,
                                            align_corners=False)[0]
        x = x.round_().clamp_(0, 255).to(torch.uint8)
    x = x[:, crop_top:crop_top + dst_hw[0]].permute(1, 2, 0)
    if x.shape[0] < dst_hw[0]:
        x = torch.nn.functional.pad(x, (0, 0, 0, 0, 0, dst_hw[0] - x.shape[0]))
    return x.contiguous()


class DeviceJpegDecoder:
    """A set of JPEGs decoded on the model's device by ``torchvision.io.decode_jpeg``
    (nvJPEG on CUDA, one batched call) and resized/cropped there: no decoded image
    crosses the PCIe bus. Sizes are checked on the JPEG headers first, as on the CPU path.
    ``decode_set`` returns None for a set that is not all JPEG (the CPU path takes it)."""

    def __init__(self, device, decode_jpeg, rgb_mode):
        import torch
        self.device = torch.device(device)
        self._decode_jpeg, self._rgb = decode_jpeg, rgb_mode
        # decoding runs on a stream of its own, so it overlaps the model's kernels
        self.stream = torch.cuda.Stream(self.device) if self.device.type == "cuda" else None

    def decode_set(self, images, cameras, expected_hws, input_hw,
                   max_pixels: int = DEFAULT_MAX_PIXELS):
        """-> (uint8 [N, H', W', 3] on the device, a CUDA event recorded when it is ready
        (None off CUDA): pass both to ``hand_over`` in the thread that uses them), or None.
        Raises BadInput naming the camera, as the CPU path does."""
        import torch
        if not all(i.compressed and _is_jpeg(i.data) for i in images):
            return None
        for image, camera, expected_hw in zip(images, cameras, expected_hws):
            try:
                with Image.open(io.BytesIO(image.data), formats=("JPEG",)) as header:
                    _check_size(header.height, header.width, expected_hw, max_pixels)
            except BadInput as error:
                raise BadInput(error.kind, f"{camera}: {error.message}") from None
            except (OSError, SyntaxError, ValueError, UnidentifiedImageError) as error:
                raise BadInput("corrupt_image", f"{camera}: corrupt JPEG header "
                               f"({len(image.data)} bytes): {error}") from None
        data = [torch.frombuffer(bytearray(i.data), dtype=torch.uint8) for i in images]
        context = torch.cuda.stream(self.stream) if self.stream is not None else nullcontext()
        with context:
            try:
                decoded = self._decode_jpeg(data, mode=self._rgb, device=self.device)
            except RuntimeError:          # name the camera whose image failed
                decoded = [self._decode_one(d, camera) for d, camera in zip(data, cameras)]
            out = torch.stack([resize_crop_tensor(d, input_hw) for d in decoded])
            ready = torch.cuda.Event() if self.stream is not None else None
            if ready is not None:
                ready.record(self.stream)
        return out, ready

    @staticmethod
    def hand_over(images, ready) -> None:
        """In the thread that uses ``decode_set``'s images: its stream waits for them (and
        the allocator keeps them until that stream is done with them)."""
        if ready is not None:
            import torch
            current = torch.cuda.current_stream(images.device)
            current.wait_event(ready)
            images.record_stream(current)

    def _decode_one(self, data, camera: str):
        try:
            return self._decode_jpeg([data], mode=self._rgb, device=self.device)[0]
        except RuntimeError as error:
            raise BadInput("corrupt_image", f"{camera}: corrupt or truncated JPEG "
                           f"({len(data)} bytes): {error}") from None


def _is_jpeg(data: bytes) -> bool:
    return data[:3] == b"\xff\xd8\xff"


def _probe_jpeg() -> bytes:
    buffer = io.BytesIO()
    Image.fromarray(np.full((16, 16, 3), 128, np.uint8)).save(buffer, format="JPEG")
    return buffer.getvalue()


def select_jpeg_decoder(device, import_io=None) -> tuple[DeviceJpegDecoder | None, str]:
    """(decoder, why) for a model on ``device``: a DeviceJpegDecoder where the device is
    CUDA and torchvision decodes a probe JPEG there, else (None, why not): Pillow on the
    CPU. ``import_io`` returns ``torchvision.io`` (tests pass their own)."""
    import torch
    device = torch.device(device)
    if device.type != "cuda":
        return None, f"JPEG decoding on the CPU (Pillow): the model runs on {device}"
    return device_jpeg_decoder(device, import_io or _import_torchvision_io)


def device_jpeg_decoder(device, import_io) -> tuple[DeviceJpegDecoder | None, str]:
    """select_jpeg_decoder past the device check (any device: tests run it on the CPU)."""
    import torch
    try:
        tv_io = import_io()
        decode_jpeg, rgb = tv_io.decode_jpeg, tv_io.ImageReadMode.RGB
    except (ImportError, AttributeError) as error:
        return None, (f"JPEG decoding on the CPU (Pillow): torchvision.io.decode_jpeg is "
                      f"not available ({error})")
    try:
        probe = torch.frombuffer(bytearray(_probe_jpeg()), dtype=torch.uint8)
        decoded = decode_jpeg([probe], mode=rgb, device=device)[0]
        if tuple(decoded.shape) != (3, 16, 16) or decoded.device != device:
            raise RuntimeError(f"probe decoded to {tuple(decoded.shape)} on {decoded.device}")
    except Exception as error:       # no nvJPEG, an old torchvision without lists, ...
        return None, (f"JPEG decoding on the CPU (Pillow): torchvision could not decode on "
                      f"{device} ({type(error).__name__}: {error})")
    return (DeviceJpegDecoder(device, decode_jpeg, rgb),
            f"JPEG decoding on {device} (torchvision.io.decode_jpeg)")


def _import_torchvision_io():
    import torchvision.io
    return torchvision.io
