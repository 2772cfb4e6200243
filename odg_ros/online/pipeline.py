"""The online pipeline without ROS: messages in (as plain values), predictions out.

The node (odg_ros/ros/node.py) only converts messages and publishes; everything it decides
lives here so it is unit-tested without rclpy::

    on_image ─> CameraSetSync ─> WaitingSets ──> prepare(): CameraInfo check, poses at
    on_camera_info (K, size) notify ^ (until its   every camera stamp, extrinsics, ego2img,
    on_pose ─> PoseBuffer ─ notify ─┤  data is     decode + resize ─> LatestMailbox
    transforms_arrived ──── notify ─┘  there)      ─> infer(): OnlinePredictor.step
                                                                  ─> OnlineResult

A complete set whose poses, camera transforms or first CameraInfo have not arrived yet waits
for them, up to ``pose_wait`` seconds of the node's clock (online/waiting.py: the newest
ready set wins, older ones are dropped as stale); one whose wait runs out is a ``pose_miss``
(or ``missing_extrinsics``, ``missing_camera_info``) saying how long it waited. ``process``
runs both stages in the caller's thread; ``start_decoding`` runs ``prepare`` in a thread of
its own, so the next set decodes while the model runs (``next_prepared``).

Every unusable input raises ``BadInput`` after it has been counted; the caller logs it
(throttled) and carries on with the next message or set.
"""
from __future__ import annotations

import os
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace
from typing import Any, Callable, Sequence

import numpy as np

from ..geometry import rigid_mask
from .diagnostics import PipelineStats
from .errors import BAD_INPUT_KINDS, BadInput
from ..preprocess import adjust_intrinsics
from .images import (DeviceJpegDecoder, EncodedImage, decode_for_input,
                     select_jpeg_decoder, to_network_input)
from .mailbox import LatestMailbox
from .pacing import DecodePacing
from .parameters import validate
from .poses import PoseBuffer
from .predictor import OnlinePredictor
from .camera_calibration import CameraCalibration, IntrinsicsRange, check_intrinsics, set_ego2img
from .sync import CameraSet, CameraSetSync
from ..network.visibility import image_bounds
from .waiting import FAILED, PENDING, READY, WaitingSets


@dataclass
class PipelineSettings:
    """slop: max stamp spread of one set (s); max_future: how far an image stamp may be
    ahead of the node clock (s); pose_max_extrapolation: beyond the pose buffer (s);
    max_pose_gap: the widest gap between two poses interpolated across (s); pose_wait: how
    long a set may wait for poses / transforms not received yet (s, node clock);
    plausibility: intrinsics (CameraInfo), max_speed (m/s) / max_acceleration (m/s^2) of the
    ego between poses, max_image_pixels of a decoded image; time_jump: a stamp this much
    older than the newest one means the source restarted (s). All but time_jump are node
    parameters, whose defaults are in config/odg_node.schema.yaml: from_parameters."""

    camera_names: Sequence[str]
    slop: float
    max_future: float
    pose_max_extrapolation: float
    max_pose_gap: float
    pose_wait: float
    intrinsics: IntrinsicsRange
    max_speed: float
    max_acceleration: float
    max_image_pixels: int
    time_jump: float = 1.0

    @classmethod
    def from_parameters(cls, camera_names: Sequence[str], parameters: dict | None = None,
                        **fields) -> PipelineSettings:
        """The settings of the node's validated ``parameters`` (None: their defaults), with
        the given ``fields`` put in."""
        p = validate({}) if parameters is None else parameters
        settings = cls(camera_names, slop=p["slop"], max_future=p["max_future_stamp"],
                       pose_max_extrapolation=p["max_pose_extrapolation"],
                       max_pose_gap=p["max_pose_gap"], pose_wait=p["pose_wait"],
                       intrinsics=IntrinsicsRange(p["min_focal_length"], p["max_focal_length"],
                                                  p["max_principal_point_offset"]),
                       max_speed=p["max_speed"], max_acceleration=p["max_acceleration"],
                       max_image_pixels=p["max_image_pixels"])
        return replace(settings, **fields)


@dataclass
class PreparedSet:
    """A set ready for the model: images uint8 [N, H, W, 3] (NumPy, or a tensor on the
    model's device when decoded there), ego2img [N, 4, 4], the reference pose, the
    seconds of the stages so far."""

    camera_set: CameraSet
    images: Any
    ego2img: np.ndarray
    reference_pose: np.ndarray
    timings: dict[str, float]
    ready: Any = None          # CUDA event of images decoded on the device
    bounds: np.ndarray | None = None   # each camera's whole image, network-input pixels


