"""Speed against error of the query budgets, per scene class: mIoU and RayIoU (from
``budget_accuracy``, ``python -m tools.eval_budget``) against the decoder's time relative to
the full budget (from ``budget_cost``, ``python -m tools.profile_budget``, the budgets and the fixed smaller query sets timed side by side).

The learned budgets, ``auto`` and the fixed smaller query sets are plotted; a random or
best-score ranking costs what its budget costs (same x). ``auto``'s cost is interpolated
from the share of the queries it refined, between the rungs' measured costs. ``python -m tools.plot_budget`` draws it.
"""
from __future__ import annotations

import numpy as np

MARKERS = {"learned budgets": ("o-", "keep-"), "random ranking": ("x", "random-"),
           "best-score ranking": ("+", "pointscore-"), "fixed smaller sets": ("s--", "q")}


def costs(profile: dict) -> dict[str, float]:
    """Configuration name of eval_budget -> decoder time relative to the full budget."""
    cost = {"full": 1.0}
    for row in profile["budgets"][1:]:
        for prefix in ("keep-", "random-", "pointscore-"):
            cost[prefix + row["budget"]] = row["decoder_vs_full"]
    cost.update({row["fixed_set"]: row["decoder_vs_full"] for row in profile["fixed_sets"]})
    return cost


def auto_cost(profile: dict, refined: float) -> float:
    points = sorted((row["queries_refined"] / profile["queries"], row["decoder_vs_full"])
                    for row in profile["budgets"])
    return float(np.interp(refined, *zip(*points)))


def plot_budget_study(classes: dict, profile: dict, out: str) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    cost = costs(profile)
    fig, axes = plt.subplots(2, len(classes), figsize=(3.6 * len(classes), 6.4), squeeze=False)
    for column, (name, rows) in enumerate(classes.items()):
        for line, metric in enumerate(("mIoU", "RayIoU")):
            ax = axes[line][column]
            for label, (style, prefix) in MARKERS.items():
                names = [n for n in rows if n.startswith(prefix) and n in cost]
                names = sorted(names + ["full"] * (prefix == "keep-"), key=lambda n: cost[n])
                ax.plot([cost[n] for n in names], [rows[n][metric] for n in names], style,
                        label=label)
            ax.plot([auto_cost(profile, rows["auto"]["refined_fraction"])],
                    [rows["auto"][metric]], "*", markersize=12, label="auto")
            ax.set_title(name if line == 0 else "")
            ax.set_xlabel("decoder time / full" if line == 1 else "")
            ax.set_ylabel(metric if column == 0 else "")
            ax.grid(alpha=0.3)
    axes[0][0].legend(fontsize=7)
    fig.suptitle(f"{profile['preset']}: query budgets per scene class (CPU, 1 thread)")
    fig.tight_layout()
    fig.savefig(out, dpi=110)
