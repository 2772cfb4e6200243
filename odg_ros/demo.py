"""The ROS-free half of ``odg demo``: the demo world, and what is made of the node's outputs.

``odg demo`` (odg_ros/commands/demo.py) runs::

    build_world          odg synth (1 scene) -> odg prepare --split all -> odg bag synth
    ros/demo_session.py  odg_node (own process) + odg replay --clock (own process) + a
                         planner stand-in that receives every output (this process)
    report               score the keyframes (mIoU, RayIoU), count, time, draw

Everything a number in the report is made of is defined here:

* frames_in: camera sets the replay published (the complete sets of the bag).
* frames_out: ``~/occupancy`` grids the planner stand-in received.
* dropped: sets the node skipped, from its final ``/diagnostics``: stale sets replaced in the
  latest-wins mailbox + incomplete sets + bad-input skips (each reason separately in
  ``dropped_by_reason``). ``lost_in_transport``: grids the node published that did not arrive;
  ``unaccounted``: sets that are neither (normally 0).
* fps: grids received per second of wall time, first to last grid. ``input_fps`` is the rate
  at which sets were published, ``node_capacity_fps`` 1000 / the node's mean processing time
  per set (its stage times), i.e. what it could do if a set were always waiting.
* latency_ms_p50/p95: wall clock, from the moment the replay published the last image of a
  set (the set became complete; taken from ``/clock``, which the replay publishes just before
  each stamp) to the moment the grid of that set reached the planner stand-in: waiting in the
  mailbox + decoding + network + publishing + transport. (The node's own diagnostics latency
  is "now - image stamp" on its clock, here the bag's simulated time, which runs at ``rate``
  times wall time; it is kept in the JSON as ``node.latency_sim_ms``.)
* mIoU (camera mask) and RayIoU (+ @1/2/4 m and per class), ``metrics.score.OccScore``, over
  the keyframes whose grid was received. A grid belongs to the keyframe whose CAM_FRONT
  stamp equals the grid's header stamp (the node stamps outputs with the reference camera's
  stamp); grids of the 12 Hz sweeps between keyframes have no GT and are only counted.
"""
from __future__ import annotations

import json
import math
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from tqdm import tqdm

DEFAULT_OUT = Path("out/demo")
DEFAULT_SEED = 1000          # the shipped model trained on seed 1 (model/odg_cpu.md): a scene it never saw
DEFAULT_SECONDS = 8.0
# 12 Hz camera sets played at 0.25 x real time arrive every 333 ms of wall time: the CPU
# preset (~200 ms per set on an idle 2-core machine) keeps up with most of them.
DEFAULT_RATE = 0.25
SHIPPED_CHECKPOINT = "model/odg_cpu.pt"
REFERENCE_CAMERA = "CAM_FRONT"
SET_SLOP_NS = 50_000_000      # as the node's default `slop` (config/odg.yaml)
WORLD_MARKER = "world.json"


class DemoError(RuntimeError):
    """A demo stage failed; the message says which and why (and what to look at)."""


# ---------------------------------------------------------------------------------------------
# The world: synthetic scene -> infos -> bag, reused when already built with the same settings


@dataclass(frozen=True)
class WorldSpec:
    image_hw: tuple[int, int]        # camera images (odg synth's default in odg demo)
    seed: int = DEFAULT_SEED
    seconds: float = DEFAULT_SECONDS

    def as_dict(self) -> dict:
        return {"scenes": 1, "seed": int(self.seed), "seconds": float(self.seconds),
                "image_hw": [int(v) for v in self.image_hw]}


@dataclass
class DemoWorld:
    root: Path          # the synthetic dataroot (odg synth)
    infos: Path         # odg prepare --split all
    bag: Path           # odg bag synth (cameras, CameraInfo, /tf, /tf_static, /odom)
    reused: bool
    seconds: float      # wall time spent here


