"""What a planner reads, studied on held-out worlds of each scene class: the visibility's
precision / recall curve over ``visibility_min_clear`` (beside the ground-truth grid's
ceiling), the calibration error and reliability of the confidence and box scores before
(raw scores) and after the checkpoint's calibration, and label flips between consecutive
keyframes with and without a temporal filter (with the mIoU and RayIoU of each).

    OMP_NUM_THREADS=1 python -m tools.planner_study --checkpoint CALIBRATED.pt \\
        --data city-quiet=data/held_out/city-quiet/infos_all.pkl \\
        city-normal=data/held_out/city-normal/infos_all.pkl \\
        city-dense=data/held_out/city-dense/infos_all.pkl \\
        open-road=data/held_out/open-road/infos_all.pkl --out docs/results/planner

The model runs once per keyframe (as ``odg eval``: the grid padded, the history of the
dataset's earlier sets); every min_clear, filter and score reuses its output. Writes
OUT.json (every number), OUT.md (the tables), OUT_curve.png (precision against recall over
min_clear, per class) and OUT_reliability.png (reliability diagrams, per class).

The temporal filter (studied here, not in the node: docs/node.md says why): each voxel's
probability of being occupied (the calibrated confidence: its class's for an occupied
voxel, 1 - P(free) for a free one) is summed as log-odds over the last k outputs, each
carried into the current ego frame (nearest voxel, by the ego poses); occupied where the sum
is positive, with the class of the highest summed confidence; the moving classes (car,
pedestrian, ...) keep the current output's voxels.
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch

from odg_ros.classes import occ_labels
from odg_ros.data.dataset import OccDataset
from odg_ros.metrics.planner import (ConfidenceScore, FlipScore, VisibilityScore, bev_cells,
                                     carried_indices)
from odg_ros.metrics.rayiou import LidarOrigins
from odg_ros.metrics.score import OccScore
from odg_ros.network.calibration import Calibration
from odg_ros.network.checkpoint import load_model
from odg_ros.network.postprocess import box_list, stray_voxels
from odg_ros.network.visibility import DEFAULT_MIN_CLEAR, Visibility
from odg_ros.train.evaluate import BEV_BAND, PublishedGrid, padded_grid, predict_split

MIN_CLEARS = (0.0, 0.3, 0.5, 0.6, 0.7, 0.75, 0.8, 0.85, 0.9, 0.95)
FILTERS = (1, 2, 3)                   # outputs fused; 1: none


class TemporalFilter:
    """Log-odds of occupancy over the last ``k`` outputs of one drive (module docstring)."""

    def __init__(self, k: int, cfg):
        self.k, self.cfg = k, cfg
        labels = cfg.labels
        self.free = labels.free_label
        self.moving = np.zeros(256, bool)
        self.moving[[labels.names.index(n) for n in labels.dynamic]] = True
        self.history: list[dict] = []

    def __call__(self, scene, pose, grid, confidence) -> np.ndarray:
        """The filtered grid uint8 [X, Y, Z] of this output (grid, confidence 0..255)."""
        if self.history and self.history[-1]["scene"] != scene:
            self.history = []
        conf = confidence.ravel() / 255.0
        flat = grid.ravel()
        occupied = np.clip(np.where(flat != self.free, np.maximum(conf, 0.5), 1.0 - conf),
                           1e-3, 1 - 1e-3)
        now = {"scene": scene, "pose": pose, "grid": flat, "p": occupied, "c": conf}
        self.history = (self.history + [now])[-self.k:]
        if self.k == 1:
            return grid
        log_odds = np.log(occupied) - np.log1p(-occupied)
        votes = np.zeros((self.free, flat.size))
        at = np.arange(flat.size)
        static = flat != self.free
        votes[flat[static], at[static]] += conf[static]
        for before in self.history[:-1]:
            index, inside = carried_indices(before["pose"], pose, self.cfg.grid_shape,
                                            self.cfg.pc_range, self.cfg.voxel_size)
            p = before["p"][index]
            log_odds += np.where(inside, np.log(p) - np.log1p(-p), 0.0)
            label = before["grid"][index]
            use = inside & (label != self.free) & ~self.moving[label]
            votes[label[use], at[use]] += before["c"][index][use]
        fused = np.where(log_odds > 0, votes.argmax(0), self.free)
        fused = np.where((log_odds > 0) & (votes.max(0) == 0), flat, fused)
        fused = np.where(self.moving[flat], flat, fused)       # moving things: as output
        return fused.astype(np.uint8).reshape(grid.shape)


class ClassStudy:
    """Everything measured on one scene class."""

    def __init__(self, cfg, dataset: str, rayiou: bool):
        labels = self.labels = occ_labels(dataset)
        self.curve = {t: VisibilityScore() for t in MIN_CLEARS}
        self.truth = VisibilityScore()
        names = labels.names[:-1]
        self.raw, self.calibrated = ConfidenceScore(names), ConfidenceScore(names)
        self.flips = {k: FlipScore(labels) for k in FILTERS}
        self.scores = {k: OccScore(dataset, rayiou=rayiou) for k in FILTERS}
        self.filters = {k: TemporalFilter(k, cfg) for k in FILTERS}
        self.before = {k: None for k in FILTERS}
        self.keyframes = 0

    def result(self) -> dict:
        return {"keyframes": self.keyframes,
                "visibility": {str(t): s.result() for t, s in self.curve.items()},
                "ground_truth_grid": self.truth.result(),
                "confidence_raw": self.raw.result(),
                "confidence_calibrated": self.calibrated.result(),
                "stability": {str(k): {**self.flips[k].result(),
                                       **_occ(self.scores[k].result())} for k in FILTERS}}


def _occ(result: dict) -> dict:
    return {key: result.get(key) for key in ("mIoU", "RayIoU")}


def study(args) -> dict:
    model, cfg = load_model(args.checkpoint)
    if cfg.calibration is None:
        raise SystemExit(f"{args.checkpoint} has no calibration: odg export --calibrate")
    publish = PublishedGrid(cfg, "cpu", 0.0)
    calibration = Calibration(cfg)
    grid_args = (cfg.grid_shape, cfg.pc_range, cfg.voxel_size, cfg.num_classes)
    visibility = {t: Visibility(*grid_args, t) for t in MIN_CLEARS}
    band = (cfg.pc_range, cfg.voxel_size, BEV_BAND, cfg.labels)
    classes = {}
    for item in args.data:
        name, path = item.split("=", 1)
        dataset = OccDataset(path, cfg, train=False)
        origins = LidarOrigins(dataset.infos) if args.rayiou else None
        scores = classes[name] = ClassStudy(cfg, dataset.dataset, args.rayiou)
        for index, batch, output in predict_split(model, dataset, args.limit, desc=name):
            info = dataset.infos[index]
            if not batch["has_occ"][0]:
                continue
            scores.keyframes += 1
            geometry = publish.geometry(
                batch["ego2img"][0, 0].numpy(),
                [info["cams"][c]["image_hw"] for c in dataset.camera_names], cfg.image_size,
                "cpu")
            labels, raw = (t.reshape(-1) for t in padded_grid(output, cfg))
            confidence, hazard = calibration(labels, raw)
            stray = stray_voxels(output.last.means[:1], output.last.logits[:1], cfg)[0]
            grid = labels.view(cfg.grid_shape).numpy()
            truth = batch["occ_semantics"][0].numpy()
            mask = batch["occ_mask_camera"][0].numpy().astype(bool)
            truth_bev = bev_cells(truth, mask, *band)
            with torch.inference_mode():
                for t, v in visibility.items():
                    observed = v(labels, *geometry, hazard=hazard, stray=stray).view(cfg.grid_shape) \
                        .numpy().astype(bool)
                    scores.curve[t].add(grid, observed, truth, mask, cfg.num_classes,
                                        bev_cells(grid, observed, *band), truth_bev)
            truth_observed = publish.truth_observed(truth, geometry)
            scores.truth.add(truth, truth_observed, truth, mask, cfg.num_classes,
                             bev_cells(truth, truth_observed, *band), truth_bev)
            calibrated = confidence.view(cfg.grid_shape).numpy()
            scores.raw.add(grid, raw.view(cfg.grid_shape).numpy(), truth, mask,
                           cfg.num_classes)
            scores.calibrated.add(grid, calibrated, truth, mask, cfg.num_classes)
            boxes = box_list(output, cfg)[0]
            gt = (batch["gt_boxes"][0].numpy(), batch["gt_labels"][0].numpy())
            scores.raw.add_boxes(boxes, *gt)
            mapped = calibration.box_score(torch.tensor([b["score"] for b in boxes]))
            scores.calibrated.add_boxes([{**b, "score": float(s)} for b, s in
                                         zip(boxes, mapped)], *gt)
            pose = np.asarray(info["ego_pose"], np.float64)
            for k in FILTERS:
                fused = scores.filters[k](info["scene_token"], pose, grid, calibrated)
                now = {"scene": info["scene_token"], "grid": fused, "truth": truth,
                       "mask": mask, "pose": pose}
                before = scores.before[k]
                if before is not None and before["scene"] == now["scene"]:
                    scores.flips[k].add(before, now, cfg.grid_shape, cfg.pc_range,
                                        cfg.voxel_size)
                scores.before[k] = now
                scores.scores[k].add(fused, truth, mask,
                                     origins(index) if origins is not None else None)
    return {"checkpoint": str(args.checkpoint), "date": time.strftime("%Y-%m-%d"),
            "min_clear_default": DEFAULT_MIN_CLEAR, "bev_band": list(BEV_BAND),
            "classes": {name: s.result() for name, s in classes.items()},
            "all": merged(classes)}


def merged(classes: dict) -> dict:
    """The classes' counts together (visibility, flips; calibration by re-adding bins)."""
    first = next(iter(classes.values()))
    out = ClassStudy.__new__(ClassStudy)
    out.keyframes = sum(c.keyframes for c in classes.values())
    out.curve = {t: VisibilityScore() for t in first.curve}
    out.truth = VisibilityScore()
    for c in classes.values():
        for t in out.curve:
            out.curve[t].counts += c.curve[t].counts
        out.truth.counts += c.truth.counts
    out.raw, out.calibrated = (ConfidenceScore(first.raw.names) for _ in range(2))
    for c in classes.values():
        for mine, theirs in ((out.raw, c.raw), (out.calibrated, c.calibrated)):
            for part in ("occupied", "free", "boxes"):
                a, b = getattr(mine, part), getattr(theirs, part)
                a.count += b.count
                a.confidence += b.confidence
                a.right += b.right
            for name, r in theirs.per_class.items():
                mine.per_class[name].count += r.count
                mine.per_class[name].confidence += r.confidence
                mine.per_class[name].right += r.right
    out.flips = {k: FlipScore(first.labels) for k in first.flips}
    for k in out.flips:
        for c in classes.values():
            out.flips[k].counts += c.flips[k].counts
            out.flips[k].pairs += c.flips[k].pairs
    out.scores = {k: first.scores[k] for k in first.scores}
    for k in out.scores:
        combined = OccScore(first.scores[k].dataset, rayiou=first.scores[k].rayiou is not None)
        for c in classes.values():
            combined.merge(c.scores[k])
        out.scores[k] = combined
    return out.result()


