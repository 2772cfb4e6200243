"""Preview pictures: a six-camera mosaic and a bird's-eye view of an Occ3D grid."""
from __future__ import annotations

import numpy as np
from PIL import Image, ImageDraw

from ...classes import FREE_LABEL, OCC_CLASSES, OCC_COLORS
from ...nuscenes_cameras import CAMERA_NAMES

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


def _top_view(semantics, keep=None):
    """[X, Y] label of the highest non-free voxel per column (among ``keep`` voxels)."""
    occupied = semantics != FREE_LABEL
    if keep is not None:
        occupied &= keep
    Z = semantics.shape[2]
    top = np.where(occupied.any(2), Z - 1 - np.argmax(occupied[:, :, ::-1], axis=2), -1)
    return np.where(top >= 0, np.take_along_axis(semantics, np.maximum(top, 0)[..., None], 2)[..., 0], FREE_LABEL)


def bev_image(semantics: np.ndarray, mask: np.ndarray | None = None, scale: int = 3) -> Image.Image:
    """Top view of a [X, Y, Z] label grid coloured with classes.OCC_COLORS (per column the
    highest non-free voxel; x = forward points up, y = left points left, the ego is the red
    triangle). With ``mask`` a second panel shows only the voxels inside it (e.g. mask_camera,
    what the mIoU counts). A legend of the classes present is drawn on the right."""
    X, Y, Z = semantics.shape
    panels = [_top_view(semantics)] + ([_top_view(semantics, mask.astype(bool))] if mask is not None else [])
    colors = np.asarray(OCC_COLORS, np.uint8)
    gap, legend_w = 10, 160
    out = Image.new("RGB", (len(panels) * (Y * scale + gap) + legend_w, X * scale + 18), (255, 255, 255))
    draw = ImageDraw.Draw(out)
    for p, label in enumerate(panels):
        rgb = colors[label][::-1, ::-1]                    # rows: x descending; cols: y descending
        img = Image.fromarray(np.ascontiguousarray(rgb)).resize((Y * scale, X * scale), Image.NEAREST)
        x0 = p * (Y * scale + gap)
        out.paste(img, (x0, 18))
        draw.text((x0 + 2, 3), "semantics" if p == 0 else "inside the mask", fill=(0, 0, 0))
        cx, cy = x0 + img.width // 2, 18 + img.height // 2
        draw.polygon([(cx, cy - 8), (cx - 5, cy + 6), (cx + 5, cy + 6)], fill=(255, 0, 0), outline=(0, 0, 0))
    lx = len(panels) * (Y * scale + gap)
    present = [int(v) for v in np.unique(panels[0]) if v != FREE_LABEL]
    for i, v in enumerate(present):
        y = 22 + i * 16
        draw.rectangle([lx + 8, y, lx + 20, y + 11], fill=tuple(OCC_COLORS[v]), outline=(0, 0, 0))
        draw.text((lx + 26, y), OCC_CLASSES[v], fill=(0, 0, 0))
    return out
