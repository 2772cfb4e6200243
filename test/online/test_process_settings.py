"""Library code changes no process-wide torch setting: cuDNN's benchmark mode (the node's step
has fixed shapes) is turned on where a process that runs the step starts, the node's main and
odg bench, and nowhere else."""
import re
from pathlib import Path

import odg_ros

PACKAGE = Path(odg_ros.__file__).parent
ENTRY_POINTS = {"ros/node.py", "commands/bench.py"}


def test_cudnn_benchmark_is_set_by_the_entry_points_only():
    setting = re.compile(r"torch\.backends\.cudnn\.benchmark\s*=")
    setters = {str(path.relative_to(PACKAGE)) for path in PACKAGE.rglob("*.py")
               if setting.search(path.read_text())}
    assert setters == ENTRY_POINTS
