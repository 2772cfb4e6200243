"""The online tests' tiny model and camera sets: a tiny checkpoint-free model, random sets for
the predictor, and the nuScenes rig at a reduced image size with PNG images fed to a pipeline
camera by camera."""
from __future__ import annotations

import io

import numpy as np
import torch
from PIL import Image
from torch.utils._python_dispatch import TorchDispatchMode

from odg_ros.geometry import make_transform
from odg_ros.network import ODG
from odg_ros.network.precision import precision_context
from odg_ros.online.images import EncodedImage
from odg_ros.online.camera_calibration import load_rig, set_ego2img
from odg_ros.preprocess import adjust_intrinsics
from odg_ros.resources import resource_path
from testing.helpers import tiny_config


def make_model():
    # thresholds 0: every point and box is kept, so the grids compared are not all free
    cfg = tiny_config(score_threshold=0.0, box_score_threshold=0.0)
    torch.manual_seed(0)
    return ODG(cfg).eval(), cfg


def stepped_predictor(steps, num_sets=4):
    """The tiny model (make_model) in an OnlinePredictor on the CPU (max_gap 1 s) after its
    first ``steps`` of ``num_sets`` random sets (make_sets) -> (predictor, model, cfg, sets)."""
    from odg_ros.online.predictor import OnlinePredictor
    model, cfg = make_model()
    sets = make_sets(cfg, num_sets)
    predictor = OnlinePredictor(model, cfg, "cpu", max_gap=1.0)
    for s in sets[:steps]:
        predictor.step(*s)
    return predictor, model, cfg, sets


def budget_model(need_threshold=0.0, **overrides):
    """The tiny model with trained-flagged random budget heads; no box passes its threshold
    (no object tracked)."""
    cfg = tiny_config(score_threshold=0.0, box_score_threshold=1.0, **overrides)
    torch.manual_seed(0)
    model = ODG(cfg).eval()
    model.decoder.budget_heads.set_trained(True, need_threshold)
    return model, cfg


@torch.inference_mode()
def raw_output(predictor, budget=None):
    """The decoder's full output (``ODGOutput``, every layer) over the predictor's ring as its
    last step saw it: the eager decoder run again on the step's packed geometry, to compare
    a step's raw outputs with a reference."""
    step = predictor.online_step
    ego2img, warps, deltas, frame_index, _ = step.layout.unpack(predictor._packed)
    with precision_context(predictor.precision, predictor.device):
        return step.model.decode_stored(step.ring.all_levels(), ego2img, warps, deltas,
                                        frame_index, False, budget=budget)


def eager_reference(model, cfg, **options):
    """An eager CPU predictor whose every kernel runs on torch's threads, as a traced,
    compiled or replayed step's do: the reference those are compared with bit for bit (the
    eager node runs its decoder on one thread, which sums in another order)."""
    from odg_ros.online.predictor import OnlinePredictor
    predictor = OnlinePredictor(model, cfg, "cpu", **options)
    predictor.online_step.parallel_encoder_only = False
    return predictor


def make_sets(cfg, num_sets, seed=0):
    """Random images and a car driving forward while turning, nuScenes rig."""
    rng = np.random.default_rng(seed)
    rig = load_rig(resource_path("config/rig_nuscenes.yaml"))
    cams = list(rig.cameras.values())
    K = np.stack([adjust_intrinsics(c.intrinsics, c.image_hw, cfg.image_size) for c in cams])
    sensor2ego = np.stack([c.sensor2ego for c in cams])
    sets = []
    for k in range(num_sets):
        stamp = 10.0 + 0.5 * k
        pose = make_transform([np.cos(0.05 * k), 0, 0, np.sin(0.05 * k)], (4.0 * k, 0.3 * k, 0))
        images = rng.integers(0, 256, (cfg.num_cams, *cfg.image_size, 3), dtype=np.uint8)
        ego2img = set_ego2img(K, sensor2ego, [pose] * len(cams), pose)
        sets.append((images, ego2img, pose, stamp))
    return sets


RIG = load_rig(resource_path("config/rig_nuscenes.yaml"))
CAMS = tuple(RIG.cameras)
HW = (144, 256)                                   # camera images (nuScenes / 6.25)
OFFSETS = (0.0, 0.008, 0.017, 0.025, 0.033, 0.042)


def scaled_K(name):
    return adjust_intrinsics(RIG.cameras[name].intrinsics, (900, 1600), HW)


def png(array):
    buffer = io.BytesIO()
    Image.fromarray(array).save(buffer, format="PNG")
    return buffer.getvalue()


def set_images(seed):
    rng = np.random.default_rng(seed)
    return [rng.integers(0, 256, (*HW, 3), dtype=np.uint8) for _ in CAMS]


