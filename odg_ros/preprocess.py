"""Image preprocessing shared by the dataset and the online node (one code path for both).

Resize keeps the aspect ratio so the width matches the network input; then the top is
cropped (or the bottom zero-padded) to the input height, the BEVDet/SparseBEV convention
that keeps the road. Intrinsics are adjusted the same way.

NumPy and Pillow; torch only inside ``normalize`` (the host side of an exported step runs
without it: online/onnx_inputs.py).
"""
from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from PIL import Image

if TYPE_CHECKING:
    import torch

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


def resize_crop_params(src_hw, dst_hw) -> tuple[float, int, tuple[int, int]]:
    """(scale, crop_top, resized_hw) taking a (H, W) image to the network input (H', W')."""
    src_h, src_w = src_hw
    dst_h, dst_w = dst_hw
    if min(src_h, src_w, dst_h, dst_w) < 1:
        raise ValueError(f"cannot resize a {src_h}x{src_w} image to {dst_h}x{dst_w}")
    scale = dst_w / src_w
    resized_h = int(round(src_h * scale))
    if resized_h < 1:  # wider than dst_w : 1 -- nothing of it would be left
        raise ValueError(f"a {src_h}x{src_w} image resizes to 0 rows at width {dst_w}")
    crop_top = max(0, resized_h - dst_h)
    return scale, crop_top, (resized_h, dst_w)


def jpeg_reduction(src_hw, dst_hw) -> int:
    """The largest of 8, 4, 2 by which libjpeg may scale a (H, W) JPEG down while decoding
    (DCT scaling) without changing the network input's geometry, else 1: the reduced image
    divides the original exactly (same field of view, pixel grid scaled exactly), is at least
    as large as the resized image and gives the same crop, so ``adjust_intrinsics`` of the
    original size still holds. Raises ValueError for a size no network input can be made of."""
    src_h, src_w = src_hw
    _, crop_top, resized_hw = resize_crop_params((src_h, src_w), dst_hw)
    for factor in (8, 4, 2):
        small = (src_h // factor, src_w // factor)
        if (src_h % factor or src_w % factor or small[0] < resized_hw[0]
                or small[1] < resized_hw[1]
                or resize_crop_params(small, dst_hw)[1:] != (crop_top, resized_hw)):
            continue
        return factor
    return 1


def draft_jpeg(image: Image.Image, dst_hw) -> bool:
    """Let libjpeg decode an opened, not yet loaded JPEG at the scale of ``jpeg_reduction``
    (Pillow ``draft``). Returns whether it applied. Measured on 1600x900 JPEGs: decode +
    resize/crop 2-3x faster; lines land within 0.02 px of the full-decode path at 128x352 and
    256x704, pixel values within ~1 grey level.
    Raises ValueError for a size no network input can be made of."""
    if image.format != "JPEG":
        return False
    factor = jpeg_reduction((image.height, image.width), dst_hw)
    if factor == 1:
        return False
    small = (image.height // factor, image.width // factor)
    image.draft("RGB", small[::-1])
    if (image.height, image.width) != small:
        raise RuntimeError(f"JPEG draft gave {image.height}x{image.width}, asked {small}")
    return True


def adjust_intrinsics(K, src_hw, dst_hw) -> np.ndarray:
    """Intrinsics of the network input image given those of the source image."""
    scale, crop_top, _ = resize_crop_params(src_hw, dst_hw)
    K2 = np.asarray(K, dtype=np.float64).copy()
    K2[:2] *= scale
    K2[1, 2] -= crop_top
    return K2


def image_bounds(image_hws, input_hw) -> np.ndarray:
    """float32 [N, 4] (u0, v0, u1, v1): each camera's whole image, of size image_hws[n]
    (H, W), in the pixels of the network input it is resized and cropped to (``input_hw``):
    the rows cropped off the top lie above row 0."""
    bounds = []
    for hw in image_hws:
        _, crop_top, (resized_h, resized_w) = resize_crop_params(tuple(hw), tuple(input_hw))
        bounds.append((0.0, -float(crop_top), float(resized_w), float(resized_h - crop_top)))
    return np.asarray(bounds, dtype=np.float32)


def resize_crop(image: np.ndarray, dst_hw) -> np.ndarray:
    """HxWx3 uint8 RGB -> H'xW'x3 uint8 (resize to width, crop top / pad bottom)."""
    if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
        raise ValueError(f"expected HxWx3 uint8 RGB, got {image.shape} {image.dtype}")
    scale, crop_top, (rh, rw) = resize_crop_params(image.shape[:2], dst_hw)
    if (rh, rw) != image.shape[:2]:
        image = np.asarray(Image.fromarray(image).resize((rw, rh), Image.BILINEAR))
    image = image[crop_top:crop_top + dst_hw[0]]
    if image.shape[0] < dst_hw[0]:
        pad = np.zeros((dst_hw[0] - image.shape[0], dst_hw[1], 3), np.uint8)
        image = np.concatenate([image, pad], axis=0)
    return image


def normalize(images_uint8: torch.Tensor) -> torch.Tensor:
    """[..., H, W, 3] uint8 RGB -> [..., 3, H, W] float32, ImageNet mean/std normalised."""
    from .transfer import device_constant
    x = images_uint8.float().div_(255.0)
    mean = device_constant(IMAGENET_MEAN, x.device, x.dtype)
    std = device_constant(IMAGENET_STD, x.device, x.dtype)
    x = (x - mean) / std
    return x.movedim(-1, -3).contiguous()
