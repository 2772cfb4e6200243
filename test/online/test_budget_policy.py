"""query_budget auto (online/budget_policy.py): a scene's first needs set the rung, then up
at once, down one rung after a calm stretch, never flapping; a reset starts at the full
budget."""
import pytest

from odg_ros.network.budget import QueryBudget
from odg_ros.online.budget_policy import BudgetPolicy

LADDER = [QueryBudget(200, 100), QueryBudget(120, 52), QueryBudget(72, 28)]


def test_needs_pick_the_smallest_covering_rung():
    policy = BudgetPolicy(LADDER)
    assert policy.covering_level(0, 0) == 2
    assert policy.covering_level(48, 18) == 2          # 1.5 x 48 = 72, 1.5 x 18 = 27
    assert policy.covering_level(49, 0) == 1           # 1.5 x 49 = 74 (rounded up) > 72
    assert policy.covering_level(0, 19) == 1           # 1.5 x 19 = 29 > 28
    assert policy.covering_level(80, 34) == 1
    assert policy.covering_level(81, 0) == 0
    assert policy.covering_level(0, 35) == 0
    assert policy.covering_level(150, 0) == 0
    assert policy.covering_level(500, 500) == 0        # more than the model has: all of it


def test_the_first_needs_of_a_scene_set_the_rung_directly():
    policy = BudgetPolicy(LADDER, patience=3)
    assert policy.budget == LADDER[0]                  # the first frame runs in full
    assert policy.update(10, 2, 1) == LADDER[2]        # its needs count at once
    assert policy.update(10, 2, 1) == LADDER[2]
    policy.reset()
    assert policy.budget == LADDER[0]
    assert policy.update(70, 2, 1) == LADDER[1]


def test_up_at_once_down_after_patience_one_rung_at_a_time():
    policy = BudgetPolicy(LADDER, patience=3)
    assert policy.update(190, 0, 0) == LADDER[0]       # a busy first frame
    levels = [LADDER.index(policy.update(10, 2, 1)) for _ in range(7)]
    assert levels == [0, 0, 1, 1, 1, 2, 2]
    assert policy.update(10, 30, 1) == LADDER[1]       # dynamic queries needed: up at once
    assert policy.update(10, 2, 30) == LADDER[1]       # many objects tracked: stays up
    assert policy.update(190, 0, 0) == LADDER[0]       # a busy static scene: full at once


def test_alternating_needs_do_not_flap():
    policy = BudgetPolicy(LADDER, patience=3)
    busy, quiet = (150, 60), (10, 2)
    seen = [LADDER.index(policy.update(*(busy if i % 2 else quiet), 0)) for i in range(20)]
    # the first (quiet) frame sets the smallest rung, the busy one after it the full budget,
    # and a calm stretch is never long enough to step down
    assert seen == [2] + [0] * 19


def test_reset_and_bad_ladders():
    policy = BudgetPolicy(LADDER, patience=1)
    policy.update(150, 0, 0)
    policy.update(0, 0, 0)
    assert policy.budget == LADDER[1]
    policy.reset()
    assert policy.budget == LADDER[0]
    with pytest.raises(ValueError, match="largest first"):
        BudgetPolicy(LADDER[::-1])
    with pytest.raises(ValueError, match="at least one"):
        BudgetPolicy([])