def tables(report: dict) -> str:
    """The markdown tables of a report."""
    rows = list(report["classes"].items()) + [("all", report["all"])]
    default = str(report["min_clear_default"])
    lines = [f"Held-out worlds, {report['all']['keyframes']} keyframes; checkpoint "
             f"{report['checkpoint']}; {report['date']}.", "",
             f"### Visibility at the default `visibility_min_clear` {default}, before (0: "
             "the predicted surfaces alone) and the ground-truth grid's ceiling", "",
             "| scene class | observed P / R | free and observed P | BEV known P / R | "
             "BEV free P | before: observed P / R, free+obs P | ground-truth grid: observed "
             "P / R, free+obs P |", "|---|---|---|---|---|---|---|"]
    for name, r in rows:
        m, b, t = r["visibility"][default], r["visibility"]["0.0"], r["ground_truth_grid"]
        lines.append(
            f"| {name} | {_f(m['voxels']['observed_precision'])} / "
            f"{_f(m['voxels']['observed_recall'])} | "
            f"{_f(m['voxels']['free_observed_precision'])} | "
            f"{_f(m['bev']['known_precision'])} / {_f(m['bev']['known_recall'])} | "
            f"{_f(m['bev']['free_precision'])} | {_f(b['voxels']['observed_precision'])} / "
            f"{_f(b['voxels']['observed_recall'])}, "
            f"{_f(b['voxels']['free_observed_precision'])} | "
            f"{_f(t['voxels']['observed_precision'])} / {_f(t['voxels']['observed_recall'])}, "
            f"{_f(t['voxels']['free_observed_precision'])} |")
    lines += ["", "### The curve over `visibility_min_clear` (observed precision / recall, "
              "free and observed precision)", "",
              "| min_clear | " + " | ".join(name for name, _ in rows) + " |",
              "|---|" + "---|" * len(rows)]
    for t in report["all"]["visibility"]:
        cells = []
        for _, r in rows:
            v = r["visibility"][t]["voxels"]
            cells.append(f"{_f(v['observed_precision'])} / {_f(v['observed_recall'])}, "
                         f"{_f(v['free_observed_precision'])}")
        lines.append(f"| {t} | " + " | ".join(cells) + " |")
    lines += ["", "### Expected calibration error (10 bins; inside mask_camera), raw scores "
              "-> calibrated", "", "| scene class | occupied voxels | free voxels | boxes |",
              "|---|---|---|---|"]
    for name, r in rows:
        a, b = r["confidence_raw"], r["confidence_calibrated"]
        lines.append(f"| {name} | " + " | ".join(
            f"{_f(a[p]['ece'])} -> {_f(b[p]['ece'])}" for p in ("occupied", "free", "boxes"))
            + " |")
    lines += ["", "### Label flips between consecutive keyframes (static voxels) and the "
              "temporal filter over k outputs", "",
              "| scene class | " + " | ".join(f"k = {k}: flips (occupied), mIoU, RayIoU"
                                              for k in FILTERS) + " |",
              "|---|" + "---|" * len(FILTERS)]
    for name, r in rows:
        cells = []
        for k in FILTERS:
            s = r["stability"][str(k)]
            cells.append(f"{_pct(s['flip_rate'])} ({_pct(s['flip_rate_occupied'])}), "
                         f"{_f(s['mIoU'], 2)}, {_f(s['RayIoU'], 2)}")
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def _f(value, digits=3) -> str:
    return "-" if value is None else f"{value:.{digits}f}"


