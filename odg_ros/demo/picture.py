"""demo.png: one keyframe's six cameras over the bird's-eye prediction and ground truth."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from .report import format_value


def pick_keyframe(scored: list[int], infos: list[dict]) -> int:
    """The scored keyframe nearest the middle of the scene (history frames are warm there)."""
    if not scored:
        raise ValueError("no scored keyframe to draw")
    middle = np.median([infos[i]["timestamp"] for i in range(len(infos))])
    return min(scored, key=lambda i: abs(infos[i]["timestamp"] - middle))


# columns the node publishes as unknown (-1 in ~/occupancy/bev): no camera sees them
UNKNOWN_COLOR = (40, 70, 110)


def bev_rgb(labels: np.ndarray, seen: np.ndarray | None = None,
            unknown: np.ndarray | None = None) -> np.ndarray:
    """Top view of a label grid uint8 [X, Y, Z] (17 = free) -> uint8 [X, Y, 3] image.

    Each column shows the class of its highest non-free voxel (classes.OCC_COLORS; white where
    the column is free). Rows run from +x (forward) at the top to -x, columns from +y (left)
    on the left to -y, so the picture looks like a map with the car driving up. ``seen``
    bool [X, Y, Z] (e.g. mask_camera): columns without a seen voxel are drawn darker.
    ``unknown`` bool [X, Y]: columns drawn in UNKNOWN_COLOR (the node's unknown space).
    """
    from ..classes import FREE_LABEL, OCC_COLORS

    labels = np.asarray(labels)
    occupied = labels != FREE_LABEL
    top = labels.shape[2] - 1 - np.argmax(occupied[:, :, ::-1], axis=2)          # [X, Y]
    label = np.where(occupied.any(axis=2),
                     np.take_along_axis(labels, top[..., None], axis=2)[..., 0], FREE_LABEL)
    rgb = np.asarray(OCC_COLORS, dtype=np.uint8)[label]
    if seen is not None:
        rgb = np.where(np.asarray(seen).any(axis=2)[..., None], rgb,
                       (rgb * 0.45).astype(np.uint8))
    if unknown is not None:
        rgb = np.where(np.asarray(unknown)[..., None], np.asarray(UNKNOWN_COLOR, np.uint8),
                       rgb)
    return np.ascontiguousarray(rgb[::-1, ::-1])


def unknown_columns(labels: np.ndarray, observed: np.ndarray) -> np.ndarray:
    """bool [X, Y]: the columns the node's ~/occupancy/bev marks unknown (-1) for this grid
    and observed mask, with its default height band."""
    from ..bev import bev_fields
    from ..model_config import load_preset
    from ..online.parameters import load_schema
    cfg, schema = load_preset("odg_cpu"), load_schema()
    fields = bev_fields(np.asarray(labels), cfg.pc_range, cfg.voxel_size,
                        schema["bev_min_z"].default, schema["bev_max_z"].default, cfg.labels,
                        np.asarray(observed))
    data = np.frombuffer(fields["data"], np.int8).reshape(fields["height"], fields["width"])
    return data.T == -1


def draw_demo_png(path, meta: dict, index: int, pred: np.ndarray, report: dict,
                  keyframe_miou: float | None, observed: np.ndarray | None = None) -> None:
    """demo.png: the six cameras of keyframe ``index`` over its BEV prediction (as the planner
    stand-in received it, its unknown space in UNKNOWN_COLOR where the node sent ``observed``)
    and BEV ground truth side by side (``bev_rgb``; darker columns: outside mask_camera, what
    the mIoU does not count), titled with the demo's numbers."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Patch
    from PIL import Image

    from ..classes import FREE_LABEL, OCC_CLASSES, OCC_COLORS
    from ..data.occ_io import load_occ
    from ..data.synth.pictures import MOSAIC_ORDER
    from ..metrics.score import resolve_occ_root

    info = meta["infos"][index]
    dataroot = Path(meta["dataroot"])
    gt, _, mask_camera = load_occ(resolve_occ_root(meta) / info["occ_path"], meta["dataset"])
    h, w = info["cams"]["CAM_FRONT"]["image_hw"]
    width = 13.0
    camera_row, bev_row = width / 3 * h / w, width / 2 * 0.9
    fig = plt.figure(figsize=(width, 2 * camera_row + bev_row + 2.2))
    grid = fig.add_gridspec(3, 6, height_ratios=[camera_row, camera_row, bev_row],
                            hspace=0.15, wspace=0.05)
    for row, names in enumerate(MOSAIC_ORDER):
        for column, name in enumerate(names):
            ax = fig.add_subplot(grid[row, 2 * column:2 * column + 2])
            with Image.open(dataroot / info["cams"][name]["data_path"]) as image:
                ax.imshow(image.convert("RGB"))
            ax.set_title(name, fontsize=8, pad=2)
            ax.axis("off")
    extent = (40.0, -40.0, -40.0, 40.0)      # lateral y: +40 (left) .. -40; forward x: -40 .. 40
    unknown = unknown_columns(pred, observed) if observed is not None else None
    for column, (picture, title) in enumerate([
            (bev_rgb(pred, unknown=unknown),
             f"prediction (from odg_node), this keyframe: mIoU "
             f"{format_value(keyframe_miou, '.1f')}"),
            (bev_rgb(gt, mask_camera), "ground truth (Occ3D layout)")]):
        ax = fig.add_subplot(grid[2, 3 * column:3 * column + 3])
        ax.imshow(picture, extent=extent, interpolation="nearest")
        ax.plot([0], [0], marker="^", color="red", markersize=8, markeredgecolor="black")
        ax.set_title(title, fontsize=10)
        ax.set_xlabel("y (m, left +)", fontsize=8)
        if column == 0:
            ax.set_ylabel("x (m, forward +)", fontsize=8)
        ax.tick_params(labelsize=7)
    present = sorted(set(np.unique(pred).tolist()) | set(np.unique(gt).tolist()) - {FREE_LABEL})
    handles = [Patch(facecolor=np.asarray(OCC_COLORS[c]) / 255, edgecolor="black",
                     label=OCC_CLASSES[c]) for c in present if c != FREE_LABEL]
    if unknown is not None:
        handles.append(Patch(facecolor=np.asarray(UNKNOWN_COLOR) / 255, edgecolor="black",
                             label="unknown (no camera sees it)"))
    fig.legend(handles=handles,
               loc="lower center", ncol=min(9, max(1, len(handles))), fontsize=8,
               frameon=False)
    t = (info["timestamp"] - meta["infos"][0]["timestamp"]) * 1e-6
    fig.suptitle(
        f"odg demo: mIoU {format_value(report['mIoU'])}  "
        f"RayIoU {format_value(report['RayIoU'])}  over "
        f"{report['keyframes_scored']} keyframes  |  {report['frames_out']} of "
        f"{report['frames_in']} camera sets out, FPS {format_value(report['fps'], '.1f')}, "
        f"latency p50 "
        f"{format_value(report['latency_ms_p50'], '.0f')} ms\n"
        f"keyframe {info['frame_index']} (t = {t:.1f} s); top views: per column the highest "
        "occupied voxel; prediction: unknown space as the node sends it, ground truth: darker "
        "= outside mask_camera", fontsize=11)
    fig.subplots_adjust(left=0.05, right=0.98, top=0.93, bottom=0.07)
    fig.savefig(path, dpi=100)
    plt.close(fig)
