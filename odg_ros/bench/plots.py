"""The sweep's picture: FPS against mIoU and RayIoU with the Pareto front, and where each
configuration's time goes (backbone, each decoder layer, post-processing)."""
from __future__ import annotations

import numpy as np


def plot_sweep(report: dict, path) -> None:
    """PNG: FPS against mIoU and against RayIoU (Pareto front as a line), and the latency
    of each configuration split into backbone, decoder layers, decoder outside layers, post."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    meta = report["meta"]
    ok = [r for r in report["configs"] if "error" not in r]
    fig, axes = plt.subplots(1, 3, figsize=(19, 6.2),
                             gridspec_kw={"width_ratios": [1, 1, 1.25]})
    # one colour per configuration (a legend instead of labels next to the points: nearby
    # configurations' labels overlap); the Pareto front gets a black edge and the line
    # (tab20's dark shades first: 10 distinct hues before any light twin)
    colours = {r["config"]["name"]: plt.get_cmap("tab20")((2 * i) % 20 + (i // 10) % 2)
               for i, r in enumerate(ok)}
    for ax, metric in zip(axes[:2], ("mIoU", "RayIoU")):
        _plot_speed_against(ax, metric, report, ok, colours)
    _plot_latency_split(axes[2], ok)
    weights = ("RANDOM WEIGHTS (no trained checkpoint): the scores are meaningless"
               if meta["random_weights"] else f"checkpoint {meta['checkpoint']}")
    fig.suptitle(
        f"odg bench --sweep: {meta['preset']} on {meta['device_name']}, "
        f"{meta['threads']} threads, torch {meta['torch']} | {meta['date']} | "
        f"commit {meta['commit']}\n{weights} | data {meta['data']} | median of "
        f"{meta['repeats']} runs per sample after {meta['warmup']} warm-up | load average "
        f"{meta['load_average_before'][0]:.1f} -> {meta['load_average_after'][0]:.1f}",
        fontsize=9, color="darkred" if meta["random_weights"] else "black")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _plot_speed_against(ax, metric: str, report: dict, ok: list[dict], colours: dict) -> None:
    """One configuration a point (FPS, ``metric``); the Pareto front as a dashed line."""
    meta = report["meta"]
    front = set(report["pareto"].get(metric, []))
    xs, ys = [], []
    for r in ok:
        value = r["scores"].get(metric)
        if value is None:
            continue
        name = r["config"]["name"]
        on_front = name in front
        marker, label = "o", name + (" (Pareto front)" if on_front else "")
        if r.get("random_weights") and not meta["random_weights"]:
            marker, label = "x", label + " (random weights)"
        ax.scatter(r["fps"], value, s=110 if on_front else 55, zorder=3, marker=marker,
                   color=colours[name], edgecolors="black" if on_front else None,
                   linewidths=1.2, label=label)
        if on_front:
            xs.append(r["fps"])
            ys.append(value)
    ax.margins(x=0.12, y=0.12)
    if xs:
        order = np.argsort(xs)
        ax.plot(np.array(xs)[order], np.array(ys)[order], "--", color="tab:red",
                label="Pareto front", zorder=2)
    ax.legend(loc="best", fontsize=7, ncol=2)
    ax.set_xlabel("FPS (online step: backbone + decoder + post-processing)")
    ax.set_ylabel(f"{metric} (%)")
    ax.grid(alpha=0.3)
    ax.set_title(f"FPS vs {metric} ({meta['samples']} samples)", fontsize=9)


def _plot_latency_split(ax, ok: list[dict]) -> None:
    """Stacked bars: backbone, decoder layer by layer, decoder outside layers, postprocess."""
    import matplotlib.pyplot as plt

    names = [r["config"]["name"] for r in ok]
    left = np.zeros(len(ok))
    segments = [("backbone", "tab:gray")]
    num_layers = max((len(r["decoder_layers_ms"]) for r in ok), default=0)
    cmap = plt.get_cmap("viridis")
    for i in range(num_layers):
        segments.append((f"layer{i + 1}", cmap(i / max(1, num_layers - 1))))
    segments += [("decoder outside layers", "tab:orange"), ("postprocess", "tab:brown")]
    for label, colour in segments:
        widths = []
        for r in ok:
            lat = r["latency_ms"]
            if label == "backbone":
                widths.append(lat["backbone"])
            elif label == "postprocess":
                widths.append(lat["postprocess"])
            elif label == "decoder outside layers":
                widths.append(lat.get("decoder_outside_layers",
                                      lat["decoder"] if not r["decoder_layers_ms"] else 0.0))
            else:
                index = int(label[5:])
                row = next((x for x in r["decoder_layers_ms"] if x["layer"] == index), None)
                widths.append(row["total"] if row else 0.0)
        widths = np.maximum(np.array(widths), 0.0)
        ax.barh(names, widths, left=left, color=colour, label=label, height=0.7)
        left += widths
    ax.invert_yaxis()
    ax.set_xlabel("median latency per online step (ms)")
    ax.legend(fontsize=7, ncol=5, loc="upper center", bbox_to_anchor=(0.5, -0.12))
    ax.grid(axis="x", alpha=0.3)
    ax.set_title("where the time goes (decoder per layer)", fontsize=9)