def build_world(out: Path, spec: WorldSpec, progress: bool = True, log=print) -> DemoWorld:
    """Build (or reuse) the demo world under ``out``: ``world/`` (dataroot + infos_all.pkl)
    and ``bag/``. ``out/world.json`` records the settings and is marked complete only after
    the bag is written, so an interrupted build is redone, and a different seed, length or
    image size rebuilds. Folders there that this function did not make are never deleted."""
    from odg_ros.data.prepare import build_infos, save_infos
    from odg_ros.data.synth.generate import generate
    from odg_ros.ros.bag import write_scene_bag
    from odg_ros.ros.nuscenes_source import NuScenesSensorTables

    start = time.monotonic()
    out = Path(out)
    world = DemoWorld(root=out / "world", infos=out / "world" / "infos_all.pkl",
                      bag=out / "bag", reused=False, seconds=0.0)
    marker = out / WORLD_MARKER
    wanted = spec.as_dict()
    recorded = _read_marker(marker)
    if world_is_built(out, spec):
        world.reused = True
        world.seconds = time.monotonic() - start
        log(f"reusing the demo world in {out} (seed {spec.seed}, {spec.seconds:g} s)")
        return world
    for path in (world.root, world.bag):
        if path.exists():
            if recorded is None:
                raise DemoError(f"{path} exists but was not made by odg demo (no {marker}); "
                                "choose another --out")
            shutil.rmtree(path)
    out.mkdir(parents=True, exist_ok=True)
    marker.write_text(json.dumps({"spec": wanted, "complete": False}, indent=1))

    log(f"building the demo world in {out}: 1 scene, {spec.seconds:g} s, seed {spec.seed}, "
        f"{spec.image_hw[0]} x {spec.image_hw[1]} images")
    generate(str(world.root), scenes=1, seconds=spec.seconds, seed=spec.seed,
             image_hw=tuple(spec.image_hw), version="v1.0-trainval", progress=progress)
    save_infos(build_infos(world.root, version="v1.0-trainval", split="all",
                           progress=progress), world.infos)
    tables = NuScenesSensorTables(world.root, "v1.0-trainval")
    (scene,) = tables.scene_names()
    # No LiDAR: the node does not use it, and 20 Hz point clouds would only load the machine.
    write_scene_bag(tables.scene_records(scene, with_lidar=False), world.bag,
                    progress=progress)
    marker.write_text(json.dumps({"spec": wanted, "complete": True}, indent=1))
    world.seconds = time.monotonic() - start
    return world


def world_is_built(out: Path, spec: WorldSpec) -> bool:
    """True when ``out`` holds a complete demo world built with exactly ``spec``."""
    out = Path(out)
    recorded = _read_marker(out / WORLD_MARKER)
    return (recorded is not None and recorded.get("spec") == spec.as_dict()
            and bool(recorded.get("complete")) and (out / "world" / "infos_all.pkl").is_file()
            and (out / "bag" / "metadata.yaml").is_file())


def _read_marker(path: Path) -> dict | None:
    try:
        return json.loads(path.read_text())
    except (FileNotFoundError, json.JSONDecodeError):
        return None


def resolve_checkpoint(given) -> Path:
    """``--checkpoint`` as given, else the shipped ``model/odg_cpu.pt`` (clear error if absent)."""
    from odg_ros.resources import resource_path

    if given is not None:
        path = Path(given)
        if not path.is_file():
            raise DemoError(f"checkpoint not found: {path}")
        return path.resolve()
    try:
        return resource_path(SHIPPED_CHECKPOINT).resolve()
    except FileNotFoundError:
        raise DemoError(
            f"the shipped checkpoint {SHIPPED_CHECKPOINT} is missing from this checkout or "
            "install. Train one (`odg train --preset odg_cpu ...`, see README.md) and pass it "
            "with --checkpoint PATH.") from None


# ---------------------------------------------------------------------------------------------
# What the bag holds, and what came back from the node


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
    from odg_ros.ros import bag_layout as layout
    from odg_ros.ros.bag import iter_bag

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


