"""OccDataset: infos (``odg prepare``) -> model-ready samples (contract in data/batch.py).

History frames. Frame 0 is the keyframe's camera set; frames 1..T-1 are earlier 12 Hz camera
sets, chosen as SparseBEV and OPUS do for their 8-frame models (``LoadMultiViewImageFrom
MultiSweeps``): with the earlier sets listed newest first, frame k takes set index
``k * interval - 1``.
* evaluation (``train=False``): interval 6, i.e. every 6th set ~ 0.5 s, the previous keyframes;
* training (``train=True``): one interval per sample drawn uniformly from 4..8, capped at
  ``len(sets) // (T - 1)``; when there are no more sets than history frames, all of them are taken.
When a scene has fewer earlier sets than needed, the oldest available set is repeated (indices
are clamped to it); a keyframe with no earlier set at all repeats itself (zero time delta,
identity warp), as SparseBEV does. The list of earlier sets is the keyframe's ``sweeps``,
continued with the previous keyframes of the same scene (their ``cams``, then their ``sweeps``)
when ``sweeps`` stops before the previous keyframe; sets missing a camera are skipped.

Geometry. Every camera image has its own ego pose (nuScenes stores one per image; the six
images of a set span ~42 ms). Frame t has one reference ego: for t = 0 the keyframe's ego pose
(LiDAR stamp), for t > 0 the ego pose of the set's first camera (CAM_FRONT). ``ego2img[t, n]``
takes a point in frame t's reference ego coordinates to camera n's input pixels *through the
ego pose at camera n's own stamp*:
    ego2img[t, n] = [K'_n 0; 0 1] @ inv(sensor2ego_n) @ inv(P_cam_n) @ P_ref_t
so the ego motion inside a set (up to ~0.6 m at 15 m/s) is not an error source. ``ego_warp[t]
= inv(P_ref_t) @ P_ref_0`` and ``time_delta[t] = (stamp_ref_0 - stamp_ref_t)`` in seconds, both
between the reference stamps. Static points therefore project exactly; dynamic points are off
by their own motion over the few ms between a camera's stamp and the frame's reference stamp.

Occupancy GT: ``occ_root / occ_path``; ``occ_root`` defaults as in ``odg score``: the infos'
optional ``occ_root`` (relative to ``dataroot``), else ``<dataroot>/gts`` (where the
Occ3D-nuScenes release unpacks). ``occ_path == ""`` means no GT: all-free semantics, False
masks and ``has_occ = False`` in the sample (an extra key next to the contract's). A non-empty
``occ_path`` whose file is missing is an error (a wrong ``occ_root`` must not train on "all free").

Render targets: the keyframe's LiDAR points (``lidar2ego``, keyframe ego) with their lidarseg
labels mapped to Occ3D classes, projected with ``ego2img[0]`` (data/lidar.py). Keyframes
without a lidarseg file (``lidarseg_path`` missing or "") get N empty [0, 4] tensors, and so do
Waymo keyframes (their LiDAR labels are not read).

Waymo infos (``dataset: "waymo"``): the cameras are the keyframe's ``cams`` in their stored
order (5), the GT is loaded with occ_io.load_occ3d_waymo (free = 15).

Works with DataLoader workers: ``__init__`` keeps only the infos in memory, every file is
opened and closed inside ``__getitem__``; the random interval uses torch's per-worker RNG
(``replay_history_draws`` brings a resumed run's worker to where the stopped one was).
"""
from __future__ import annotations

import bisect
from pathlib import Path

import numpy as np
import torch

from .. import geometry, preprocess
from ..model_config import ModelConfig
from ..nuscenes_cameras import CAMERA_NAMES
from . import lidar, occ_io
from .decode import read_image
from .lidarseg import lidarseg_to_occ
from .prepare import load_infos

EVAL_INTERVAL = 6          # SparseBEV/OPUS test_interval (12 Hz sets -> 0.5 s)
TRAIN_INTERVAL = (4, 8)    # SparseBEV/OPUS train_interval, inclusive


