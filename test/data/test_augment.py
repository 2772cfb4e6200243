"""Training augmentation: after every geometric augmentation a GT voxel, a box centre and a
render target still project onto the same image content; flip twice is the identity; the
photometric distortion changes colours only."""
import numpy as np
import pytest
import torch

from odg_ros.data.augment import (augment_batch, flip_sample, photometric_distortion,
                                  resize_crop_sample)
from odg_ros.geometry import ego_to_image, invert_transform
from odg_ros.nuscenes_cameras import ring_cameras

HW = (48, 96)
PC_RANGE = (-40.0, -40.0, -1.0, 40.0, 40.0, 5.4)
VOXEL = 0.4
GRID = (200, 200, 16)


def smooth_images(frames, cams):
    """Images whose colour varies slowly and differently per camera and channel, so that a
    bilinear read at a sub-pixel position identifies the place."""
    v, u = torch.meshgrid(torch.arange(HW[0]) + 0.5, torch.arange(HW[1]) + 0.5, indexing="ij")
    images = torch.empty(frames, cams, 3, *HW)
    for t in range(frames):
        for n in range(cams):
            for c in range(3):
                images[t, n, c] = (torch.sin(u / (9.0 + 2 * c) + n) + torch.cos(v / 7.0 + t)
                                   + 0.01 * u)
    return images


def make_batch(seed=0):
    g = torch.Generator().manual_seed(seed)
    K, T_ego_cam = ring_cameras(HW)
    cam_from_ego = np.stack([invert_transform(t) for t in T_ego_cam])
    ego2img = torch.from_numpy(np.stack([ego_to_image(k, t) for k, t in zip(K, T_ego_cam)]))
    T = 2
    warp = torch.eye(4).repeat(T, 1, 1)
    warp[1, 0, 3] = 3.0
    warp[1, 1, 3] = 1.0
    boxes = torch.tensor([[12.0, 3.0, 0.5, 1.8, 4.5, 1.6, 0.4, 5.0, 1.5],
                          [-9.0, -6.0, 0.8, 0.7, 0.8, 1.7, -2.0, 0.0, -1.0]])
    points = torch.tensor([[15.0, 2.0, 0.3], [10.0, -1.5, 1.0], [-12.0, 4.0, 0.0]])
    targets = []
    for n in range(6):
        h = torch.cat([points, torch.ones(3, 1)], 1).double() @ ego2img[n].T
        uvd = torch.cat([h[:, :2] / h[:, 2:3], h[:, 2:3]], 1).float()
        keep = (uvd[:, 2] > 0.1) & (uvd[:, 0] >= 0) & (uvd[:, 0] < HW[1]) & \
               (uvd[:, 1] >= 0) & (uvd[:, 1] < HW[0])
        targets.append(torch.cat([uvd[keep], torch.full((int(keep.sum()), 1), 3.0)], 1))
    sample = {
        "images": smooth_images(T, 6),
        "ego2img": ego2img.float().expand(T, -1, -1, -1).clone(),
        "ego_warp": warp, "time_delta": torch.tensor([0.0, 0.5]),
        "intrinsics": torch.from_numpy(K).float(),
        "cam_from_ego": torch.from_numpy(cam_from_ego).float(),
        "occ_semantics": torch.randint(0, 18, GRID, generator=g, dtype=torch.uint8),
        "occ_mask_camera": torch.rand(GRID, generator=g) > 0.5,
        "occ_mask_lidar": torch.rand(GRID, generator=g) > 0.5,
        "gt_boxes": boxes, "gt_labels": torch.tensor([0, 8]),
        "render_targets": targets, "token": "t", "has_occ": True}
    return sample


def read(images, n, uv):
    """Bilinear colour [3] of camera n's image [N, 3, H, W] at continuous pixel uv."""
    grid = torch.tensor([[[[uv[0] / HW[1] * 2 - 1, uv[1] / HW[0] * 2 - 1]]]], dtype=torch.float32)
    return torch.nn.functional.grid_sample(images[n:n + 1], grid, align_corners=False)[0, :, 0, 0]


def project(ego2img, n, point):
    h = ego2img[n].double() @ torch.tensor([*point, 1.0], dtype=torch.float64)
    return (h[:2] / h[2]).tolist(), float(h[2])


def voxel_centre(index):
    return [PC_RANGE[a] + (index[a] + 0.5) * VOXEL for a in range(3)]