# ---------------------------------------------------------------------------------------------
# Scoring and numbers


def keyframes_by_stamp(infos: list[dict]) -> dict[int, int]:
    """CAM_FRONT stamp (ns) -> index into ``infos`` of every keyframe that has GT."""
    return {int(info["cams"][REFERENCE_CAMERA]["timestamp"]) * 1000: i
            for i, info in enumerate(infos) if info["occ_path"]}


def score_keyframes(meta: dict, grids: dict[int, np.ndarray], progress: bool = True):
    """Score the received grids of keyframes against the Occ3D GT.

    meta: the infos dict (``metrics.score.load_infos``); grids: stamp_ns -> uint8 [X, Y, Z].
    Returns (OccScore.result() or None when no keyframe grid arrived, scored info indices,
    per-keyframe mIoU {info index: percent or None}).
    """
    from odg_ros.data.occ_io import load_occ
    from odg_ros.metrics.rayiou import LidarOrigins
    from odg_ros.metrics.score import OccScore, resolve_occ_root

    infos, dataset = meta["infos"], meta["dataset"]
    root = resolve_occ_root(meta)
    by_stamp = keyframes_by_stamp(infos)
    scored = sorted(by_stamp[s] for s in grids if s in by_stamp)
    if not scored:
        return None, [], {}
    stamp_of = {i: s for s, i in by_stamp.items()}
    origins = LidarOrigins(infos)
    total = OccScore(dataset)
    single = {}
    for i in tqdm(scored, desc="scoring keyframes", unit="keyframe", disable=not progress):
        gt, _, mask_camera = load_occ(root / infos[i]["occ_path"], dataset)
        pred = grids[stamp_of[i]]
        if pred.shape != gt.shape:
            raise DemoError(f"received grid {pred.shape} does not match the GT {gt.shape}")
        total.add(pred, gt, mask_camera, origins(i))
        one = OccScore(dataset, rayiou=False)
        one.add(pred, gt, mask_camera)
        single[i] = one.result()["mIoU"]
    return total.result(), scored, single


def _percentile(values, q) -> float | None:
    values = np.asarray(values, dtype=np.float64)
    return float(np.percentile(values, q)) if values.size else None


def grid_latencies_ms(record: SessionRecord, sets: CameraSets) -> np.ndarray:
    """Wall-clock latency of every received grid whose set's completion was seen on /clock
    (see the module docstring), milliseconds."""
    index = {int(s): i for i, s in enumerate(sets.reference_ns)}
    out = []
    for grid in record.grids:
        i = index.get(grid.stamp_ns)
        if i is None or sets.complete_ns[i] < 0:
            continue
        published = record.clock_wall.get(int(sets.complete_ns[i]))
        if published is not None:
            out.append((grid.wall_s - published) * 1e3)
    return np.asarray(out, dtype=np.float64)


DROP_COUNTERS = ("stale_sets_dropped", "dropped_incomplete_sets")