def _pct(value) -> str:
    return "-" if value is None else f"{100 * value:.2f} %"


def plots(report: dict, out: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    rows = list(report["classes"].items()) + [("all", report["all"])]
    default = str(report["min_clear_default"])
    fig, axes = plt.subplots(1, 2, figsize=(13, 5.2))
    for (name, r), colour in zip(rows, plt.get_cmap("tab10").colors):
        for ax, key in zip(axes, ("observed_precision", "free_observed_precision")):
            recall = [r["visibility"][t]["voxels"]["observed_recall"] for t in r["visibility"]]
            value = [r["visibility"][t]["voxels"][key] for t in r["visibility"]]
            ax.plot(recall, value, "-o", ms=3, color=colour, label=name,
                    lw=2.5 if name == "all" else 1.2)
            at = list(r["visibility"]).index(default)
            ax.plot(recall[at], value[at], "*", ms=12, color=colour)
            truth = r["ground_truth_grid"]["voxels"]
            ax.plot(truth["observed_recall"], truth[key], "s", ms=7, mfc="none", color=colour)
    for ax, title in zip(axes, ("precision of 'observed'", "precision of 'free and observed'")):
        ax.set_xlabel("recall of 'observed' (against mask_camera)")
        ax.set_ylabel(title)
        ax.axhline(0.9 if "free" not in title else 0.95, color="grey", ls=":", lw=1)
        ax.axvline(0.6, color="grey", ls=":", lw=1)
        ax.grid(alpha=0.3)
    axes[0].legend(title="scene class", fontsize=8)
    fig.suptitle(f"visibility_min_clear from 0 (right) to 0.95 (left); star: the default "
                 f"{default}; square: the ground-truth grid (the method's ceiling); "
                 f"{report['all']['keyframes']} held-out keyframes", fontsize=9)
    fig.tight_layout()
    fig.savefig(str(out) + "_curve.png", dpi=110)
    plt.close(fig)

    fig, axes = plt.subplots(1, len(rows), figsize=(3.3 * len(rows), 3.6), sharey=True)
    for ax, (name, r) in zip(axes, rows):
        for key, style, label in (("confidence_raw", ":", "raw"),
                                  ("confidence_calibrated", "-", "calibrated")):
            for part, colour in (("occupied", "tab:red"), ("boxes", "tab:blue")):
                bins = r[key][part]["bins"]
                xs = [c for c, a in zip(bins["confidence"], bins["accuracy"]) if c is not None]
                ys = [a for c, a in zip(bins["confidence"], bins["accuracy"]) if c is not None]
                ax.plot(xs, ys, style, marker="o", ms=3, color=colour,
                        label=f"{part} {label} (ECE {_f(r[key][part]['ece'])})")
        ax.plot([0, 1], [0, 1], color="grey", lw=0.8)
        ax.set_title(name, fontsize=9)
        ax.set_xlabel("stated confidence")
        ax.legend(fontsize=6)
    axes[0].set_ylabel("share right")
    fig.suptitle("reliability: occupied voxels (right class) and boxes (right class within "
                 "2 m), raw scores dotted, calibrated solid", fontsize=9)
    fig.tight_layout()
    fig.savefig(str(out) + "_reliability.png", dpi=110)
    plt.close(fig)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--checkpoint", required=True, help="a calibrated checkpoint")
    parser.add_argument("--data", required=True, nargs="+", metavar="CLASS=INFOS")
    parser.add_argument("--out", required=True, help="path prefix of the results")
    parser.add_argument("--limit", type=int, default=None, help="first N keyframes per class")
    parser.add_argument("--no-rayiou", dest="rayiou", action="store_false")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    report = study(args)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    Path(str(out) + ".json").write_text(json.dumps(report, indent=1))
    Path(str(out) + ".md").write_text(tables(report))
    plots(report, out)
    print(tables(report))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
