"""Find the project's data files (model presets, checkpoints, config) wherever it is installed.

Order: the source tree next to the package (editable pip install, a checkout), then the
prefix of a pip/colcon install (``share/odg_ros``), then the ament index of a ROS install.
"""
from __future__ import annotations

import os
import sys
from pathlib import Path

PACKAGE_NAME = "odg_ros"


def _candidate_roots() -> list[Path]:
    roots = [Path(__file__).resolve().parent.parent]
    roots.append(Path(sys.prefix) / "share" / PACKAGE_NAME)
    for prefix in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep):
        if prefix:
            roots.append(Path(prefix) / "share" / PACKAGE_NAME)
    return roots


def resource_path(relative: str) -> Path:
    """Path of ``relative`` (e.g. ``model/odg_t.yaml``) in the first root that has it."""
    for root in _candidate_roots():
        candidate = root / relative
        if candidate.exists():
            return candidate
    searched = ", ".join(str(r) for r in _candidate_roots())
    raise FileNotFoundError(f"{relative} not found under any of: {searched}")


SHIPPED_CHECKPOINT = "model/odg_cpu.pt"


def shipped_checkpoint() -> Path:
    """The checkpoint the package ships (``model/odg_cpu.pt``), wherever it is installed."""
    try:
        return resource_path(SHIPPED_CHECKPOINT)
    except FileNotFoundError:
        raise FileNotFoundError(f"the shipped checkpoint {SHIPPED_CHECKPOINT} is missing from "
                                "this checkout or install") from None
