"""The host side of the exported step (``odg export --onnx``, onnx_export.py): camera sets
in, the graph's named inputs out, and the history of features carried from run to run.

NumPy and Pillow only (no torch: a deployment needs onnxruntime and this package), and the
node's own functions for every number it makes, so the graph sees what the node's step sees:

- ``camera_set_geometry``: CameraInfo K and image size, the extrinsics (T_ego_from_cam) and
  the ego poses (T_global_from_ego) at each camera's stamp and at the set's reference stamp
  -> ego2img and image_bounds of the set (rig.check_intrinsics, preprocess.adjust_intrinsics,
  rig.set_ego2img, preprocess.image_bounds: as the node's pipeline);
- ``network_input``: camera images -> the network input (preprocess.resize_crop);
- ``StepInputs``: the history the node keeps (history.FrameHistory: resets on a time jump,
  a gap or a teleport; a set closer than ``min_interval`` to the last one kept takes its
  place) -> the named inputs in time order (history.history_geometry), and the features
  the graph returned, fed back at the next run.

    session = onnxruntime.InferenceSession("odg_step.onnx")
    feeder = StepInputs.for_session(session)
    for each camera set:
        ego2img, bounds = camera_set_geometry(K, image_hws, sensor2ego, camera_poses,
                                              reference_pose, feeder.input_hw)
        out = feeder.run(session, network_input(images, feeder.input_hw), ego2img,
                         reference_pose, reference_stamp, bounds)
        out["labels"], out["observed"], out["boxes"][out["valid"]], ...

A runtime of its own (TensorRT, onnxruntime with I/O binding) calls ``feeds`` before each
run and ``keep`` with the returned history after it.
"""
from __future__ import annotations

import math
from typing import Sequence

import numpy as np

from ..geometry import invert_projections, is_rigid
from ..preprocess import adjust_intrinsics, image_bounds, resize_crop
from .history import Frame, FrameHistory, history_geometry
from .camera_calibration import IntrinsicsRange, check_intrinsics, set_ego2img

# the node's defaults (config/odg_node.schema.yaml: history_max_gap, max_speed,
# history_interval); a test keeps them equal
MAX_GAP, MAX_SPEED, MIN_INTERVAL = 1.0, 70.0, 0.45
_DTYPES = {"tensor(float)": np.float32, "tensor(float16)": np.float16}


def camera_set_geometry(intrinsics, image_hws, sensor2ego, camera_poses, reference_pose,
                        input_hw, plausible: IntrinsicsRange | None = IntrinsicsRange()):
    """One camera set's projections, as the node makes them.

    intrinsics [N, 3, 3]: each camera's CameraInfo K (of its original image); image_hws [N]
    (H, W): those images' sizes; sensor2ego [N, 4, 4]: T_ego_from_cam; camera_poses
    [N, 4, 4]: T_global_from_ego at each camera's own stamp; reference_pose [4, 4]:
    T_global_from_ego at the set's reference stamp (the first camera's); input_hw: the
    network input (H', W'), cameras in the training rig's order
    -> ego2img float64 [N, 4, 4]: the set's ego frame (at the reference stamp) -> network-input
    pixels (u*d, v*d, d, 1), [K' 0; 0 1] @ inv(sensor2ego) @ inv(P(t_n)) @ P(t_ref) with K'
    the intrinsics after the resize and crop; image_bounds float32 [N, 4] (u0, v0, u1, v1):
    each camera's whole image in network-input pixels.

    Raises online.errors.BadInput (kind bad_camera_info / implausible_camera_info /
    wrong_image_size) for an unusable camera, ValueError for a transform that is not rigid.
    """
    from .errors import BadInput
    K = np.asarray(intrinsics, dtype=np.float64)
    N = len(K)
    if K.shape != (N, 3, 3) or len(image_hws) != N:
        raise ValueError(f"intrinsics {K.shape} and {len(image_hws)} image sizes: expected "
                         "[N, 3, 3] and N (H, W)")
    adjusted = []
    for n in range(N):
        height, width = (int(v) for v in image_hws[n])
        check_intrinsics(K[n], height, width, f"camera {n}", plausible)
        try:
            adjusted.append(adjust_intrinsics(K[n], (height, width), input_hw))
        except ValueError as error:        # an image no network input can be made of
            raise BadInput("wrong_image_size", str(error)) from None
    ego2img = set_ego2img(np.stack(adjusted), _transforms(sensor2ego, N, "sensor2ego"),
                          _transforms(camera_poses, N, "camera_poses"),
                          _transforms(reference_pose, None, "reference_pose"))
    return ego2img, image_bounds(image_hws, input_hw)


def network_input(images: Sequence[np.ndarray], input_hw) -> np.ndarray:
    """Camera images (each uint8 [H, W, 3] RGB, of the size its CameraInfo gives) -> uint8
    [N, H', W', 3], resized to the input width and cropped at the top (preprocess)."""
    return np.stack([resize_crop(np.asarray(image), tuple(input_hw)) for image in images])


