"""The contract between data, model, losses and metrics.

Infos file (written by ``odg prepare``, read by the dataset, ``odg score`` and ``odg eval``):
a pickle of ``{"version": str, "dataset": "nuscenes" | "waymo", "dataroot": str,
"infos": [keyframe, ...]}`` with keyframes sorted by scene, then time. One keyframe::

    token, scene_token, scene_name, timestamp (int, microseconds), frame_index (in scene)
    ego_pose        4x4 T_global_from_ego at the LiDAR stamp
    lidar_path      path relative to dataroot; lidar2ego 4x4
    lidarseg_path   per-point labels (nuScenes-lidarseg) relative to dataroot, "" when none
    cams            {CAM_NAME: camera}, the keyframe's set, in rig.CAMERA_NAMES order
    sweeps          [{CAM_NAME: camera}, ...] earlier camera sets, newest first (12 Hz sweeps)
    occ_path        labels.npz path relative to the occ root ("" when there is no GT)
    gt_boxes        float [M, 9] (cx, cy, cz, w, l, h, yaw, vx, vy) in this keyframe's ego frame
    gt_labels       int [M] index into classes.BOX_CLASSES
  camera = {data_path, timestamp, intrinsics 3x3 (original image), sensor2ego 4x4,
            ego_pose 4x4 T_global_from_ego at the camera's own stamp, image_hw (H, W)}

Model-ready sample (``OccDataset.__getitem__``), T frames (0 = current, then older), N cameras::

    images          uint8 [T, N, H, W, 3]    RGB network input, not yet normalised (a quarter
                                             of float32's bytes to copy and pin); ``to_device``
                                             makes it the model's float32 [T, N, 3, H, W]
    ego2img         float32 [T, N, 4, 4]     frame t's ego -> input pixels (geometry.ego_to_image)
    ego_warp        float32 [T, 4, 4]        T_ego(t)_from_ego(0); identity at t = 0
    time_delta      float32 [T]              t_0 - t_t in seconds (>= 0)
    intrinsics      float32 [N, 3, 3]        current frame, of the network input image
    cam_from_ego    float32 [N, 4, 4]        current frame (ego2img[0] = [K 0; 0 1] @ cam_from_ego)
    occ_semantics   uint8 [X, Y, Z]          Occ3D labels (17 = free), X=Y=200, Z=16
    occ_mask_camera bool  [X, Y, Z]
    occ_mask_lidar  bool  [X, Y, Z]
    gt_boxes        float32 [M, 9]           as in the infos
    gt_labels       int64 [M]
    render_targets  list of N float32 [P_n, 4]  (u, v, depth, occ label) LiDAR points in each
                                             current-frame camera, input pixels, depth in m
    token           str
    has_occ         bool                     False when the keyframe has no GT file (all free)
``collate`` stacks the tensors into a leading batch dim B and keeps the rest as lists;
``to_device`` uploads a batch and normalises its images there (preprocess.normalize). The
targets (``HOST_KEYS``) stay on the host: the augmentation moves them there, and the losses
check them and take the sizes that depend on them (occupied voxels, render pixels kept in
view) without waiting for the device, then upload what they use.
"""
from __future__ import annotations

import torch

from ..preprocess import normalize

STACKED_KEYS = ("images", "ego2img", "ego_warp", "time_delta", "intrinsics", "cam_from_ego",
                "occ_semantics", "occ_mask_camera", "occ_mask_lidar")

# checked, filtered and sampled on the host, where their sizes are known without waiting
HOST_KEYS = ("occ_semantics", "occ_mask_camera", "occ_mask_lidar", "gt_boxes", "gt_labels",
             "render_targets")


def collate(samples: list[dict]) -> dict:
    batch = {}
    for key in samples[0]:
        values = [s[key] for s in samples]
        batch[key] = torch.stack(values) if key in STACKED_KEYS else values
    return batch


def tensors_in(value):
    """The tensors in ``value``: a tensor, or lists and tuples of them nested to any depth."""
    if torch.is_tensor(value):
        yield value
    elif isinstance(value, (list, tuple)):
        for item in value:
            yield from tensors_in(item)


def to_device(batch: dict, device) -> dict:
    """A collated batch on ``device``: tensors (and lists of them) copied, uint8 images
    normalised there (float images are taken as normalised already). Copies from pinned
    memory do not block the host; nothing else is read back. The targets (``HOST_KEYS``)
    stay where they are (module docstring)."""
    out = {}
    for key, value in batch.items():
        if key in HOST_KEYS:
            out[key] = value
        elif torch.is_tensor(value):
            out[key] = value.to(device, non_blocking=True)
        elif isinstance(value, list) and value and torch.is_tensor(value[0]):
            out[key] = [v.to(device, non_blocking=True) for v in value]
        elif isinstance(value, list) and value and isinstance(value[0], list):
            out[key] = [[t.to(device, non_blocking=True) for t in v] for v in value]
        else:
            out[key] = value
    images = out.get("images")
    if torch.is_tensor(images) and images.dtype == torch.uint8:
        out["images"] = normalize(images)
    return out
