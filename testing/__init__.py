"""What the test suite and the maintainer tools share: tiny configurations, worlds and
checkpoints, transcriptions of reference implementations (SparseOcc's RayIoU, OPUS's
post-processing), hard-case strategies and ROS helpers. Importable from the repository root
(pytest's ``pythonpath``, ``python -m tools.NAME``); not part of the installed package."""
from pathlib import Path

REPOSITORY = Path(__file__).resolve().parent.parent
