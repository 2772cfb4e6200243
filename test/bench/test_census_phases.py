"""The census counts by the phases the training step marks (``training_phases``): an op
belongs to the innermost phase open, "other" outside every phase; the ranges themselves and
profiler ranges of other names launch nothing and are not counted."""
import pytest
import torch
from torch.profiler import record_function

from odg_ros.bench.census import Census, CensusMode
from odg_ros.training_phases import PHASES, training_phase


def test_ops_are_counted_in_the_innermost_phase_marked():
    x = torch.ones(3)
    census = Census()
    with CensusMode(census, device_type=None):
        x = x + 1                                   # other
        with training_phase("losses"):
            x = x * 2
            with training_phase("render"):
                x = x - 1
                x = x.exp()
            with record_function("not.a.phase"):    # a range of another name: still losses
                x = x.sum()
        with training_phase("backward"):
            x.item()                                # a read: a wait in backward
    by_phase = {phase: census.per_step(census.ops, phase) for phase in PHASES + ("other",)}
    assert by_phase == {"data": 0, "forward": 0, "losses": 2, "render": 2, "backward": 1,
                        "optimizer": 0, "other": 1}
    assert census.per_step(census.syncs, "backward") == 1


def test_an_unknown_phase_is_an_error():
    with pytest.raises(ValueError, match="unknown training phase 'forwards'"):
        training_phase("forwards")