def feed_set(pipeline, start, images, now=None, encode=png):
    completed = False
    for name, offset, image in zip(CAMS, OFFSETS, images):
        completed |= pipeline.on_image(name, start + offset, EncodedImage(True, "png",
                                                                          encode(image)),
                                       now=start + 0.1 if now is None else now,
                                       header=("stamp", start + offset))
    return completed


# Operators that make the host wait for the device on CUDA (a value read back, an output
# whose size depends on the data) or copy host data to the device inside the step.
HOST_SYNC_OPS = {"_local_scalar_dense", "item", "nonzero", "_unique2", "unique_dim",
                 "unique_consecutive", "masked_select", "bincount", "is_nonzero", "equal",
                 "lift_fresh", "lift_fresh_copy", "allclose", "_assert_async"}


class HostSyncCounter(TorchDispatchMode):
    """Counts the ATen ops run inside it and names those in HOST_SYNC_OPS."""

    def __init__(self):
        super().__init__()
        self.syncs, self.ops = [], 0

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        self.ops += 1
        name = func.overloadpacket.__name__
        boolean_index = name.startswith("index") and any(
            isinstance(i, torch.Tensor) and i.dtype == torch.bool
            for i in (args[1] if len(args) > 1 and isinstance(args[1], (list, tuple)) else ()))
        if name in HOST_SYNC_OPS or boolean_index or name == "repeat_interleave" and \
                "output_size" not in (kwargs or {}):
            self.syncs.append("boolean index" if boolean_index else name)
        return func(*args, **(kwargs or {}))


def _makes_the_host_wait(func, args, kwargs) -> bool:
    name = func.overloadpacket.__name__
    boolean_index = name.startswith("index") and any(
        isinstance(i, torch.Tensor) and i.dtype == torch.bool
        for i in (args[1] if len(args) > 1 and isinstance(args[1], (list, tuple)) else ()))
    return name in HOST_SYNC_OPS or boolean_index or (
        name == "repeat_interleave" and "output_size" not in (kwargs or {}))


class _OpRecorder(TorchDispatchMode):
    """Records every ATen op (with the tensor objects it took and made) of a capture; an op
    that makes the host wait fails, as it does while a CUDA stream is capturing."""

    def __init__(self):
        super().__init__()
        self.ops = []

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        if _makes_the_host_wait(func, args, kwargs):
            raise RuntimeError(f"{func}: operation not permitted when stream is capturing "
                               "(it makes the host wait for the device)")
        out = func(*args, **kwargs)
        self.ops.append((func, args, kwargs, out))
        return out


class RecordedGraph:
    """``predictor.CudaGraphStep`` on the CPU, replaying as a CUDA graph does: against the
    memory of the capture.

    The function runs twice (the warm-up), then once more while every ATen op it launches is
    recorded with the tensors it read and wrote. ``replay()`` re-runs the recorded ops, not
    the function: a tensor that existed before the capture (a static input buffer, a weight,
    the feature ring's memory) is the very tensor of the capture, every later one is the
    replay's own, and the results are copied into the capture's output tensors. So, as on a
    GPU, a buffer reassigned after the capture (``ring.use_memory(...)``, ``_packed = ...``) is
    neither read nor written by a replay, a Python value read during the capture (which
    budget, which slot) is frozen into the graph, an op that waits for the device fails the
    capture, and a result not copied out is overwritten by the next replay. Each instance is
    one graph; ``captured`` lists every capture made."""

    captured: list = []

    def __init__(self, function, images, packed, device):
        for _ in range(2):
            function(images, packed)
        with _OpRecorder() as recorder:
            outputs = function(images, packed)
        self.ops = recorder.ops
        self.outputs = list(outputs)
        self.replays = 0
        RecordedGraph.captured.append(self)

    def replay(self):
        made = {}                     # id(tensor of the capture) -> the replay's tensor

        def replayed(value):
            if isinstance(value, torch.Tensor):
                return made.get(id(value), value)
            if isinstance(value, (list, tuple)):
                return type(value)(replayed(v) for v in value)
            return value

        for func, args, kwargs, out in self.ops:
            result = func(*replayed(args), **{k: replayed(v) for k, v in kwargs.items()})
            for captured, new in zip(*(_tensors_of(x) for x in (out, result))):
                made[id(captured)] = new
        for static, value in zip(self.outputs, (made.get(id(o), o) for o in self.outputs)):
            if value is not static:
                static.copy_(value)
        self.replays += 1
        return self.outputs


def _tensors_of(value) -> list:
    if isinstance(value, torch.Tensor):
        return [value]
    if isinstance(value, (list, tuple)):
        return [t for v in value for t in _tensors_of(v)]
    return []
