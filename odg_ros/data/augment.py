"""Training-time data augmentation of a collated batch, on whatever device the batch is on
(the trainer applies it after moving the batch to the GPU, where it costs a few kernels).

Per sample (as OPUS / SparseBEV train, adapted to our already resized network input):
- **flip** (probability 0.5): the world mirrored about the ego x-z plane (y -> -y) in every
  frame. The images are flipped left-right, and every quantity follows: ego2img' =
  F_img ego2img F, ego_warp' = F ego_warp F, cam_from_ego' = F_cam cam_from_ego F (still a
  rigid transform: two reflections), intrinsics' = F_img K F_cam (cx' = W - cx), occupancy
  GT and masks mirrored along y, boxes (y, yaw, vy) -> (-y, -yaw, -vy), render targets
  u -> W - u. F = diag(1, -1, 1), F_cam = diag(-1, 1, 1), F_img: u -> W - u.
- **resize-and-crop**: the image zoomed by s in ``ZOOM`` about its origin and shifted by a
  random crop offset, every camera and frame alike: pixel (u, v) -> (s u - ox, s v - oy),
  folded into ego2img and the intrinsics; render targets follow (those leaving the image
  are dropped, one per pixel kept: the nearest). Pixels from outside the source image are 0
  (the mean colour after normalisation).
  Render targets stay where the batch keeps them: on the host (``batch.to_device``), so their
  filtering and de-duplication, whose sizes depend on the data, never wait for the device.
- **photometric distortion** of each image independently, each part with probability 0.5:
  brightness +-32/255, contrast x [0.5, 1.5], saturation x [0.5, 1.5] (hue is not varied).
Evaluation never calls it. Geometry is float32 on the batch's device. Random draws come from a
host generator, by default torch's global CPU generator (saved and restored with a resumed
run's RNG state): reading a draw never waits for the device.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F

from ..preprocess import IMAGENET_MEAN, IMAGENET_STD
from ..transfer import device_constant, upload

ZOOM = (0.9, 1.1)
FLIP_PROBABILITY = 0.5
BRIGHTNESS = 32.0 / 255.0
CONTRAST = (0.5, 1.5)
SATURATION = (0.5, 1.5)


def uniform(low: float, high: float, generator: torch.Generator) -> float:
    return low + (high - low) * float(torch.rand((), generator=generator))


def augment_batch(batch: dict, pc_range, generator: torch.Generator | None = None,
                  zoom=ZOOM, flip_probability: float = FLIP_PROBABILITY,
                  photometric: bool = True) -> dict:
    """A new batch dict, every sample augmented (module docstring); ``batch`` is unchanged.
    ``generator``: a CPU generator for the random parameters (None: the global one)."""
    generator = torch.default_generator if generator is None else generator
    if generator.device.type != "cpu":
        raise ValueError(f"augmentation draws on a host generator, got one on {generator.device}")
    out = dict(batch)
    B = batch["images"].shape[0]
    samples = [dict((k, v[b]) for k, v in batch.items()
                    if torch.is_tensor(v) or isinstance(v, list)) for b in range(B)]
    if flip_probability > 0:
        # made whether or not a sample flips, so that the first step makes them, whatever
        # it draws, and no later step waits for their upload
        flip_constants(batch["images"].shape[-1], batch["images"].device)
    for sample in samples:
        if float(torch.rand((), generator=generator)) < flip_probability:
            flip_sample(sample, pc_range)
        s = uniform(*zoom, generator)
        H, W = sample["images"].shape[-2:]
        spare_x, spare_y = (s - 1.0) * W, (s - 1.0) * H
        offset = (uniform(min(0.0, spare_x), max(0.0, spare_x), generator),
                  uniform(min(0.0, spare_y), max(0.0, spare_y), generator))
        resize_crop_sample(sample, s, offset)
        if photometric:
            sample["images"] = photometric_distortion(sample["images"], generator)
    for key, value in batch.items():
        if torch.is_tensor(value):
            out[key] = torch.stack([s[key] for s in samples])
        elif isinstance(value, list) and key in samples[0]:
            out[key] = [s[key] for s in samples]
    return out


# ---------------------------------------------------------------------------- flip
# The flip's matrices are constants of the device (writing an element of a device tensor
# from the host would be a copy that the host waits for).
def mirror_y(device, dtype=torch.float32) -> torch.Tensor:
    return device_constant(_diagonal(1.0, -1.0, 1.0, 1.0), device, dtype)


def image_flip(width: float, device, dtype=torch.float32) -> torch.Tensor:
    """4x4 acting on (u d, v d, d, 1): u -> width - u."""
    return device_constant(((-1.0, 0.0, float(width), 0.0), (0.0, 1.0, 0.0, 0.0),
                            (0.0, 0.0, 1.0, 0.0), (0.0, 0.0, 0.0, 1.0)), device, dtype)


def flip_constants(width: float, device):
    """(mirror in y, image flip, camera-frame flip) of images ``width`` pixels wide."""
    return (mirror_y(device), image_flip(width, device),
            device_constant(_diagonal(-1.0, 1.0, 1.0, 1.0), device))


def _diagonal(*values: float) -> tuple:
    return tuple(tuple(v if i == j else 0.0 for j in range(len(values)))
                 for i, v in enumerate(values))


def flip_sample(sample: dict, pc_range) -> None:
    """Mirror one sample's world about the ego x-z plane, in place (module docstring)."""
    if abs(pc_range[1] + pc_range[4]) > 1e-6:
        raise ValueError(f"flip needs a grid symmetric in y, pc_range is {tuple(pc_range)}")
    images = sample["images"]
    device, W = images.device, images.shape[-1]
    Fy, Fimg, Fcam = flip_constants(W, device)
    sample["images"] = images.flip(-1)
    sample["ego2img"] = Fimg @ sample["ego2img"].float() @ Fy
    sample["ego_warp"] = Fy @ sample["ego_warp"].float() @ Fy
    if "cam_from_ego" in sample:
        sample["cam_from_ego"] = Fcam @ sample["cam_from_ego"].float() @ Fy
    if "intrinsics" in sample:
        sample["intrinsics"] = Fimg[:3, :3] @ sample["intrinsics"].float() @ Fcam[:3, :3]
    for key in ("occ_semantics", "occ_mask_camera", "occ_mask_lidar"):
        if key in sample:
            sample[key] = sample[key].flip(1)
    if "gt_boxes" in sample:
        boxes = sample["gt_boxes"].clone()
        boxes[:, 1], boxes[:, 6], boxes[:, 8] = -boxes[:, 1], -boxes[:, 6], -boxes[:, 8]
        sample["gt_boxes"] = boxes
    if "render_targets" in sample:
        flipped = []
        for t in sample["render_targets"]:
            t = t.clone()
            t[:, 0] = W - t[:, 0]
            flipped.append(t)
        sample["render_targets"] = flipped


