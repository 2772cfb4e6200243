"""``query_budget: auto``: the budget of frame t, chosen on the host from frame t-1's outputs.

Every step reports, with its grid and boxes, how many static and dynamic queries its
keep-scores call worth refining (``network.budget.needed_queries``) and how many objects it
publishes. The next step runs the smallest budget of the ladder that covers these needs with
a margin. More is granted at once; less only after ``patience`` frames in a row that could
have done with less, one rung at a time, so the budget does not flap between two rungs. A
history reset (a new scene) starts again at the full budget, and the first needs after it
set the rung directly: they describe the scene as well as any later frame's, and a drive
should not spend its first seconds at the full budget waiting out the patience.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

from ..network.budget import QueryBudget

PATIENCE = 3              # frames in a row that could do with less before stepping down
# a budget covers a need n if it keeps at least MARGIN * n queries; 1.5 keeps dense traffic
# within 0.3 mIoU and RayIoU of the full budget (docs/results/query_budget.md)
MARGIN = 1.5


@dataclass
class BudgetPolicy:
    """ladder: the budgets, largest first (``network.budget.budget_ladder``)."""
    ladder: list[QueryBudget]
    patience: int = PATIENCE
    margin: float = MARGIN
    level: int = 0
    calm: int = 0
    fresh: bool = True        # no needs seen since the reset

    def __post_init__(self):
        if not self.ladder:
            raise ValueError("a budget policy needs at least one budget")
        if any(a.static < b.static or a.dynamic < b.dynamic
               for a, b in zip(self.ladder, self.ladder[1:])):
            raise ValueError("the budget ladder must be ordered largest first")

    @property
    def budget(self) -> QueryBudget:
        """The budget of the next step."""
        return self.ladder[self.level]

    def reset(self) -> None:
        self.level, self.calm, self.fresh = 0, 0, True

    def covering_level(self, static: int, dynamic: int) -> int:
        """The smallest rung that keeps MARGIN x the needed static and dynamic queries."""
        level = 0
        for index, budget in enumerate(self.ladder):
            if budget.static >= math.ceil(self.margin * static) and \
                    budget.dynamic >= math.ceil(self.margin * dynamic):
                level = index
        return level

    def update(self, needed_static: int, needed_dynamic: int, objects: int) -> QueryBudget:
        """Frame t's needs (keep-score counts, published objects) -> frame t+1's budget."""
        wanted = self.covering_level(needed_static, max(needed_dynamic, objects))
        if self.fresh:                              # the first frame of a scene: trusted
            self.level, self.calm, self.fresh = wanted, 0, False
        elif wanted < self.level:                   # more needed: at once
            self.level, self.calm = wanted, 0
        elif wanted > self.level:                   # less would do: after `patience` frames
            self.calm += 1
            if self.calm >= self.patience:
                self.level, self.calm = self.level + 1, 0
        else:
            self.calm = 0
        return self.budget
