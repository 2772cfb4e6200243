"""Scoring a split: mIoU + geometry IoU + RayIoU together, the infos/GT/prediction files they
read, and the report (table or JSON). Used by ``odg score`` and ``odg eval``.

Where the GT lives (``resolve_occ_root``): an explicit ``--occ-root``; else the infos' optional
``"occ_root"`` key (a relative one is taken relative to ``dataroot``); else ``<dataroot>/gts``
(the Occ3D-nuScenes layout). Each keyframe's ``occ_path`` is relative to that root.

Predictions on disk: ``<pred_dir>/<sample_token>.npz`` with key ``semantics``, an integer
[X, Y, Z] grid (uint8 200 x 200 x 16) of labels 0..C, C = free (17 nuScenes, 15 Waymo).
"""
from __future__ import annotations

import math
import pickle
from pathlib import Path

import numpy as np

from ..classes import LABEL_SETS
from .miou import MIOU_CONVENTIONS, MIoU, check_labels
from .rayiou import RayIoU

DATASETS = {name: labels.names for name, labels in LABEL_SETS.items()}  # names incl. free (last)
MIOU_NOTES = {
    "sparseocc": "sparseocc (SparseOcc / OPUS: a class absent from the GT is left out; "
                 "--miou-convention occ3d counts it as 0 where predicted)",
    "occ3d": "occ3d (Occ3D Metric_mIoU: a class absent from the GT counts as 0 where predicted; "
             "--miou-convention sparseocc leaves it out)",
}
assert set(MIOU_NOTES) == set(MIOU_CONVENTIONS)


def class_names(dataset: str) -> tuple[str, ...]:
    """Semantic class names (without free) of ``dataset``."""
    if dataset not in DATASETS:
        raise ValueError(f"unknown dataset {dataset!r} (expected one of {sorted(DATASETS)})")
    return DATASETS[dataset][:-1]


def load_scoring_infos(path) -> dict:
    """The infos pickle (``odg_ros/data/batch.py``), checked for the keys scoring needs."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"infos file not found: {path}")
    with open(path, "rb") as f:
        meta = pickle.load(f)
    if not isinstance(meta, dict) or "infos" not in meta:
        raise ValueError(f"{path}: not an infos file (expected a dict with an 'infos' list)")
    meta.setdefault("dataset", "nuscenes")
    class_names(meta["dataset"])
    for i, info in enumerate(meta["infos"]):
        missing = [k for k in ("token", "scene_token", "timestamp", "ego_pose", "lidar2ego",
                               "occ_path") if k not in info]
        if missing:
            raise ValueError(f"{path}: keyframe {i} ({info.get('token', '?')}) lacks {missing}")
    return meta


def resolve_occ_root(meta: dict, override=None) -> Path:
    """The directory the keyframes' ``occ_path`` are relative to (see the module docstring)."""
    if override is not None:
        return Path(override)
    dataroot = Path(meta.get("dataroot", "."))
    if meta.get("occ_root"):
        return dataroot / meta["occ_root"]  # an absolute occ_root replaces dataroot
    return dataroot / "gts"