def visible(ego2img, point, margin=3.0, cameras=None):
    """(first camera among ``cameras`` that sees ``point`` inside a margin, its pixel)."""
    for n in (range(ego2img.shape[0]) if cameras is None else cameras):
        (u, v), d = project(ego2img, n, point)
        if d > 1 and margin <= u < HW[1] - margin and margin <= v < HW[0] - margin:
            return n, (u, v)
    return None


def seen_voxels(sample, count=20):
    """GT voxels seen by some current-frame camera, with (camera, pixel, colour, label)."""
    found = []
    for i in range(60, 200, 7):
        for j in range(0, 200, 11):
            index = (i if (i + j) % 2 else 199 - i, j, 3)
            hit = visible(sample["ego2img"][0], voxel_centre(index))
            if hit:
                n, uv = hit
                found.append((index, n, read(sample["images"][0], n, uv),
                              int(sample["occ_semantics"][index])))
            if len(found) == count:
                return found
    return found


def mirrored(index, flipped):
    return (index[0], GRID[1] - 1 - index[1], index[2]) if flipped else index


@pytest.mark.parametrize("flip,scale,offset", [(True, 1.0, (0.0, 0.0)),
                                               (False, 1.08, (5.0, 2.5)),
                                               (False, 0.92, (-4.0, -3.0)),
                                               (True, 1.05, (2.0, 1.0))])
def test_gt_voxels_boxes_and_render_targets_keep_their_image_content(flip, scale, offset):
    sample = make_batch()
    before = seen_voxels(sample)
    assert len(before) >= 10
    box_colours = []
    for box in sample["gt_boxes"]:
        hit = visible(sample["ego2img"][0], box[:3].tolist())
        box_colours.append(read(sample["images"][0], hit[0], hit[1]) if hit else None)
    target_colours = [[read(sample["images"][0], n, t[:2].tolist()) for t in targets]
                      for n, targets in enumerate(sample["render_targets"])]
    aug = dict(sample)
    if flip:
        flip_sample(aug, PC_RANGE)
    resize_crop_sample(aug, scale, offset)
    checked = 0
    # the same camera (a zoomed-out neighbour may show the point in its empty border)
    for index, n, colour, label in before:
        new_index = mirrored(index, flip)
        assert int(aug["occ_semantics"][new_index]) == label
        assert bool(aug["occ_mask_camera"][new_index]) == bool(sample["occ_mask_camera"][index])
        hit = visible(aug["ego2img"][0], voxel_centre(new_index), margin=1.0, cameras=[n])
        if hit is None:   # zoomed / cropped out of every camera
            continue
        torch.testing.assert_close(read(aug["images"][0], *hit), colour, atol=0.03, rtol=0)
        checked += 1
    assert checked >= 5
    # history frame 1: a static voxel carried by ego_warp reads the same past content
    checked = 0
    for index, _, _, _ in before:
        def in_frame_1(batch, idx):
            x = torch.tensor([*voxel_centre(idx), 1.0])
            return (batch["ego_warp"][1] @ x)[:3].tolist()
        old = visible(sample["ego2img"][1], in_frame_1(sample, index))
        new = old and visible(aug["ego2img"][1], in_frame_1(aug, mirrored(index, flip)),
                              margin=1.0, cameras=[old[0]])
        if old is None or new is None:
            continue
        torch.testing.assert_close(read(aug["images"][1], *new),
                                   read(sample["images"][1], *old), atol=0.03, rtol=0)
        checked += 1
    assert checked >= 5
    boxes_checked = 0
    for box, new_box, colour in zip(sample["gt_boxes"], aug["gt_boxes"], box_colours):
        old = visible(sample["ego2img"][0], box[:3].tolist())
        hit = old and visible(aug["ego2img"][0], new_box[:3].tolist(), margin=1.0,
                              cameras=[old[0]])
        if hit:
            boxes_checked += 1
            torch.testing.assert_close(read(aug["images"][0], *hit), colour, atol=0.03, rtol=0)
    assert boxes_checked >= 1
    for n, targets in enumerate(aug["render_targets"]):
        for t in targets:   # each kept target still lies on its point's pixel content
            hits = [c for c in target_colours[n]
                    if torch.allclose(read(aug["images"][0], n, t[:2].tolist()), c, atol=0.03)]
            assert hits, (n, t)
    # the intrinsics and extrinsics still compose to ego2img, and stay a rigid transform
    composed = torch.zeros(6, 4, 4)
    composed[:, :3, :3] = aug["intrinsics"]
    composed[:, 3, 3] = 1
    torch.testing.assert_close(composed @ aug["cam_from_ego"], aug["ego2img"][0], atol=1e-3,
                               rtol=1e-5)
    R = aug["cam_from_ego"][:, :3, :3]
    torch.testing.assert_close(torch.linalg.det(R), torch.ones(6), atol=1e-5, rtol=0)


