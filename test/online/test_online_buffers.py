"""Feature history (fill-up, resets) and the latest-wins mailbox under a slow consumer."""
import threading
import time

import numpy as np
import pytest
import torch

from odg_ros.online.history import Frame, FrameHistory
from odg_ros.online.mailbox import LatestMailbox


def frame(stamp):
    return Frame(features=[torch.zeros(1)], pose=np.eye(4), ego2img=np.eye(4)[None], stamp=stamp)


def test_history_fills_up_to_capacity_newest_first():
    history = FrameHistory(capacity=3, max_gap=1.0)
    for i in range(5):
        assert history.push(frame(0.1 * i)) is None
        assert len(history) == min(i + 1, 3)
    assert [f.stamp for f in history.frames()] == pytest.approx([0.4, 0.3, 0.2])


def test_history_resets_on_time_backwards_and_on_gap():
    history = FrameHistory(capacity=4, max_gap=1.0)
    for i in range(3):
        history.push(frame(10 + 0.5 * i))
    assert history.push(frame(5.0)) == "time_backwards"        # bag loop
    assert [f.stamp for f in history.frames()] == [5.0]
    history.push(frame(5.5))
    assert history.push(frame(5.5)) == "time_backwards"        # same set twice
    assert history.push(frame(7.0)) == "gap"                   # 1.5 s without input
    assert len(history) == 1
    assert history.resets == {"time_backwards": 2, "gap": 1, "teleport": 0}


def test_mailbox_keeps_only_the_latest():
    box = LatestMailbox()
    assert box.get(timeout=0.01) is None
    assert box.put(1) is False
    assert box.put(2) is True
    assert box.put(3) is True
    assert box.get(timeout=0.01) == 3
    assert box.get(timeout=0.01) is None
    assert box.dropped == 2 and box.delivered == 1


def test_mailbox_slow_consumer_sees_fresh_items_and_drops_are_counted():
    box = LatestMailbox()
    got = []

    def slow_worker():
        while True:
            item = box.get(timeout=1.0)
            if item is None:
                return
            got.append(item)
            time.sleep(0.02)            # inference 4x slower than the producer

    worker = threading.Thread(target=slow_worker)
    worker.start()
    for i in range(100):
        box.put(i)
        time.sleep(0.005)
    time.sleep(0.05)
    box.close()
    worker.join(timeout=5)
    assert not worker.is_alive()
    assert got == sorted(got) and got[-1] == 99           # in order, the last one processed
    assert len(got) < 60                                  # most were skipped, not queued
    assert box.dropped + box.delivered == 100


def test_mailbox_close_wakes_a_waiting_worker():
    box = LatestMailbox()
    result = []
    worker = threading.Thread(target=lambda: result.append(box.get(timeout=10)))
    worker.start()
    time.sleep(0.05)
    start = time.monotonic()
    box.close()
    worker.join(timeout=2)
    assert result == [None] and time.monotonic() - start < 1.0