class StepInputs:
    """The history of the node's predictor, for the exported step: one call to ``feeds``
    per camera set, in stamp order, then ``keep`` with what the graph returned (``run``
    does both). feature_shapes/feature_dtype: the graph's ``features_l`` inputs;
    max_gap, max_speed, min_interval: the node's history_max_gap, max_speed and
    history_interval (its defaults here)."""

    def __init__(self, num_cams: int, input_hw, feature_shapes, feature_dtype=np.float32,
                 max_gap: float = MAX_GAP, max_speed: float = MAX_SPEED,
                 min_interval: float = MIN_INTERVAL):
        shapes = [tuple(int(d) for d in shape) for shape in feature_shapes]
        if not shapes or len({s[0] for s in shapes}) != 1:
            raise ValueError(f"feature shapes {shapes}: expected [k, ...] per level")
        self.capacity = shapes[0][0]
        self.num_cams, self.input_hw = int(num_cams), tuple(int(v) for v in input_hw)
        self.history = FrameHistory(self.capacity, max_gap, max_speed)
        self.min_interval = float(min_interval)
        # the node allocates its ring as zeros too; slots are written before they are read
        self.features = [np.zeros(shape, feature_dtype) for shape in shapes]
        self.last_reset: str | None = None

    @classmethod
    def for_session(cls, session, **history_settings) -> "StepInputs":
        """The inputs of an onnxruntime session (or anything with ``get_inputs()`` of
        objects with name, shape and type) of an ``odg export --onnx`` graph."""
        inputs = {i.name: i for i in session.get_inputs()}
        missing = [name for name in ("images", "ego2img", "features_0") if name not in inputs]
        if missing:
            raise ValueError(f"the graph has no input {missing}: not a graph of "
                             f"odg export --onnx (inputs: {list(inputs)})")
        levels = sorted((name for name in inputs if name.startswith("features_")),
                        key=lambda name: int(name.split("_")[1]))
        dtype = _DTYPES.get(inputs["features_0"].type)
        if dtype is None:
            raise ValueError(f"features of type {inputs['features_0'].type}: NumPy feeds "
                             "float32 or float16 only")
        N, H, W, _ = inputs["images"].shape
        return cls(N, (H, W), [inputs[name].shape for name in levels], dtype,
                   **history_settings)

    def feeds(self, images: np.ndarray, ego2img: np.ndarray, pose: np.ndarray, stamp: float,
              bounds: np.ndarray | None = None) -> dict[str, np.ndarray]:
        """The current set -> every named input of the graph (the history included).

        images uint8 [N, H, W, 3] network input (``network_input``); ego2img [N, 4, 4] and
        bounds [N, 4] of the set (``camera_set_geometry``; bounds None: the network input
        itself); pose [4, 4] T_global_from_ego at the reference stamp ``stamp`` (s).
        The set joins the history (``last_reset``: why the history restarted, or None)."""
        images = np.asarray(images)
        ego2img = np.asarray(ego2img, dtype=np.float64)
        N, (H, W) = self.num_cams, self.input_hw
        if images.shape != (N, H, W, 3) or images.dtype != np.uint8:
            raise ValueError(f"images {images.dtype} {list(images.shape)}: expected uint8 "
                             f"[{N}, {H}, {W}, 3] (network_input)")
        if ego2img.shape != (N, 4, 4) or not np.isfinite(ego2img).all():
            raise ValueError(f"ego2img {list(ego2img.shape)}: expected finite [{N}, 4, 4]")
        pose = _transforms(pose, None, "pose")
        if not is_rigid(pose) or not math.isfinite(stamp):
            raise ValueError(f"pose {pose.tolist()} at stamp {stamp}: expected a rigid "
                             "transform at a finite stamp")
        bounds = np.broadcast_to(np.asarray((0.0, 0.0, W, H) if bounds is None else bounds,
                                            dtype=np.float32), (N, 4))
        # as OnlinePredictor.step: the newest kept frame is provisional while it is closer
        # than min_interval to the one before it; the current set then takes its place
        replace = self.history.newest_is_provisional(self.min_interval)
        self.last_reset = self.history.push(
            Frame(features=None, pose=pose, ego2img=ego2img,
                  stamp=float(stamp)), replace_newest=replace)
        frames = self.history.frames()
        k = self.capacity
        # frames in time order: the ring of the node with slot t holding frame t
        all_ego2img, warps, deltas, _ = history_geometry(frames, list(range(len(frames))),
                                                         k, k)
        feeds = {"images": np.ascontiguousarray(images),
                 "ego2img": all_ego2img.astype(np.float32),
                 "ego_warp": warps.astype(np.float32),
                 "time_delta": deltas.astype(np.float32),
                 "history_length": np.array([len(frames)], np.int64),
                 "replace_newest": np.array([replace and self.last_reset is None]),
                 "img2ego": invert_projections(ego2img).astype(np.float32),
                 "image_bounds": np.ascontiguousarray(bounds)}
        feeds.update({f"features_{level}": f for level, f in enumerate(self.features)})
        return feeds

    def keep(self, history_out: Sequence[np.ndarray]) -> None:
        """The graph's ``features_l_out``, in level order: the next run's ``features_l``."""
        if [np.shape(h) for h in history_out] != [f.shape for f in self.features]:
            raise ValueError("feature outputs of shapes "
                             f"{[list(np.shape(h)) for h in history_out]}, expected "
                             f"{[list(f.shape) for f in self.features]}")
        self.features = [np.asarray(h) for h in history_out]

    def run(self, session, images, ego2img, pose, stamp, bounds=None) -> dict[str, np.ndarray]:
        """``feeds``, an onnxruntime ``session.run`` and ``keep`` -> the outputs by name."""
        names = [o.name for o in session.get_outputs()]
        outputs = dict(zip(names, session.run(None, self.feeds(images, ego2img, pose, stamp,
                                                               bounds))))
        self.keep([outputs[f"features_{level}_out"] for level in range(len(self.features))])
        return outputs

    def reset(self) -> None:
        """Forget the history (the next set starts a new one)."""
        self.history.clear()


def _transforms(matrices, count: int | None, name: str) -> np.ndarray:
    """float64 [count, 4, 4] (or [4, 4] for count None) or a ValueError naming ``name``."""
    T = np.asarray(matrices, dtype=np.float64)
    shape = (4, 4) if count is None else (count, 4, 4)
    if T.shape != shape:
        raise ValueError(f"{name} {list(T.shape)}: expected {list(shape)}")
    return T