def test_flip_mirrors_boxes_and_velocities_and_twice_is_the_identity():
    sample = make_batch()
    once = dict(sample)
    flip_sample(once, PC_RANGE)
    box, flipped = sample["gt_boxes"][0], once["gt_boxes"][0]

    def corners(b):
        c, s = np.cos(float(b[6])), np.sin(float(b[6]))
        half = np.array([[1, 1], [1, -1], [-1, -1], [-1, 1]]) * [float(b[4]) / 2, float(b[3]) / 2]
        return {tuple(np.round(b[:2].numpy() + [c * x - s * y, s * x + c * y], 4))
                for x, y in half}
    assert corners(flipped) == {(x, -y) for x, y in corners(box)}
    assert flipped[8] == -box[8] and flipped[7] == box[7]
    twice = dict(once)
    flip_sample(twice, PC_RANGE)
    for key, value in sample.items():
        if torch.is_tensor(value):
            torch.testing.assert_close(twice[key], value, atol=1e-5, rtol=0, msg=key)
        elif key == "render_targets":
            for a, b in zip(twice[key], value):
                torch.testing.assert_close(a, b, atol=1e-5, rtol=0)


def test_flip_refuses_a_grid_not_symmetric_in_y():
    with pytest.raises(ValueError, match="symmetric in y"):
        flip_sample(make_batch(), (-40.0, -30.0, -1.0, 40.0, 40.0, 5.4))


def test_photometric_distortion_changes_colours_only_and_stays_in_range():
    torch.manual_seed(0)
    images = make_batch()["images"].clamp(-2.0, 2.0)
    out = photometric_distortion(images)
    assert out.shape == images.shape and torch.isfinite(out).all()
    assert not torch.equal(out, images)
    from odg_ros.preprocess import IMAGENET_MEAN, IMAGENET_STD
    low = (0 - torch.tensor(IMAGENET_MEAN)) / torch.tensor(IMAGENET_STD)
    high = (1 - torch.tensor(IMAGENET_MEAN)) / torch.tensor(IMAGENET_STD)
    assert (out >= low.view(3, 1, 1) - 1e-5).all() and (out <= high.view(3, 1, 1) + 1e-5).all()


def test_augment_batch_draws_per_sample_and_leaves_the_input_alone():
    samples = [make_batch(0), make_batch(1)]
    batch = {k: (torch.stack([s[k] for s in samples]) if torch.is_tensor(samples[0][k])
                 else [s[k] for s in samples]) for k in samples[0]}
    original = batch["ego2img"].clone()
    g = torch.Generator().manual_seed(3)
    out = augment_batch(batch, PC_RANGE, generator=g)
    assert torch.equal(batch["ego2img"], original)
    assert out["images"].shape == batch["images"].shape
    assert out["token"] == batch["token"] and len(out["render_targets"]) == 2
    assert not torch.equal(out["ego2img"], original)


@pytest.mark.parametrize("flip_probability", [0.0, 1.0])
def test_augmentation_never_waits_for_the_device(flip_probability):
    # with the CUDA paths forced every tensor counts as a device tensor, except those a CUDA
    # run keeps on the host: the render targets (to_device leaves them) and host draws
    from odg_ros.data.batch import collate, to_device
    from odg_ros.bench.census import Census, CensusMode, batch_host_tensors
    batch = to_device(collate([make_batch(0), make_batch(1)]), "cpu")
    augment_batch(batch, PC_RANGE, flip_probability=1.0)   # a first step makes the constants
    census = Census()
    with CensusMode(census, None, batch_host_tensors(batch)):
        out = augment_batch(batch, PC_RANGE, zoom=(1.05, 1.1),
                            flip_probability=flip_probability)
    assert sum(census.ops.values()) > 20                              # it ran, on the device
    assert sum(census.syncs.values()) == 0, census.report()
    assert all(len(t) <= len(s) for o, b in zip(out["render_targets"], batch["render_targets"])
               for t, s in zip(o, b))


def test_to_device_leaves_the_targets_on_the_host():
    from odg_ros.data.batch import collate, to_device
    batch = collate([make_batch(0)])
    moved = to_device(batch, "meta")
    assert moved["images"].device.type == "meta" and moved["ego2img"].device.type == "meta"
    assert moved["render_targets"][0][0] is batch["render_targets"][0][0]
    for key in ("occ_semantics", "occ_mask_camera", "gt_boxes", "gt_labels"):
        assert moved[key] is batch[key], key