# ---------------------------------------------------------------------------- resize-and-crop
def resize_crop_sample(sample: dict, scale: float, offset) -> None:
    """Zoom every image of one sample by ``scale`` and shift it by ``offset`` = (ox, oy)
    pixels: (u, v) -> (scale u - ox, scale v - oy); in place, geometry updated."""
    images = sample["images"]                                          # [T, N, 3, H, W]
    H, W = images.shape[-2:]
    ox, oy = offset
    device = images.device
    # output pixel centre (i + 0.5) reads the source at ((i + 0.5) + o) / s
    u = (torch.arange(W, device=device, dtype=torch.float32) + 0.5 + ox) / scale
    v = (torch.arange(H, device=device, dtype=torch.float32) + 0.5 + oy) / scale
    grid = torch.stack([(u / W * 2 - 1)[None, :].expand(H, W),
                        (v / H * 2 - 1)[:, None].expand(H, W)], dim=-1)
    flat = images.flatten(0, 1)
    resampled = F.grid_sample(flat.float(), grid.expand(flat.shape[0], H, W, 2),
                              mode="bilinear", padding_mode="zeros", align_corners=False)
    sample["images"] = resampled.to(images.dtype).view_as(images)
    # made on the host from the drawn numbers, sent in one non-blocking copy
    A = upload(torch.tensor([[scale, 0.0, -ox, 0.0], [0.0, scale, -oy, 0.0],
                             [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]]), device)
    sample["ego2img"] = A @ sample["ego2img"].float()
    if "intrinsics" in sample:
        sample["intrinsics"] = A[:3, :3] @ sample["intrinsics"].float()
    if "render_targets" in sample:
        sample["render_targets"] = [resize_targets(t, scale, offset, (H, W))
                                    for t in sample["render_targets"]]


def resize_targets(targets: torch.Tensor, scale: float, offset, image_hw) -> torch.Tensor:
    """(u, v, depth, label) rows moved as their pixels; off-image ones dropped, one per pixel
    (the nearest) kept."""
    H, W = image_hw
    t = targets.clone()
    t[:, 0] = t[:, 0] * scale - offset[0]
    t[:, 1] = t[:, 1] * scale - offset[1]
    t = t[(t[:, 0] >= 0) & (t[:, 0] < W) & (t[:, 1] >= 0) & (t[:, 1] < H)]
    if len(t) < 2:
        return t
    t = t[t[:, 2].argsort(stable=True)]                                # nearest first
    pixel = t[:, 1].long() * W + t[:, 0].long()
    _, inverse = pixel.unique(return_inverse=True)
    first = torch.full((int(inverse.max()) + 1,), len(t), device=t.device, dtype=torch.long)
    first = first.scatter_reduce(0, inverse, torch.arange(len(t), device=t.device), "amin")
    return t[first.sort().values]


# ---------------------------------------------------------------------------- photometric
def photometric_distortion(images: torch.Tensor, generator=None) -> torch.Tensor:
    """images [..., 3, H, W] normalised -> distorted, each image independently."""
    shape = images.shape
    flat = images.reshape(-1, 3, *shape[-2:]).float()
    n, device = flat.shape[0], flat.device
    mean = device_constant(IMAGENET_MEAN, device).view(1, 3, 1, 1)
    std = device_constant(IMAGENET_STD, device).view(1, 3, 1, 1)
    rgb = flat * std + mean                                            # [0, 1]

    def draw(low, high, identity):   # per image: a factor with probability 0.5, else identity
        on = torch.rand(n, generator=generator) < 0.5
        value = low + (high - low) * torch.rand(n, generator=generator)
        return upload(torch.where(on, value, torch.full_like(value, identity)),
                      device).view(n, 1, 1, 1)

    rgb = rgb + draw(-BRIGHTNESS, BRIGHTNESS, 0.0)
    rgb = rgb * draw(*CONTRAST, 1.0)
    gray = (0.299 * rgb[:, 0:1] + 0.587 * rgb[:, 1:2] + 0.114 * rgb[:, 2:3])
    rgb = gray + (rgb - gray) * draw(*SATURATION, 1.0)
    return ((rgb.clamp(0.0, 1.0) - mean) / std).to(images.dtype).view(shape)