def summarize(record: SessionRecord, sets: CameraSets, meta: dict, score: dict | None,
              scored: list[int], rate: float) -> dict:
    """The demo's numbers (see the module docstring), JSON-ready (None where unmeasured)."""
    from odg_ros.online.errors import BAD_INPUT_KINDS

    diag = record.diagnostics

    def counter(key) -> int:
        try:
            return int(diag.get(key, "0"))
        except ValueError:
            return 0

    reasons = {k: counter(k) for k in DROP_COUNTERS + BAD_INPUT_KINDS}
    dropped = sum(reasons.values())
    frames_in = sets.num_complete
    frames_out = len(record.grids)
    wall = [g.wall_s for g in record.grids]
    fps = (frames_out - 1) / (wall[-1] - wall[0]) if frames_out >= 2 and wall[-1] > wall[0] \
        else None
    published = [record.clock_wall[int(c)] for c in sets.complete_ns
                 if c >= 0 and int(c) in record.clock_wall]
    input_fps = ((len(published) - 1) / (published[-1] - published[0])
                 if len(published) >= 2 and published[-1] > published[0] else None)
    stage_ms = {}
    for key, value in diag.items():
        if key.startswith("stage_") and key.endswith("_ms"):
            try:
                stage_ms[key[len("stage_"):-len("_ms")]] = float(value)
            except ValueError:
                pass       # "n/a" before the first output
    step_ms = sum(stage_ms.values())
    latencies = grid_latencies_ms(record, sets)
    keyframes = keyframes_by_stamp(meta["infos"])
    node_outputs = counter("outputs")

    def node_float(key):
        try:
            return float(diag[key])
        except (KeyError, ValueError):
            return None

    report = {
        "frames_in": frames_in,
        "frames_out": frames_out,
        "dropped": dropped,
        "fps": fps,
        "latency_ms_p50": _percentile(latencies, 50),
        "latency_ms_p95": _percentile(latencies, 95),
        "mIoU": score["mIoU"] if score else None,
        "RayIoU": score.get("RayIoU") if score else None,
        "RayIoU@1": score.get("RayIoU@1") if score else None,
        "RayIoU@2": score.get("RayIoU@2") if score else None,
        "RayIoU@4": score.get("RayIoU@4") if score else None,
        "IoU_geometry": score["IoU_geometry"] if score else None,
        "keyframes": len(keyframes),
        "keyframes_scored": len(scored),
        "per_class": score["per_class"] if score else {},
        "dropped_by_reason": {k: v for k, v in reasons.items() if v},
        # outputs the node published that never reached the planner (reliable, keep-last 1)
        "lost_in_transport": max(0, node_outputs - frames_out) if diag else None,
        # sets published but neither output nor counted by the node (every image of the set
        # lost on the way: best effort); 0 normally
        "unaccounted": (frames_in - frames_out - dropped - max(0, node_outputs - frames_out)
                        if diag else None),
        "input_fps": input_fps,
        "node_capacity_fps": 1e3 / step_ms if step_ms > 0 else None,
        "rate": rate,
        "latency_ms_mean": float(latencies.mean()) if latencies.size else None,
        "latency_samples": int(latencies.size),
        "objects_per_output": (float(np.mean([n for _, n in record.objects]))
                               if record.objects else None),
        "node": {
            "outputs": node_outputs if diag else None,
            "fps_topic_median": (float(np.median([f for f in record.fps_samples if f > 0]))
                                 if any(f > 0 for f in record.fps_samples) else None),
            "stage_ms": stage_ms,
            "latency_sim_ms": {"p50": node_float("latency_p50_ms"),
                               "p95": node_float("latency_p95_ms")},
            "counters": {k: v for k, v in diag.items()
                         if k not in ("rate_hz", "latency_p50_ms", "latency_p95_ms")
                         and not k.startswith("stage_")},
            "status": record.diagnostics_message,
        },
        "warnings": list(record.warnings),
    }
    return report


def _fmt(value, spec=".2f", none="-") -> str:
    return none if value is None or (isinstance(value, float) and math.isnan(value)) \
        else format(value, spec)


