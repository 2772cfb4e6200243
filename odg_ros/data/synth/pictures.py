"""Preview pictures: a six-camera mosaic and a bird's-eye view of an Occ3D grid."""
from __future__ import annotations

import numpy as np
from PIL import Image, ImageDraw

from odg_ros.classes import FREE_LABEL, OCC_CLASSES, OCC_COLORS
from odg_ros.data.batch import CAMERA_NAMES

# mosaic layout as the cameras look around the car: front row left to right, back row mirrored
MOSAIC_ORDER = (("CAM_FRONT_LEFT", "CAM_FRONT", "CAM_FRONT_RIGHT"),
                ("CAM_BACK_RIGHT", "CAM_BACK", "CAM_BACK_LEFT"))


def camera_mosaic(images: dict) -> Image.Image:
    """2 x 3 mosaic of {CAM_NAME: HxWx3 uint8} with the camera names written in."""
    assert set(images) == set(CAMERA_NAMES), sorted(images)
    h, w = next(iter(images.values())).shape[:2]
    out = Image.new("RGB", (3 * w, 2 * h))
    draw = ImageDraw.Draw(out)
    for r, row in enumerate(MOSAIC_ORDER):
        for c, name in enumerate(row):
            out.paste(Image.fromarray(images[name]), (c * w, r * h))
            draw.text((c * w + 4, r * h + 3), name, fill=(255, 255, 0))
    return out


def bev_image(semantics: np.ndarray, mask: np.ndarray | None = None, scale: int = 3) -> Image.Image:
    """Top view of a [X, Y, Z] label grid: per column the highest non-free voxel, coloured with
    classes.OCC_COLORS; x (forward) points up, y (left) points left; columns outside ``mask``
    (any voxel observed) are darkened. A legend of the classes present is drawn on the right."""
    X, Y, Z = semantics.shape
    occupied = semantics != FREE_LABEL
    top = np.where(occupied.any(2), Z - 1 - np.argmax(occupied[:, :, ::-1], axis=2), -1)
    label = np.where(top >= 0, np.take_along_axis(semantics, np.maximum(top, 0)[..., None], 2)[..., 0], FREE_LABEL)
    rgb = np.asarray(OCC_COLORS, np.uint8)[label]
    if mask is not None:
        seen = mask.any(2)
        rgb = np.where(seen[..., None], rgb, (rgb * 0.45).astype(np.uint8))
    rgb = rgb[::-1, ::-1]                                  # rows: x descending; cols: y descending
    img = Image.fromarray(np.ascontiguousarray(rgb)).resize((Y * scale, X * scale), Image.NEAREST)
    legend_w = 150
    out = Image.new("RGB", (img.width + legend_w, img.height), (255, 255, 255))
    out.paste(img, (0, 0))
    draw = ImageDraw.Draw(out)
    cx, cy = img.width // 2, img.height // 2
    draw.polygon([(cx, cy - 8), (cx - 5, cy + 6), (cx + 5, cy + 6)], fill=(255, 0, 0), outline=(0, 0, 0))
    present = [int(v) for v in np.unique(label) if v != FREE_LABEL]
    for i, v in enumerate(present):
        y = 8 + i * 16
        draw.rectangle([img.width + 8, y, img.width + 20, y + 11], fill=tuple(OCC_COLORS[v]), outline=(0, 0, 0))
        draw.text((img.width + 26, y), OCC_CLASSES[v], fill=(0, 0, 0))
    return out