def select_history(num_sets: int, num_history: int, train: bool = False,
                   generator: torch.Generator | None = None) -> list[int]:
    """Indices into the newest-first list of earlier sets for history frames 1..num_history.

    -1 means "repeat the current set" (only when ``num_sets == 0``). See the module docstring.
    """
    if num_history <= 0:
        return []
    if num_sets == 0:
        return [-1] * num_history
    if not train:
        choices = [(k + 1) * EVAL_INTERVAL - 1 for k in range(num_history)]
    elif num_sets <= num_history:
        choices = list(range(num_sets)) + [num_sets - 1] * (num_history - num_sets)
    else:
        high = min(num_sets // num_history, TRAIN_INTERVAL[1])
        low = min(high, TRAIN_INTERVAL[0])
        interval = int(torch.randint(low, high + 1, (1,), generator=generator))
        choices = [(k + 1) * interval - 1 for k in range(num_history)]
    return [min(c, num_sets - 1) for c in choices]


def load_infos_file(path) -> dict:
    """Read an infos pickle (format in data/batch.py, ``odg prepare``) and check it."""
    return check_infos(load_infos(path), source=str(path))


def check_infos(infos, source: str = "infos") -> dict:
    if not isinstance(infos, dict) or not {"dataset", "dataroot", "infos"} <= set(infos):
        raise ValueError(f"{source}: not an infos dict with 'dataset', 'dataroot', 'infos'")
    if infos["dataset"] not in ("nuscenes", "waymo"):
        raise ValueError(f"{source}: unknown dataset {infos['dataset']!r}")
    if not infos["infos"]:
        raise ValueError(f"{source}: no keyframes")
    return infos


def _pose(matrix, what: str) -> np.ndarray:
    T = np.asarray(matrix, dtype=np.float64)
    if not geometry.is_rigid(T):
        raise ValueError(f"{what} is not a finite rigid 4x4 transform:\n{T}")
    return T


class OccDataset(torch.utils.data.Dataset):
    """Keyframes of an infos file as model-ready samples (data/batch.py).

    infos_path_or_dict  path of an infos pickle, or the loaded dict
    cfg                 ModelConfig: image_size, num_frames, num_cams, grid are used
    occ_root            folder the keyframes' ``occ_path`` are relative to
                        (default: infos' ``occ_root`` under dataroot, else ``<dataroot>/gts``)
    train               random history interval (module docstring); no other change
    dataroot            overrides the infos' ``dataroot`` (data moved to another disk)

    GT boxes: only those whose centre lies inside the grid's x-y range are kept.
    """

    def __init__(self, infos_path_or_dict, cfg: ModelConfig, occ_root=None, train: bool = False,
                 dataroot=None):
        if isinstance(infos_path_or_dict, dict):
            infos = check_infos(infos_path_or_dict)
        else:
            infos = load_infos_file(infos_path_or_dict)
        self.cfg = cfg
        self.train = train
        self.dataset = infos["dataset"]
        self.infos = infos["infos"]
        self.dataroot = Path(dataroot if dataroot is not None else infos["dataroot"])
        if occ_root is not None:
            self.occ_root = Path(occ_root)
        else:  # the rule of metrics/score.resolve_occ_root, so training and scoring agree
            self.occ_root = self.dataroot / (infos.get("occ_root") or "gts")
        if cfg.dataset != self.dataset:
            raise ValueError(f"the data is {self.dataset} (labels 0..{occ_io.free_label_of(self.dataset)}"
                             f", free last), the model config {cfg.name!r} has dataset="
                             f"{cfg.dataset!r}: use a {self.dataset} preset")
        self.image_size = tuple(cfg.image_size)
        self.grid_shape = tuple(cfg.grid_shape)
        cams = self.infos[0]["cams"]
        if self.dataset == "nuscenes":
            missing = [c for c in CAMERA_NAMES if c not in cams]
            if missing:
                raise ValueError(f"keyframe {self.infos[0]['token']} lacks cameras {missing}")
            self.camera_names = CAMERA_NAMES
        else:
            self.camera_names = tuple(cams)
        if len(self.camera_names) != cfg.num_cams:
            raise ValueError(f"the data has {len(self.camera_names)} cameras, the model config "
                             f"{cfg.name!r} expects num_cams={cfg.num_cams}")

    def __len__(self) -> int:
        return len(self.infos)

    # ---------------------------------------------------------------- history sets
    def history_choices(self, index: int) -> tuple[list[dict], list[int]]:
        """(earlier camera sets newest first, the ones history frames 1.. take); in training
        this draws the random interval from torch's global RNG (the worker's in a loader)."""
        num_history = self.cfg.num_frames - 1
        longest = TRAIN_INTERVAL[1] if self.train else EVAL_INTERVAL
        sets = self.earlier_sets(index, num_history * longest)
        return sets, select_history(len(sets), num_history, self.train)

    def _complete(self, cam_set) -> bool:
        return all(name in cam_set for name in self.camera_names)

    def earlier_sets(self, index: int, max_sets: int) -> list[dict]:
        """Up to ``max_sets`` complete camera sets before keyframe ``index``, newest first."""
        info = self.infos[index]
        oldest = info["cams"][self.camera_names[0]]["timestamp"]
        sets: list[dict] = []

        def extend(candidates):
            nonlocal oldest
            for cam_set in candidates:
                if len(sets) >= max_sets:
                    return
                if not self._complete(cam_set):
                    continue
                stamp = cam_set[self.camera_names[0]]["timestamp"]
                if stamp < oldest:  # strictly older: drops repeats when sweeps already span
                    sets.append(cam_set)
                    oldest = stamp

        extend(info.get("sweeps", []))
        k = index - 1
        while len(sets) < max_sets and k >= 0 and self.infos[k]["scene_token"] == info["scene_token"]:
            extend([self.infos[k]["cams"]])
            extend(self.infos[k].get("sweeps", []))
            k -= 1
        return sets

    # ---------------------------------------------------------------- geometry
    def frame_geometry(self, cam_set, T_global_from_ref):
        """ego2img [N,4,4], input intrinsics [N,3,3], cam_from_ego [N,4,4] of one set, with
        ``ego`` = the reference ego pose ``T_global_from_ref`` (module docstring)."""
        ego2img, intrinsics, cam_from_ego = [], [], []
        for name in self.camera_names:
            cam = cam_set[name]
            K = preprocess.adjust_intrinsics(cam["intrinsics"], cam["image_hw"], self.image_size)
            T_ref_from_cam = (geometry.invert_transform(T_global_from_ref)
                              @ _pose(cam["ego_pose"], f"{name} ego_pose")
                              @ _pose(cam["sensor2ego"], f"{name} sensor2ego"))
            ego2img.append(geometry.ego_to_image(K, T_ref_from_cam))
            intrinsics.append(K)
            cam_from_ego.append(geometry.invert_transform(T_ref_from_cam))
        return np.stack(ego2img), np.stack(intrinsics), np.stack(cam_from_ego)

    # ---------------------------------------------------------------- images
    def load_image(self, cam) -> np.ndarray:
        """One camera image -> network input uint8 [H, W, 3] (data/decode.py)."""
        return read_image(self.dataroot / cam["data_path"], self.image_size, cam["image_hw"])

    # ---------------------------------------------------------------- labels
    def load_occupancy(self, info):
        occ_path = info.get("occ_path", "")
        if not occ_path:
            return (*occ_io.empty_occ(self.dataset, self.grid_shape), False)
        path = self.occ_root / occ_path
        if not path.is_file():
            raise FileNotFoundError(
                f"keyframe {info['token']}: occupancy GT {path} not found (occ_root is "
                f"{self.occ_root}; pass the folder holding the Occ3D files as occ_root)")
        return (*occ_io.load_occ(path, self.dataset, self.grid_shape), True)

    def render_targets(self, info, ego2img0) -> list[torch.Tensor]:
        seg_path = info.get("lidarseg_path", "")
        lidar_path = info.get("lidar_path", "")
        empty = [torch.zeros((0, 4), dtype=torch.float32) for _ in self.camera_names]
        if (self.dataset != "nuscenes" or not seg_path or not lidar_path
                or not (self.dataroot / seg_path).is_file()):
            return empty  # Waymo's LiDAR segmentation labels are not read (yet)
        points = lidar.load_points(self.dataroot / lidar_path)
        labels = lidarseg_to_occ(lidar.load_lidarseg(self.dataroot / seg_path, len(points)))
        points_ego = lidar.transform_points(_pose(info["lidar2ego"], "lidar2ego"), points[:, :3])
        valid_heights = []
        for name in self.camera_names:
            hw = info["cams"][name]["image_hw"]
            _, crop_top, (resized_h, _) = preprocess.resize_crop_params(hw, self.image_size)
            valid_heights.append(resized_h - crop_top)
        targets = lidar.lidar_render_targets(points_ego, labels, ego2img0, self.image_size,
                                             valid_heights, num_classes=self.cfg.num_classes)
        return [torch.from_numpy(t) for t in targets]

    # ---------------------------------------------------------------- sample
    def __getitem__(self, index: int) -> dict:
        info = self.infos[index]
        sets, choices = self.history_choices(index)

        P_ref0 = _pose(info["ego_pose"], f"keyframe {info['token']} ego_pose")
        stamp0 = info["timestamp"]
        frames = [(info["cams"], P_ref0, stamp0)]
        for c in choices:
            if c < 0:
                frames.append(frames[0])
                continue
            first = sets[c][self.camera_names[0]]
            frames.append((sets[c], _pose(first["ego_pose"], f"{self.camera_names[0]} ego_pose"),
                           first["timestamp"]))

        ego2img, ego_warp, time_delta, decoded = [], [], [], {}
        images = np.empty((len(frames), len(self.camera_names), *self.image_size, 3), np.uint8)
        for t, (cam_set, P_ref, stamp) in enumerate(frames):
            matrices, K, cam_from_ego = self.frame_geometry(cam_set, P_ref)
            if t == 0:
                intrinsics0, cam_from_ego0 = K, cam_from_ego
            ego2img.append(matrices)
            ego_warp.append(geometry.ego_warp(P_ref0, P_ref))
            dt = (stamp0 - stamp) * 1e-6
            if dt < 0:
                raise ValueError(f"keyframe {info['token']}: history set at {stamp} is newer "
                                 f"than the keyframe ({stamp0})")
            time_delta.append(dt)
            for n, name in enumerate(self.camera_names):
                key = cam_set[name]["data_path"]
                if key not in decoded:
                    decoded[key] = self.load_image(cam_set[name])
                images[t, n] = decoded[key]
        ego2img = np.stack(ego2img)

        semantics, mask_lidar, mask_camera, has_occ = self.load_occupancy(info)
        gt_boxes = np.asarray(info.get("gt_boxes", np.zeros((0, 9))), dtype=np.float32)
        gt_boxes = gt_boxes.reshape(-1, 9)
        gt_labels = np.asarray(info.get("gt_labels", np.zeros(0)), dtype=np.int64).reshape(-1)
        if len(gt_labels) != len(gt_boxes):
            raise ValueError(f"keyframe {info['token']}: {len(gt_boxes)} boxes, "
                             f"{len(gt_labels)} labels")
        # Only the objects inside the grid's x-y range (mmdet3d's ObjectRangeFilter in the
        # SparseBEV / OPUS pipelines): the queries live in the grid, farther boxes (the infos
        # keep them up to the annotation range) would be targets no query can reach.
        inside = geometry.inside_bev_range(gt_boxes, self.cfg.pc_range)
        gt_boxes, gt_labels = gt_boxes[inside], gt_labels[inside]
        return {
            "images": torch.from_numpy(images),
            "ego2img": torch.from_numpy(ego2img).float(),
            "ego_warp": torch.from_numpy(np.stack(ego_warp)).float(),
            "time_delta": torch.tensor(time_delta, dtype=torch.float32),
            "intrinsics": torch.from_numpy(intrinsics0).float(),
            "cam_from_ego": torch.from_numpy(cam_from_ego0).float(),
            "occ_semantics": torch.from_numpy(np.ascontiguousarray(semantics)),
            "occ_mask_camera": torch.from_numpy(np.ascontiguousarray(mask_camera)),
            "occ_mask_lidar": torch.from_numpy(np.ascontiguousarray(mask_lidar)),
            "gt_boxes": torch.from_numpy(gt_boxes),
            "gt_labels": torch.from_numpy(gt_labels),
            "render_targets": self.render_targets(info, ego2img[0]),
            "token": info["token"],
            "has_occ": has_occ,
        }


def replay_history_draws(dataset: torch.utils.data.Dataset, indices) -> None:
    """Draw the random history intervals of samples ``indices`` of ``dataset`` (an OccDataset
    or a ConcatDataset of them) in that order, as ``__getitem__`` would, loading nothing: it
    brings a fresh loader worker's RNG to where an interrupted run's worker had it."""
    ends = getattr(dataset, "cumulative_sizes", None)
    for index in indices:
        if ends is None:
            dataset.history_choices(index)
            continue
        part = bisect.bisect_right(ends, index)
        dataset.datasets[part].history_choices(index - (ends[part - 1] if part else 0))