def format_summary(report: dict) -> str:
    """The demo's table (the numbers of ``summarize`` plus the run's settings and times)."""
    r = report
    reasons = r["dropped_by_reason"]
    why = ", ".join(f"{k.replace('_', ' ')} {v}" for k, v in reasons.items()) or "none"
    world = r.get("world", {})
    rows = [
        ("camera sets in", f"{r['frames_in']}",
         f"published by the replay at {r['rate']:g} x real time "
         f"({_fmt(r['input_fps'], '.1f')} sets/s)"),
        ("grids out", f"{r['frames_out']}", "received by the planner stand-in"
         + (f", {r['lost_in_transport']} lost in transport" if r.get("lost_in_transport")
            else "")),
        ("dropped", f"{r['dropped']}", why),
        ("FPS", _fmt(r["fps"]), f"grids per wall second; node capacity "
         f"{_fmt(r['node_capacity_fps'], '.1f')}/s from its stage times"),
        ("latency p50 / p95", f"{_fmt(r['latency_ms_p50'], '.0f')} / "
         f"{_fmt(r['latency_ms_p95'], '.0f')} ms", "set complete -> grid at the planner"),
        ("keyframes scored", f"{r['keyframes_scored']} of {r['keyframes']}",
         "the others were dropped by the node"
         if r["keyframes_scored"] < r["keyframes"] else ""),
        ("mIoU", _fmt(r["mIoU"]), "camera mask, 17 classes"),
        ("RayIoU", _fmt(r["RayIoU"]), f"@1/2/4 m: {_fmt(r['RayIoU@1'])} / "
         f"{_fmt(r['RayIoU@2'])} / {_fmt(r['RayIoU@4'])}"),
    ]
    width = max(len(a) for a, _, _ in rows)
    value_width = max(len(b) for _, b, _ in rows)
    title = "odg demo"
    if world:
        title += (f": 1 synthetic scene, {world['seconds']:g} s, seed {world['seed']}; "
                  f"checkpoint {r.get('checkpoint', '?')}")
    lines = [title, "-" * max(60, len(title))]
    lines += [f"{a:<{width}}  {b:>{value_width}}  {c}".rstrip() for a, b, c in rows]
    lines.append("-" * max(60, len(title)))
    t = r.get("timings_s", {})
    if t:
        lines.append("wall time: " + ", ".join(f"{k.replace('_', ' ')} {v:.0f} s"
                                               for k, v in t.items()))
    for warning in r.get("warnings", []):
        lines.append(f"warning: {warning}")
    return "\n".join(lines)


def write_json(report: dict, path) -> None:
    Path(path).write_text(json.dumps(report, indent=2, allow_nan=False) + "\n")


# ---------------------------------------------------------------------------------------------
# The picture


def pick_keyframe(scored: list[int], infos: list[dict]) -> int:
    """The scored keyframe nearest the middle of the scene (history frames are warm there)."""
    if not scored:
        raise ValueError("no scored keyframe to draw")
    middle = np.median([infos[i]["timestamp"] for i in range(len(infos))])
    return min(scored, key=lambda i: abs(infos[i]["timestamp"] - middle))


def bev_rgb(labels: np.ndarray, seen: np.ndarray | None = None) -> np.ndarray:
    """Top view of a label grid uint8 [X, Y, Z] (17 = free) -> uint8 [X, Y, 3] image.

    Each column shows the class of its highest non-free voxel (classes.OCC_COLORS; white where
    the column is free). Rows run from +x (forward) at the top to -x, columns from +y (left)
    on the left to -y, so the picture looks like a map with the car driving up. ``seen``
    bool [X, Y, Z] (e.g. mask_camera): columns without a seen voxel are drawn darker.
    """
    from odg_ros.classes import FREE_LABEL, OCC_COLORS

    labels = np.asarray(labels)
    occupied = labels != FREE_LABEL
    top = labels.shape[2] - 1 - np.argmax(occupied[:, :, ::-1], axis=2)          # [X, Y]
    label = np.where(occupied.any(axis=2),
                     np.take_along_axis(labels, top[..., None], axis=2)[..., 0], FREE_LABEL)
    rgb = np.asarray(OCC_COLORS, dtype=np.uint8)[label]
    if seen is not None:
        rgb = np.where(np.asarray(seen).any(axis=2)[..., None], rgb,
                       (rgb * 0.45).astype(np.uint8))
    return np.ascontiguousarray(rgb[::-1, ::-1])