@dataclass
class OnlineResult:
    """stamp: reference stamp (s); header: the opaque header object given with the
    reference camera's image; grid/confidence uint8 [X, Y, Z]; boxes: list of dicts;
    timings: seconds per stage; num_frames: frames the decoder used; observed: bool
    [X, Y, Z], the voxels a camera sees (None with the visibility off); received: steady
    time (time.monotonic) its set became complete; query_budget, refined_fraction: the
    query budget the step ran and the share of the queries it refined (Prediction)."""

    stamp: float
    header: Any
    grid: np.ndarray
    confidence: np.ndarray
    boxes: list[dict]
    timings: dict[str, float]
    num_frames: int
    observed: np.ndarray | None = None
    received: float | None = None
    query_budget: str = "full"
    refined_fraction: float = 1.0


ExtrinsicsLookup = Callable[[str, str, float], np.ndarray]   # (camera, frame_id, stamp) -> 4x4
PoseLookup = Callable[[float], np.ndarray]                  # stamp -> T_global_from_ego


class OnlinePipeline:
    """Thread-safe between the input callbacks and either one worker calling
    ``next_set``/``process``, or ``start_decoding``'s thread and one worker calling
    ``next_prepared``/``infer`` (the node).

    extrinsics: T_ego_from_cam per (camera name, CameraInfo frame id, stamp), e.g. from a rig
    file or TF (online/extrinsics.py); it raises BadInput('missing_extrinsics') when it has
    none, pending when it may still come. An object with a ``settle(camera, frame_id)``
    method is told when a set's wait ran out (extrinsics auto: the rig file from then on).
    pose_lookup: T_global_from_ego at a stamp (e.g. TF); None = the internal PoseBuffer fed by
    ``on_pose`` (odometry). Call ``transforms_arrived`` when its data grows (TF messages).
    clock: the node's clock in seconds (0 while it does not run), which measures the wait
    for poses; None: the steady clock.
    """

    def __init__(self, predictor: OnlinePredictor, settings: PipelineSettings,
                 extrinsics: ExtrinsicsLookup, pose_lookup: PoseLookup | None = None,
                 stats: PipelineStats | None = None, clock: Callable[[], float] | None = None):
        self.predictor = predictor
        self.settings = settings
        self.camera_names = tuple(settings.camera_names)
        if len(self.camera_names) != predictor.cfg.num_cams:
            raise ValueError(f"{len(self.camera_names)} cameras configured, the model takes "
                             f"{predictor.cfg.num_cams}")
        self.input_hw = tuple(predictor.cfg.image_size)
        self.extrinsics = extrinsics
        self.poses = PoseBuffer(max_extrapolation=settings.pose_max_extrapolation,
                                max_interpolation_gap=settings.max_pose_gap,
                                time_jump=settings.time_jump, max_speed=settings.max_speed,
                                max_acceleration=settings.max_acceleration)
        predictor.restart_above_speed(settings.max_speed)
        self.pose_lookup = pose_lookup if pose_lookup is not None else self._buffer_lookup
        self.sync = CameraSetSync(self.camera_names, settings.slop, time_jump=settings.time_jump)
        # complete sets, not decoded yet, waiting for their poses / extrinsics if need be
        self.waiting = WaitingSets(self._ready, settings.pose_wait,
                                   clock if clock is not None else time.monotonic)
        self.prepared = LatestMailbox()          # decoded sets (start_decoding)
        self.pacing = DecodePacing()             # when start_decoding's thread decodes
        self._decoding: threading.Thread | None = None
        # JPEG sets decoded on the GPU where torchvision can (None: Pillow on the CPU)
        self.jpeg_decoder, self.jpeg_decoder_reason = select_jpeg_decoder(predictor.device)
        self.stats = stats if stats is not None else PipelineStats()
        self.bad_inputs = {kind: 0 for kind in BAD_INPUT_KINDS}
        self._camera_info: dict[str, CameraCalibration] = {}
        self._input_lock = threading.Lock()     # sync + camera info
        self._pose_lock = threading.Lock()
        self._count_lock = threading.Lock()
        self._decoder_pool = ThreadPoolExecutor(max_workers=max(1, min(len(self.camera_names),
                                                                       os.cpu_count() or 1)))

    # ----------------------------------------------------------------- inputs (callbacks)
    def count_bad_input(self, error: BadInput) -> BadInput:
        """Count a bad input found outside the pipeline (e.g. while converting a message)."""
        with self._count_lock:
            self.bad_inputs[error.kind] += 1
        return error

    def on_image(self, camera: str, stamp: float, image: EncodedImage, now: float,
                 header: Any = None) -> bool:
        """Feed one camera message (not decoded yet). ``now``: node clock (s), 0 if not
        running yet. Returns True if it completed a set (now waiting for the worker)."""
        if camera not in self.camera_names:
            raise self.count_bad_input(
                BadInput("unknown_camera", f"camera {camera!r} is not configured"))
        if not np.isfinite(stamp) or (now > 0 and stamp > now + self.settings.max_future):
            raise self.count_bad_input(BadInput(
                "future_stamp", f"{camera} stamp {stamp:.3f} is {stamp - now:.3f} s ahead of "
                f"the clock ({now:.3f})"))
        with self._input_lock:
            complete = self.sync.add(camera, stamp, (image, header))
        for camera_set in complete:
            camera_set.completed_at = time.monotonic()
            self.stats.record_complete_set()
            self.waiting.put(camera_set)
        return bool(complete)

    def on_camera_info(self, camera: str, K, height: int, width: int, frame_id: str) -> None:
        """Store a camera's intrinsics and image size (the last valid CameraInfo wins)."""
        if camera not in self.camera_names:
            raise self.count_bad_input(
                BadInput("unknown_camera", f"camera {camera!r} is not configured"))
        try:
            calibration = check_intrinsics(K, height, width, frame_id,
                                           self.settings.intrinsics)
        except BadInput as error:
            raise self.count_bad_input(error) from None
        with self._input_lock:
            first = camera not in self._camera_info
            self._camera_info[camera] = calibration
        if first:          # a set may be waiting for it (its CameraInfo came after it)
            self.waiting.notify()

    def on_pose(self, stamp: float, T_global_from_ego) -> None:
        """Odometry: one T_global_from_ego sample."""
        try:
            with self._pose_lock:
                self.poses.add(stamp, T_global_from_ego)
        except BadInput as error:
            raise self.count_bad_input(error) from None
        self.waiting.notify()

    def transforms_arrived(self) -> None:
        """New data behind ``pose_lookup`` / ``extrinsics`` (a TF message): a waiting set may
        be ready now."""
        self.waiting.notify()

    def _buffer_lookup(self, stamp: float) -> np.ndarray:
        with self._pose_lock:
            return self.poses.lookup(stamp)

    # ------------------------------------------------------------------------- worker
    def next_set(self, timeout: float | None = None) -> CameraSet | None:
        """The newest complete set ready to prepare: its look-ups succeed, fail for good, or
        waited ``pose_wait`` in vain (then ``prepare`` counts the miss). None on timeout."""
        return self.waiting.get(timeout)

    def process(self, camera_set: CameraSet) -> OnlineResult:
        """Run one complete set through the model. Raises (counted) BadInput to skip it."""
        return self.infer(self.prepare(camera_set))

    def prepare(self, camera_set: CameraSet) -> PreparedSet:
        """Everything before the model: look-ups and decoding. Raises (counted) BadInput."""
        try:
            return self._prepare(camera_set)
        except BadInput as error:
            raise self.count_bad_input(error) from None

    def infer(self, prepared: PreparedSet) -> OnlineResult:
        """The model on a prepared set."""
        camera_set = prepared.camera_set
        if prepared.ready is not None:
            DeviceJpegDecoder.hand_over(prepared.images, prepared.ready)
        prediction = self.predictor.step(prepared.images, prepared.ego2img,
                                         prepared.reference_pose,
                                         camera_set.reference_stamp, prepared.bounds)
        timings = dict(prediction.timings)
        timings.update(prepared.timings)
        return OnlineResult(stamp=camera_set.reference_stamp,
                            header=camera_set.payloads[camera_set.reference_camera][1],
                            grid=prediction.grid, confidence=prediction.confidence,
                            boxes=prediction.boxes, timings=timings,
                            num_frames=prediction.num_frames, observed=prediction.observed,
                            received=camera_set.completed_at,
                            query_budget=prediction.query_budget,
                            refined_fraction=prediction.refined_fraction)

    # ---------------------------------------------------------------- decoding ahead
    def start_decoding(self, on_bad_input: Callable[[BadInput], None],
                       on_error: Callable[[], None]) -> None:
        """Prepare (decode) sets in a thread of their own, ahead of the model: while the
        model runs on set n, set n+1 is decoded. Take the results with ``next_prepared``.

        One prepared set waits at most; a newer one replaces it (counted in
        stale_sets_dropped), so the model always starts on the newest set decoded, in
        stamp order. Once the model's and the decoding's durations are known, the thread
        decodes the newest set just before the model will want it (pacing.py): one decode
        per output, not one per set that arrives. A bad set is counted and
        ``on_bad_input(error)`` called; any other exception calls ``on_error()`` inside its
        ``except`` block (for the traceback)."""
        def run():
            while not self.waiting.closed:
                if not self.pacing.wait_until_due(timeout=0.2):
                    continue
                camera_set = self.waiting.get(timeout=0.2)
                if camera_set is None:
                    continue
                try:
                    start = time.monotonic()
                    prepared = self.prepare(camera_set)
                    self.pacing.decoded(time.monotonic() - start)
                    self.prepared.put(prepared)
                except BadInput as error:
                    on_bad_input(error)
                except Exception:     # never let the thread die silently
                    on_error()

        self._decoding = threading.Thread(target=run, name="odg_decode", daemon=True)
        self._decoding.start()

    def next_prepared(self, timeout: float | None = None) -> PreparedSet | None:
        """The newest set prepared by ``start_decoding``'s thread (None on timeout). Call it
        when done with the previous one: that tells the decoding thread how long a set
        takes."""
        self.pacing.ready()
        prepared = self.prepared.get(timeout)
        if prepared is not None:
            self.pacing.taken()
        return prepared

    def _ready(self, camera_set: CameraSet, final: bool) -> str:
        """WaitingSets' probe: READY, FAILED (a look-up fails for good) or PENDING (one waits
        for data not received yet). ``final``: its wait ran out (a source that can settle
        does so: extrinsics auto takes the rig file)."""
        start = time.perf_counter()
        try:
            looked_up = self._look_up(camera_set, settle=final)
        except BadInput as error:
            return PENDING if error.pending else FAILED
        # kept for prepare (the set is handed on next): the look-ups are not done twice
        camera_set.looked_up = (looked_up, time.perf_counter() - start)
        return READY

    def _look_up(self, camera_set: CameraSet, settle: bool = False):
        """(camera infos, poses [1 + N, 4, 4]: the reference stamp's then each camera's,
        sensor2ego [N, 4, 4]) of a set; raises BadInput (pending where the data may come)."""
        names = self.camera_names
        with self._input_lock:
            infos = {c: self._camera_info.get(c) for c in names}
        missing = [c for c in names if infos[c] is None]
        if missing:
            # pending: a player publishes each CameraInfo with its image, and the first set
            # can complete before the callback of its last CameraInfo has run
            raise BadInput("missing_camera_info", f"no valid CameraInfo yet for {missing}",
                           pending=True)

        # Cheap checks before the expensive decoding, each kind for the whole set at once
        # (stacked: NumPy on 4x4 matrices costs its per-call overhead, not arithmetic). The
        # newest stamp first: while a set waits for its poses, that is the one missing.
        stamps = [camera_set.reference_stamp] + [camera_set.stamps[c] for c in names]
        order = sorted(range(len(stamps)), key=lambda i: -stamps[i])
        looked_up = [None] * len(stamps)
        for i in order:
            looked_up[i] = self.pose_lookup(stamps[i])
        poses = _stacked_transforms(looked_up)
        for i in np.flatnonzero(~rigid_mask(poses))[:1]:
            raise BadInput("bad_pose", f"pose at t={stamps[i]:.3f} is not a finite rigid "
                           "transform")
        sensor2ego = _stacked_transforms([self._extrinsics(c, infos[c].frame_id,
                                                           camera_set.stamps[c], settle)
                                          for c in names])
        for i in np.flatnonzero(~rigid_mask(sensor2ego))[:1]:
            raise BadInput("missing_extrinsics", f"extrinsics of {names[i]} are not rigid")
        return infos, poses, sensor2ego

    def _extrinsics(self, camera: str, frame_id: str, stamp: float, settle: bool):
        try:
            return self.extrinsics(camera, frame_id, stamp)
        except BadInput as error:
            settle_source = getattr(self.extrinsics, "settle", None)
            if not (settle and error.pending and settle_source is not None):
                raise
        settle_source(camera, frame_id)
        return self.extrinsics(camera, frame_id, stamp)

    def _prepare(self, camera_set: CameraSet) -> PreparedSet:
        names = self.camera_names
        t_lookup = time.perf_counter()
        try:
            if camera_set.looked_up is not None:
                (infos, poses, sensor2ego), seconds = camera_set.looked_up
                camera_set.looked_up = None
                t_lookup -= seconds                   # timed as it was done, in the probe
            else:
                infos, poses, sensor2ego = self._look_up(camera_set)
        except BadInput as error:
            if not error.pending:
                raise
            waited = (f"still missing after waiting {camera_set.waited:.2f} s (pose_wait "
                      f"{self.settings.pose_wait:g} s)" if camera_set.expired
                      else "not received (yet)")
            raise BadInput(error.kind, f"{waited}: {error.message}") from None
        try:
            intrinsics = np.stack([adjust_intrinsics(infos[c].intrinsics, infos[c].image_hw,
                                                     self.input_hw) for c in names])
        except ValueError as error:      # a CameraInfo size no network input is made of
            raise BadInput("wrong_image_size", str(error)) from None
        reference_pose = poses[0]
        ego2img = set_ego2img(intrinsics, sensor2ego, poses[1:], reference_pose)

        t0 = time.perf_counter()
        on_device = None
        if self.jpeg_decoder is not None:      # all-JPEG sets on the GPU; None: not all JPEG
            on_device = self.jpeg_decoder.decode_set(
                [camera_set.payloads[c][0] for c in names], names,
                [infos[c].image_hw for c in names], self.input_hw,
                self.settings.max_image_pixels)
        if on_device is not None:
            images, ready = on_device
        else:
            # each decoding worker writes its camera into the set's array: the copy runs in
            # the pool, in parallel, instead of a stack of six images in this thread
            images, ready = np.empty((len(names), *self.input_hw, 3), np.uint8), None

            def decode_into(i: int) -> None:
                images[i] = self._decode(names[i], camera_set.payloads[names[i]][0],
                                         infos[names[i]])

            for _ in self._decoder_pool.map(decode_into, range(len(names))):
                pass
        bounds = image_bounds([infos[c].image_hw for c in names], self.input_hw)
        return PreparedSet(camera_set, images, ego2img, reference_pose,
                           {"lookup": t0 - t_lookup,
                            "decode_images": time.perf_counter() - t0}, ready, bounds)

    def _decode(self, camera: str, image: EncodedImage, info: CameraCalibration) -> np.ndarray:
        try:
            rgb, original_hw = decode_for_input(image, self.input_hw, info.image_hw,
                                                self.settings.max_image_pixels)
            return to_network_input(rgb, info.image_hw, info.intrinsics, self.input_hw,
                                    original_hw)[0]
        except BadInput as error:
            raise BadInput(error.kind, f"{camera}: {error.message}") from None

    # ---------------------------------------------------------------------- reporting
    def counters(self) -> dict[str, int]:
        """Every skip/drop counter (bad inputs by kind, sync, mailbox, resets)."""
        with self._count_lock:
            out = dict(self.bad_inputs)
        with self._input_lock:
            sync = dict(self.sync.counters)
        out["dropped_incomplete_sets"] = sync["dropped_incomplete"]
        out["late_messages"] = sync["late_messages"]
        out["duplicate_messages"] = sync["duplicate_messages"]
        out["input_time_jumps"] = sync["time_jumps"]
        out["sets_completed"] = sync["sets_emitted"]
        out["pose_teleports"] = self.poses.teleports
        out["stale_sets_dropped"] = self.waiting.dropped + self.prepared.dropped
        out["sets_waited"] = self.waiting.waited
        out["sets_waiting"] = len(self.waiting)
        history_resets = self.predictor.history.resets
        out["history_resets_time_backwards"] = history_resets["time_backwards"]
        out["history_resets_gap"] = history_resets["gap"]
        out["history_resets_teleport"] = history_resets["teleport"]
        return out

    def close(self) -> None:
        self.waiting.close()
        self.prepared.close()
        self.pacing.close()
        if self._decoding is not None:
            self._decoding.join(timeout=5.0)
        self._decoder_pool.shutdown(wait=False, cancel_futures=True)


def _stacked_transforms(matrices) -> np.ndarray:
    """float64 [M, 4, 4] of looked-up transforms; one of another shape becomes NaN (so the
    rigidity check that follows rejects it, naming it, as it does a non-rigid one)."""
    out = np.full((len(matrices), 4, 4), np.nan)
    for i, T in enumerate(matrices):
        T = np.asarray(T, dtype=np.float64)
        if T.shape == (4, 4):
            out[i] = T
    return out
