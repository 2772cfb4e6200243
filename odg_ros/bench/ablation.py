"""The paper's Table 4 on our data: variants side by side, against the full model's seed spread.

``odg ablation --out docs/results/ablation full=runs/a/eval.json full=runs/b/eval.json
no_render=runs/c/eval.json ...`` reads ``odg eval --json`` results (a name may repeat: one
file per training seed), writes ``<out>.json``, ``<out>.md`` (one row per variant: the mean
over its seeds, the change against the first variant's mean) and ``<out>.png`` (the changes,
with the first variant's own seed-to-seed range drawn as the band a change must leave before
it says anything).
"""
from __future__ import annotations

import json
import math
from pathlib import Path

METRICS = (("mIoU", "mIoU"), ("RayIoU", "RayIoU"), ("RayIoU@1", "@1"), ("RayIoU@2", "@2"),
           ("RayIoU@4", "@4"), ("IoU_geometry", "geometry"), ("mIoU_dynamic", "mIoU dyn."),
           ("box_mAP", "box mAP"))


def metric_values(result: dict) -> dict[str, float | None]:
    """The compared numbers of one ``odg eval --json`` result (percent; None where absent)."""
    values = {key: result.get(key) for key, _ in METRICS if key != "box_mAP"}
    values["box_mAP"] = (result.get("boxes") or {}).get("mAP")
    return values


def _mean(values: list) -> float | None:
    present = [v for v in values if v is not None and not math.isnan(v)]
    return sum(present) / len(present) if present else None


def summarize_ablation(runs: list[tuple[str, dict]]) -> dict:
    """runs: (variant, eval result) in order, the first variant is the reference. ->
    {"reference", "variants": [{"name", "seeds", "mean": {metric}, "delta": {metric},
    "range": {metric: [min, max]}}]}; a variant's delta is its mean minus the reference's."""
    if not runs:
        raise ValueError("no results to compare")
    grouped: dict[str, list[dict]] = {}
    for name, result in runs:
        grouped.setdefault(name, []).append(metric_values(result))
    variants = []
    for name, seeds in grouped.items():
        mean = {key: _mean([s[key] for s in seeds]) for key, _ in METRICS}
        present = {key: [s[key] for s in seeds if s[key] is not None] for key, _ in METRICS}
        variants.append({"name": name, "seeds": len(seeds), "mean": mean,
                         "range": {k: [min(v), max(v)] if v else None
                                   for k, v in present.items()}})
    reference = variants[0]
    for variant in variants:
        variant["delta"] = {key: None if variant["mean"][key] is None
                            or reference["mean"][key] is None
                            else variant["mean"][key] - reference["mean"][key]
                            for key, _ in METRICS}
    return {"reference": reference["name"], "variants": variants}


def ablation_table(summary: dict) -> str:
    cell = lambda v: "-" if v is None else f"{v:.2f}"  # noqa: E731
    signed = lambda v: "" if v is None else f" ({v:+.2f})"  # noqa: E731
    lines = ["| variant | seeds | " + " | ".join(label for _, label in METRICS) + " |",
             "|---|---|" + "---|" * len(METRICS)]
    for i, variant in enumerate(summary["variants"]):
        cells = [cell(variant["mean"][key]) + ("" if i == 0 else signed(variant["delta"][key]))
                 for key, _ in METRICS]
        lines.append(f"| {variant['name']} | {variant['seeds']} | " + " | ".join(cells) + " |")
    reference = summary["variants"][0]
    if reference["seeds"] > 1:
        spread = ", ".join(f"{label} {reference['range'][key][1] - reference['range'][key][0]:.2f}"
                           for key, label in METRICS if reference["range"][key] is not None)
        lines.append("")
        lines.append(f"Seed-to-seed range of {reference['name']} ({reference['seeds']} seeds): "
                     f"{spread}.")
    return "\n".join(lines) + "\n"


def plot_ablation(summary: dict, path: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    reference, others = summary["variants"][0], summary["variants"][1:]
    keys = [key for key, _ in METRICS if reference["mean"][key] is not None]
    labels = dict(METRICS)
    fig, axes = plt.subplots(1, len(keys), figsize=(2.2 * len(keys), 3.4), squeeze=False)
    axes = axes[0]
    for ax, key in zip(axes, keys):
        low, high = reference["range"][key]
        ax.axhspan(low - reference["mean"][key], high - reference["mean"][key], color="0.85",
                   label=f"{reference['name']} seed range")
        deltas = [v["delta"][key] if v["delta"][key] is not None else 0.0 for v in others]
        ax.bar(range(len(others)), deltas,
               color=["tab:red" if d < 0 else "tab:green" for d in deltas])
        ax.axhline(0.0, color="k", lw=0.8)
        ax.set_xticks(range(len(others)), [v["name"] for v in others], rotation=60, ha="right",
                      fontsize=8)
        ax.set_title(f"{labels[key]} ({reference['mean'][key]:.2f})", fontsize=9)
    axes[0].set_ylabel(f"change vs {reference['name']} (points)")
    axes[0].legend(fontsize=7, loc="lower left")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def write_ablation(summary: dict, out: Path) -> None:
    """``<out>.json``, ``<out>.md`` and ``<out>.png`` of a summary."""
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".json").write_text(json.dumps(summary, indent=2) + "\n")
    out.with_suffix(".md").write_text(ablation_table(summary))
    plot_ablation(summary, out.with_suffix(".png"))