def draw_demo_png(path, meta: dict, index: int, pred: np.ndarray, report: dict,
                  keyframe_miou: float | None) -> None:
    """demo.png: the six cameras of keyframe ``index`` over its BEV prediction (as the planner
    stand-in received it) and BEV ground truth side by side (``bev_rgb``; darker columns: no
    camera sees them, outside what the mIoU counts), titled with the demo's numbers."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Patch
    from PIL import Image

    from odg_ros.classes import FREE_LABEL, OCC_CLASSES, OCC_COLORS
    from odg_ros.data.occ_io import load_occ
    from odg_ros.metrics.score import resolve_occ_root

    info = meta["infos"][index]
    dataroot = Path(meta["dataroot"])
    gt, _, mask_camera = load_occ(resolve_occ_root(meta) / info["occ_path"], meta["dataset"])
    # Cameras as they sit on the car: front row left to right, back row seen from behind.
    layout = (("CAM_FRONT_LEFT", "CAM_FRONT", "CAM_FRONT_RIGHT"),
              ("CAM_BACK_RIGHT", "CAM_BACK", "CAM_BACK_LEFT"))
    h, w = info["cams"]["CAM_FRONT"]["image_hw"]
    width = 13.0
    camera_row, bev_row = width / 3 * h / w, width / 2 * 0.9
    fig = plt.figure(figsize=(width, 2 * camera_row + bev_row + 2.2))
    grid = fig.add_gridspec(3, 6, height_ratios=[camera_row, camera_row, bev_row],
                            hspace=0.15, wspace=0.05)
    for row, names in enumerate(layout):
        for column, name in enumerate(names):
            ax = fig.add_subplot(grid[row, 2 * column:2 * column + 2])
            with Image.open(dataroot / info["cams"][name]["data_path"]) as image:
                ax.imshow(image.convert("RGB"))
            ax.set_title(name, fontsize=8, pad=2)
            ax.axis("off")
    extent = (40.0, -40.0, -40.0, 40.0)      # lateral y: +40 (left) .. -40; forward x: -40 .. 40
    for column, (labels, title) in enumerate([
            (pred, f"prediction (from odg_node), this keyframe: mIoU "
                   f"{_fmt(keyframe_miou, '.1f')}"),
            (gt, "ground truth (Occ3D layout)")]):
        ax = fig.add_subplot(grid[2, 3 * column:3 * column + 3])
        ax.imshow(bev_rgb(labels, mask_camera), extent=extent, interpolation="nearest")
        ax.plot([0], [0], marker="^", color="red", markersize=8, markeredgecolor="black")
        ax.set_title(title, fontsize=10)
        ax.set_xlabel("y (m, left +)", fontsize=8)
        if column == 0:
            ax.set_ylabel("x (m, forward +)", fontsize=8)
        ax.tick_params(labelsize=7)
    present = sorted(set(np.unique(pred).tolist()) | set(np.unique(gt).tolist()) - {FREE_LABEL})
    fig.legend(handles=[Patch(facecolor=np.asarray(OCC_COLORS[c]) / 255, edgecolor="black",
                              label=OCC_CLASSES[c]) for c in present if c != FREE_LABEL],
               loc="lower center", ncol=min(9, max(1, len(present))), fontsize=8,
               frameon=False)
    t = (info["timestamp"] - meta["infos"][0]["timestamp"]) * 1e-6
    fig.suptitle(
        f"odg demo: mIoU {_fmt(report['mIoU'])}  RayIoU {_fmt(report['RayIoU'])}  over "
        f"{report['keyframes_scored']} keyframes  |  {report['frames_out']} of "
        f"{report['frames_in']} camera sets out, FPS {_fmt(report['fps'], '.1f')}, latency p50 "
        f"{_fmt(report['latency_ms_p50'], '.0f')} ms\n"
        f"keyframe {info['frame_index']} (t = {t:.1f} s); top views: per column the highest "
        "occupied voxel, darker = no camera sees it", fontsize=11)
    fig.subplots_adjust(left=0.05, right=0.98, top=0.93, bottom=0.07)
    fig.savefig(path, dpi=100)
    plt.close(fig)
