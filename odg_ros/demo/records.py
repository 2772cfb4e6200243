"""What the demo's bag holds (its camera sets) and what came back from the node (the
planner stand-in's record of one session)."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from . import REFERENCE_CAMERA, DemoError

SET_SLOP_NS = 50_000_000      # as the node's default `slop` (config/odg.yaml)


@dataclass
class CameraSets:
    """The camera sets of the bag, in time order.

    reference_ns int64 [S]: CAM_FRONT stamp of each set (the stamp the node's outputs carry);
    complete_ns int64 [S]: stamp of the set's last image (the set is complete once the replay
    has published it), -1 when some camera has no image within the slop (never complete).
    """
    reference_ns: np.ndarray
    complete_ns: np.ndarray

    @property
    def num_complete(self) -> int:
        return int((self.complete_ns >= 0).sum())

    def duration_s(self) -> float:
        return float(self.reference_ns[-1] - self.reference_ns[0]) * 1e-9


def bag_camera_sets(bag, slop_ns: int = SET_SLOP_NS) -> CameraSets:
    """Group the bag's camera images into sets around each CAM_FRONT image (nearest image of
    every other camera within ``slop_ns``), as the node's synchroniser will."""
    from ..bags import layout
    from ..bags.reader import iter_bag

    topics = {layout.image_topic(c): c for c in layout.CAMERA_NAMES}
    stamps = {c: [] for c in layout.CAMERA_NAMES}
    for topic, stamp_ns, _, _ in iter_bag(bag, topics=topics):
        stamps[topics[topic]].append(stamp_ns)
    if not stamps[REFERENCE_CAMERA]:
        raise DemoError(f"{bag}: no {layout.image_topic(REFERENCE_CAMERA)} images")
    reference = np.array(sorted(stamps[REFERENCE_CAMERA]), dtype=np.int64)
    complete = reference.copy()
    for values in stamps.values():
        values = np.array(sorted(values), dtype=np.int64)
        if not len(values):
            complete[:] = -1
            continue
        right = np.clip(np.searchsorted(values, reference), 0, len(values) - 1)
        left = np.maximum(right - 1, 0)
        nearest = np.where(np.abs(values[left] - reference) <= np.abs(values[right] - reference),
                           values[left], values[right])
        inside = (np.abs(nearest - reference) <= slop_ns) & (complete >= 0)
        complete = np.where(inside, np.maximum(complete, nearest), -1)
    return CameraSets(reference, complete)


@dataclass
class ReceivedGrid:
    """One ``~/occupancy`` message as the planner stand-in got it."""
    stamp_ns: int              # header stamp (the set's CAM_FRONT stamp)
    wall_s: float              # time.monotonic() on receipt
    labels: np.ndarray         # uint8 [X, Y, Z], 17 = free
    observed: np.ndarray | None = None    # bool [X, Y, Z]: a camera sees it (None: not sent)


@dataclass
class SessionRecord:
    """What the planner stand-in saw during one node + replay session (ros/demo_session.py).

    clock_wall: simulated time (ns, from /clock) -> time.monotonic() when first seen.
    diagnostics: the node's last DiagnosticStatus values (key -> string), read after its
    last output; objects: (stamp_ns, number of objects) per ~/objects message.
    """
    grids: list[ReceivedGrid] = field(default_factory=list)
    objects: list[tuple[int, int]] = field(default_factory=list)
    clock_wall: dict[int, float] = field(default_factory=dict)
    fps_samples: list[float] = field(default_factory=list)
    diagnostics: dict[str, str] = field(default_factory=dict)
    diagnostics_message: str = ""
    odometry_messages: int = 0
    replay_exit_code: int | None = None
    timings: dict[str, float] = field(default_factory=dict)   # wall s per session stage
    warnings: list[str] = field(default_factory=list)
