"""The sweep's picture: FPS against mIoU and RayIoU with the Pareto front, and where each
configuration's time goes (backbone, each decoder layer, post-processing)."""
from __future__ import annotations

import numpy as np

# the least span of a plot's axis: FPS from 0 always; a score axis at least this many points
# (two configurations 0.001 FPS or 0.01 mIoU apart must not fill a whole axis)
SCORE_SPAN = 2.0


def axis_limits(values, least_span: float, from_zero: bool = False,
                margin: float = 0.12) -> tuple[float, float]:
    """(low, high) of an axis showing ``values``: spanning at least ``least_span`` (centred
    on the values), or from 0 where ``from_zero``, with a ``margin`` of the span beyond;
    never below 0 for values that are not (scores, rates)."""
    values = [v for v in values if v is not None and np.isfinite(v)]
    low, high = (min(values), max(values)) if values else (0.0, 1.0)
    if from_zero:
        low = min(low, 0.0)
        return low, low + max(high - low, least_span) * (1 + margin)
    span = max(high - low, least_span)
    middle = (low + high) / 2
    bottom = middle - span * (0.5 + margin)
    return max(bottom, 0.0) if low >= 0 else bottom, middle + span * (0.5 + margin)


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
    ax.set_xlim(*axis_limits([r["fps"] for r in ok], 1e-3, from_zero=True))
    ax.set_ylim(*axis_limits([r["scores"].get(metric) for r in ok], SCORE_SPAN))
    if xs:
        order = np.argsort(xs)
        ax.plot(np.array(xs)[order], np.array(ys)[order], "--", color="tab:red",
                label="Pareto front", zorder=2)
    ax.legend(loc="best", fontsize=7, ncol=2)
    ax.set_xlabel("FPS (the node's step per camera set)")
    ax.set_ylabel(f"{metric} (%)")
    ax.grid(alpha=0.3)
    ax.set_title(f"FPS vs {metric} ({meta['samples']} samples)", fontsize=9)


def latency_segments(r: dict) -> dict[str, float]:
    """One configuration's step (ms) split for the bars: backbone, each decoder layer, the
    decoder outside the layers, post-processing (grid, padding, boxes, visibility) and the
    rest of the step (host: packing, copies, results into Python); a step without marks
    (compiled, graphs) as its device part and the rest."""
    lat = r["latency_ms"]
    if "decoder" not in lat:
        return {"device step (no marks)": lat["model"],
                "host": max(lat["step"] - lat["model"], 0.0)}
    segments = {"backbone": lat["backbone"]}
    segments.update({f"layer{row['layer']}": row["total"] for row in r["decoder_layers_ms"]})
    segments["decoder outside layers"] = lat.get("decoder_outside_layers", lat["decoder"]) \
        if r["decoder_layers_ms"] else lat["decoder"]
    segments["postprocess"] = lat["postprocess"]
    segments["host"] = max(lat["step"] - lat["backbone"] - lat["decoder"]
                           - lat["postprocess"], 0.0)
    return segments


def _plot_latency_split(ax, ok: list[dict]) -> None:
    """Stacked bars of ``latency_segments``: one colour per segment, in the order of the step."""
    import matplotlib.pyplot as plt

    names = [r["config"]["name"] for r in ok]
    split = [latency_segments(r) for r in ok]
    num_layers = max((len(r["decoder_layers_ms"]) for r in ok), default=0)
    cmap = plt.get_cmap("viridis")
    colours = {"backbone": "tab:gray", "device step (no marks)": "tab:purple",
               **{f"layer{i + 1}": cmap(i / max(1, num_layers - 1)) for i in range(num_layers)},
               "decoder outside layers": "tab:orange", "postprocess": "tab:brown",
               "host": "tab:olive"}
    left = np.zeros(len(ok))
    for label, colour in colours.items():
        widths = np.array([segments.get(label, 0.0) for segments in split])
        if not widths.any():
            continue
        ax.barh(names, widths, left=left, color=colour, label=label, height=0.7)
        left += widths
    ax.invert_yaxis()
    ax.set_xlabel("median ms per step (split: the step's marks, eager steps)")
    ax.legend(fontsize=7, ncol=5, loc="upper center", bbox_to_anchor=(0.5, -0.12))
    ax.grid(axis="x", alpha=0.3)
    ax.set_title("where the time goes (decoder per layer)", fontsize=9)
