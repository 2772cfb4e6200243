"""Memory and CPU cost of hostile inputs to the node's ROS-free core, each case in a fresh
process (peak RSS is per process), with and without the protections:

* bomb: an 8000 x 8000 PNG (0.2 MB encoded) through decode_for_input, unprotected
  (no size known before decoding: what the node did) and protected (CameraInfo size and
  max_pixels checked on the header);
* names: 40,000 /tf frame names at 5,000 transforms/s into a TransformBuffer that keeps
  everything (unprotected) and into the node's (only needed chains kept, stale frames
  forgotten after 10 s);
* busy_tree: the node's /tf callback on messages of 250 fixed frames, converting every
  transform (unprotected) or only the needed ones: microseconds per transform and the cores
  a 5,000 transforms/s tree costs.

    python -m tools.measure_hostile_inputs            # all cases, one line each
"""
from __future__ import annotations

import argparse
import io
import json
import resource
import subprocess
import sys
import time
import types


def rss_mb() -> float:
    with open("/proc/self/status") as f:
        return next(int(line.split()[1]) for line in f if line.startswith("VmRSS")) / 1024


def peak_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def bomb(protected: bool) -> dict:
    import numpy as np
    from PIL import Image
    buffer = io.BytesIO()
    Image.fromarray(np.zeros((8000, 8000), np.uint8)).save(buffer, format="PNG")
    data = buffer.getvalue()
    del buffer
    # the encoder's working memory raised the peak; measure in a child with only the bytes
    code = ("import sys, json; "
            "from tools.measure_hostile_inputs import _decode_child; _decode_child(%r)"
            % protected)
    out = subprocess.run([sys.executable, "-c", code], input=data, capture_output=True,
                         check=True).stdout
    result = json.loads(out)
    result["encoded_mb"] = round(len(data) / 2**20, 2)
    return result


def _decode_child(protected: bool) -> None:
    from odg_ros.online.errors import BadInput
    from odg_ros.online.images import EncodedImage, decode_for_input
    data = sys.stdin.buffer.read()
    before, peak_before = rss_mb(), peak_mb()
    kwargs = dict(expected_hw=(900, 1600)) if protected else dict(max_pixels=10**12)
    try:
        decode_for_input(EncodedImage(True, "png", data), (256, 704), **kwargs)
        outcome = "decoded"
    except BadInput as error:
        outcome = error.kind
    print(json.dumps({"outcome": outcome, "rss_before_mb": round(before),
                      "peak_growth_mb": round(max(peak_mb() - peak_before, 0)),
                      "retained_mb": round(rss_mb() - before)}))


def names(protected: bool) -> dict:
    import numpy as np

    from odg_ros.online.transforms import TransformBuffer
    clock = [0.0]
    if protected:
        tf = TransformBuffer(cache_time=10.0, wanted={"base_link"}, clock=lambda: clock[0])
    else:
        tf = TransformBuffer(cache_time=float("inf"), clock=lambda: clock[0])
    before = rss_mb()
    T = np.eye(4)
    for k in range(40_000):
        name = f"object_{k}"
        if tf.wants(name):
            tf.add("map", name, clock[0], T)
        clock[0] += 1 / 5000
    return {"frames_kept": len(tf.frames()), "rss_growth_mb": round(rss_mb() - before, 1)}


def busy_tree(protected: bool) -> dict:
    from builtin_interfaces.msg import Time
    from geometry_msgs.msg import TransformStamped
    from tf2_msgs.msg import TFMessage

    from odg_ros.online.transforms import TransformBuffer
    from odg_ros.ros.node import OdgNode
    tf = TransformBuffer(wanted={"base_link"} if protected else None)
    node = types.SimpleNamespace(tf=tf, warn_bad_input=lambda error: None,
                                 pipeline=types.SimpleNamespace(count_bad_input=lambda e: e))
    messages = []
    for step in range(20):                          # 1 s of a 20 Hz tree of 250 frames
        transforms = []
        for k in range(250):
            t = TransformStamped()
            t.header.stamp = Time(sec=100, nanosec=step * 50_000_000)
            t.header.frame_id, t.child_frame_id = "world", f"fixed_{k}"
            t.transform.rotation.w = 1.0
            transforms.append(t)
        messages.append(TFMessage(transforms=transforms))
    start = time.perf_counter()
    for msg in messages:
        OdgNode.on_tf(node, msg, False)
    seconds = time.perf_counter() - start
    return {"us_per_transform": round(seconds / 5000 * 1e6, 2),
            "cores_at_5000_per_s": round(seconds, 3)}


CASES = {"bomb": bomb, "names": names, "busy_tree": busy_tree}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("case", nargs="?", choices=CASES,
                        help="run only this case, in this process (default: every case, each "
                             "in a fresh process)")
    parser.add_argument("mode", nargs="?", choices=("unprotected", "protected"),
                        default="protected", help="with CASE: with or without the protections")
    args = parser.parse_args()
    if args.case is not None:
        print(json.dumps(CASES[args.case](args.mode == "protected")))
        return
    for case in CASES:
        for mode in ("unprotected", "protected"):
            out = subprocess.run([sys.executable, __file__, case, mode], capture_output=True,
                                 text=True, check=True).stdout.strip().splitlines()[-1]
            print(f"{case:10s} {mode:12s} {out}")


if __name__ == "__main__":
    main()