def load_prediction(path, shape, free_label: int) -> np.ndarray:
    """``<token>.npz`` -> integer labels [X, Y, Z]; a clear error for anything else."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"prediction missing: {path}")
    with np.load(path, allow_pickle=False) as data:
        if "semantics" not in data.files:
            raise ValueError(f"{path}: no 'semantics' array (has {sorted(data.files)})")
        pred = np.asarray(data["semantics"])
    if pred.shape != tuple(shape):
        raise ValueError(f"{path}: semantics shape {pred.shape}, expected {tuple(shape)}")
    return check_labels(str(path), pred, free_label)


class OccScore:
    """mIoU (camera mask) + geometry IoU + RayIoU (no mask) of one split, streamed."""

    def __init__(self, dataset: str = "nuscenes", rayiou: bool = True,
                 miou_convention: str = "sparseocc"):
        """miou_convention: "sparseocc" (a class absent from the GT is left out of the mean)
        or "occ3d" (such a class, when predicted, counts with IoU 0); see metrics/miou.py."""
        self.dataset = dataset
        self.names = class_names(dataset)
        self.num_classes = len(self.names)
        self.free_label = self.num_classes
        self.miou = MIoU(self.num_classes, miou_convention)
        self.rayiou = RayIoU(self.num_classes) if rayiou else None

    def add(self, pred, gt, mask_camera, origins=None) -> None:
        """pred, gt: int [X, Y, Z] labels 0..C; mask_camera: bool [X, Y, Z]; origins: [T, 3]
        metres (``LidarOrigins``), needed when RayIoU is on."""
        self.miou.add(pred, gt, mask_camera)
        if self.rayiou is not None:
            if origins is None:
                raise ValueError("RayIoU needs the sample's LiDAR origins")
            self.rayiou.add(pred, gt, origins)

    def merge(self, other: "OccScore") -> None:
        """Add the keyframes ``other`` scored (the same dataset, convention and RayIoU on or
        off) to this score, as if they had been added here."""
        self.miou.confusion += other.miou.confusion
        self.miou.samples += other.miou.samples
        if self.rayiou is not None:
            for name in ("gt_count", "pred_count", "tp_count"):
                setattr(self.rayiou, name, getattr(self.rayiou, name)
                        + getattr(other.rayiou, name))
            self.rayiou.samples += other.rayiou.samples
            self.rayiou.rays += other.rayiou.rays

    def result(self) -> dict:
        """Report in percent (0..100), NaN as None (JSON null)::

            {"mIoU", "mIoU_convention", "RayIoU", "RayIoU@1", "RayIoU@2", "RayIoU@4",
             "IoU_geometry", "samples",
             "per_class": {name: {"IoU", "RayIoU", "RayIoU@1", "RayIoU@2", "RayIoU@4"}}}
        """
        m = self.miou.result()
        out = {"mIoU": _pct(m["mIoU"]), "mIoU_convention": m["convention"]}
        per_class = {name: {"IoU": _pct(v)} for name, v in zip(self.names, m["per_class"])}
        if self.rayiou is not None:
            r = self.rayiou.result()
            out["RayIoU"] = _pct(r["RayIoU"])
            for j, t in enumerate(self.rayiou.thresholds):
                out[f"RayIoU@{t:g}"] = _pct(r[f"RayIoU@{t:g}"])
            for c, name in enumerate(self.names):
                per_class[name]["RayIoU"] = _pct(r["per_class"][c])
                for j, t in enumerate(self.rayiou.thresholds):
                    per_class[name][f"RayIoU@{t:g}"] = _pct(r["per_class_at"][j, c])
        out["IoU_geometry"] = _pct(m["IoU_geometry"])
        out["samples"] = m["samples"]
        out["per_class"] = per_class
        return out


def format_table(result: dict) -> str:
    """The per-class table of an ``OccScore.result()`` (percent, '-' for NaN)."""
    ray_keys = [k for k in ("RayIoU", "RayIoU@1", "RayIoU@2", "RayIoU@4")
                if k in next(iter(result["per_class"].values()), {})]
    header = ["class", "IoU"] + ray_keys
    rows = [[name] + [values.get(k) for k in header[1:]]
            for name, values in result["per_class"].items()]
    rows.append(["MEAN"] + [result.get("mIoU")] + [result.get(k) for k in ray_keys])
    width = max(len(r[0]) for r in rows + [header])
    cell = lambda v: "-" if v is None else f"{v:.2f}"  # noqa: E731
    lines = [f"{header[0]:<{width}}  " + "  ".join(f"{h:>8}" for h in header[1:])]
    for i, row in enumerate(rows):
        if i == len(rows) - 1:
            lines.append("-" * len(lines[0]))
        lines.append(f"{row[0]:<{width}}  " + "  ".join(f"{cell(v):>8}" for v in row[1:]))
    lines.append(f"geometry IoU (occupied vs free, camera mask): {cell(result['IoU_geometry'])}")
    if "mIoU_convention" in result:
        lines.append(f"mIoU convention: {MIOU_NOTES[result['mIoU_convention']]}")
    lines.append(f"samples: {result['samples']}")
    return "\n".join(lines)


def plot_per_class(result: dict, path) -> None:
    """Bar chart PNG of an ``OccScore.result()``: per-class IoU and RayIoU ("n/a" marks classes
    absent from the split), the means in the title."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(result["per_class"])
    series = [("IoU", "voxel IoU (camera mask)")]
    if "RayIoU" in result:
        series.append(("RayIoU", "RayIoU (mean of 1/2/4 m)"))
    x = np.arange(len(names))
    width = 0.8 / len(series)
    fig, ax = plt.subplots(figsize=(max(8.0, 0.55 * len(names)), 4.5))
    for k, (key, label) in enumerate(series):
        values = [result["per_class"][n].get(key) for n in names]
        ax.bar(x + (k - (len(series) - 1) / 2) * width,
               [np.nan if v is None else v for v in values], width, label=label)
    title = [f"mIoU {_fmt(result['mIoU'])}"]
    if "RayIoU" in result:
        title.append(f"RayIoU {_fmt(result['RayIoU'])}")
    title.append(f"geometry IoU {_fmt(result['IoU_geometry'])}")
    title.append(f"{result['samples']} samples")
    ax.set_title(" | ".join(title))
    ax.set_xticks(x, names, rotation=45, ha="right")
    ax.set_ylabel("%")
    for i, n in enumerate(names):
        if all(result["per_class"][n].get(key) is None for key, _ in series):
            ax.text(i, 1, "n/a", ha="center", va="bottom", fontsize=8, color="grey")
    ax.set_ylim(0, 115)
    ax.set_yticks(range(0, 101, 20))
    ax.grid(axis="y", alpha=0.3)
    ax.legend(loc="upper center", ncol=len(series), frameon=False)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _fmt(value) -> str:
    return "-" if value is None else f"{value:.2f}"


def _pct(value) -> float | None:
    value = float(value)
    return None if math.isnan(value) else 100.0 * value
