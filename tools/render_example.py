"""See the renderer work: a synthetic street of Gaussians rendered into the nuScenes rig, and
the timing of a training-size render.

    python -m tools.render_example --out docs/results/render_example.png
    python -m tools.render_example --bench

The street (road, sidewalks, facades, trees, cars, pedestrians; one-hot class features) exists
only to make conventions visible in a picture: ground at the bottom of the images, near things
occluding far ones, classes in their places. The benchmark uses the rendering loss's
training workload: Gaussians scattered at random in the 80 x 80 x 6 m occupancy box,
6 cameras at 128 x 352, 2,000 supervised pixels per camera, forward + backward.
"""
from __future__ import annotations

import argparse
import time

import numpy as np
import torch
import yaml

from odg_ros.classes import OCC_CLASSES, OCC_COLORS, NUM_OCC_CLASSES
from odg_ros.geometry import invert_transform, make_transform
from odg_ros.preprocess import adjust_intrinsics
from odg_ros.resources import resource_path
from odg_ros.render.splat import render_cameras

IMAGE_HW = (128, 352)


def nuscenes_rig(image_hw=IMAGE_HW):
    """(camera names, cam_from_ego [6, 4, 4], intrinsics [6, 3, 3]) of config/rig_nuscenes.yaml,
    intrinsics adjusted to the network input size (float32 torch)."""
    rig = yaml.safe_load(resource_path("config/rig_nuscenes.yaml").read_text())["cameras"]
    names, cams, ks = [], [], []
    for name, cam in rig.items():
        ego_from_cam = make_transform(cam["sensor2ego"]["rotation"],
                                      cam["sensor2ego"]["translation"])
        names.append(name)
        cams.append(invert_transform(ego_from_cam))
        ks.append(adjust_intrinsics(np.asarray(cam["intrinsics"]), cam["image_size"], image_hw))
    return names, torch.tensor(np.stack(cams)).float(), torch.tensor(np.stack(ks)).float()


def _box_of_points(rng, centre, size, spacing):
    """Points on a regular grid filling an axis-aligned box (jittered a little)."""
    axes = [np.arange(-s / 2 + spacing / 2, s / 2, spacing) if s > spacing else np.zeros(1)
            for s in size]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    return grid + np.asarray(centre) + rng.normal(0, spacing * 0.1, grid.shape)


def street_scene(seed: int = 0):
    """Gaussians of a straight street along ego x. -> dict of float32 tensors: means [G, 3],
    scales [G, 3], rotations [G, 4], opacities [G], features [G, 17] (one-hot), labels [G]."""
    rng = np.random.default_rng(seed)
    parts = []   # (points [n, 3], scale [3], label)

    def add(points, scale, label):
        parts.append((points, np.broadcast_to(np.asarray(scale, float), points.shape), label))

    label = OCC_CLASSES.index
    add(_box_of_points(rng, (0, 0, 0), (80, 12, 0), 0.8), (0.5, 0.5, 0.05),
        label("driveable_surface"))
    for side in (-1, 1):
        add(_box_of_points(rng, (0, side * 7.5, 0.15), (80, 3, 0), 0.8), (0.5, 0.5, 0.05),
            label("sidewalk"))
        add(_box_of_points(rng, (0, side * 12, 2.7), (80, 0, 5.4), 0.8), (0.5, 0.05, 0.5),
            label("manmade"))
        for x in np.arange(-36, 40, 9.0):
            add(_box_of_points(rng, (x + side * 2, side * 10, 3.5), (2.4, 2.4, 2.4), 0.6),
                (0.4, 0.4, 0.4), label("vegetation"))
            add(_box_of_points(rng, (x + side * 2, side * 10, 1.2), (0, 0, 2.4), 0.4),
                (0.12, 0.12, 0.25), label("vegetation"))
        for x in (-14.0, 5.0, 22.0):
            add(_box_of_points(rng, (x + side, side * 7.5, 0.9), (0.4, 0.4, 1.6), 0.2),
                (0.12, 0.12, 0.15), label("pedestrian"))
    for x, y in ((9.0, -2.5), (16.0, 2.5), (-10.0, -2.5), (30.0, -2.5), (-22.0, 2.5),
                 (3.0, 9.5)):
        add(_box_of_points(rng, (x, y, 0.85), (4.4, 1.8, 1.5), 0.3), (0.2, 0.2, 0.2),
            label("car"))
    means = np.concatenate([p for p, _, _ in parts])
    scales = np.concatenate([s for _, s, _ in parts]) * rng.uniform(0.8, 1.2, means.shape)
    labels = np.concatenate([np.full(len(p), c) for p, _, c in parts])
    g = len(means)
    return dict(
        means=torch.tensor(means).float(),
        scales=torch.tensor(scales).float(),
        rotations=torch.tensor([[1.0, 0.0, 0.0, 0.0]]).repeat(g, 1),
        opacities=torch.full((g,), 0.9),
        features=torch.nn.functional.one_hot(torch.tensor(labels), NUM_OCC_CLASSES).float(),
        labels=torch.tensor(labels),
    )


def render_images(scene, cam_from_ego, intrinsics, image_hw=IMAGE_HW):
    """Every pixel of every camera. -> depth [N, H, W], features [N, H, W, C], alpha [N, H, W]."""
    height, width = image_hw
    v, u = torch.meshgrid(torch.arange(height) + 0.5, torch.arange(width) + 0.5, indexing="ij")
    pixels = torch.stack([u.flatten(), v.flatten()], -1)
    n = cam_from_ego.shape[0]
    with torch.no_grad():
        results = render_cameras(scene["means"], scene["scales"], scene["rotations"],
                                 scene["opacities"], scene["features"], cam_from_ego, intrinsics,
                                 [pixels] * n, image_hw)
    depth = torch.stack([r.depth for r in results]).reshape(n, height, width)
    features = torch.stack([r.features for r in results]).reshape(n, height, width, -1)
    alpha = torch.stack([r.alpha for r in results]).reshape(n, height, width)
    return depth, features, alpha


def save_picture(path, names, depth, features, alpha):
    """Semantic (argmax, black where alpha < 0.5) and depth (/ alpha) maps of each camera."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    colours = torch.tensor(OCC_COLORS[:NUM_OCC_CLASSES], dtype=torch.float32) / 255.0
    order = [2, 0, 1, 4, 3, 5]   # front-left, front, front-right / back-left, back, back-right
    fig, axes = plt.subplots(4, 3, figsize=(15, 6.4))
    for slot, cam in enumerate(order):
        row, col = 2 * (slot // 3), slot % 3
        semantic = colours[features[cam].argmax(-1)] * (alpha[cam] >= 0.5)[..., None]
        axes[row, col].imshow(semantic.numpy())
        axes[row, col].set_title(f"{names[cam]}: semantics", fontsize=9)
        expected_depth = (depth[cam] / alpha[cam].clamp_min(1e-6)).masked_fill(
            alpha[cam] < 0.5, float("nan"))
        im = axes[row + 1, col].imshow(expected_depth.numpy(), cmap="turbo", vmin=0, vmax=40)
        axes[row + 1, col].set_title(f"{names[cam]}: depth / alpha (m)", fontsize=9)
    for ax in axes.flat:
        ax.set_xticks([])
        ax.set_yticks([])
    fig.colorbar(im, ax=axes, fraction=0.015, pad=0.01, label="depth (m)")
    fig.suptitle("odg_ros.render: a synthetic street of Gaussians in the nuScenes rig "
                 f"({IMAGE_HW[0]}x{IMAGE_HW[1]}, every pixel)", fontsize=11)
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)


def random_gaussians(num_gaussians: int, seed: int = 0, scale_range=(0.05, 0.4)):
    """Gaussians scattered uniformly in the 80 x 80 x 6 m box [-40, 40]^2 x [-1, 5] around the
    ego, random orientations, opacities U(0.1, 0.9), scales U(scale_range) per axis,
    17 softmax features; all requiring grad."""
    gen = torch.Generator().manual_seed(seed)
    lo, hi = scale_range
    means = torch.rand(num_gaussians, 3, generator=gen) * torch.tensor([80.0, 80.0, 6.0]) \
        - torch.tensor([40.0, 40.0, 1.0])
    tensors = [means,
               torch.rand(num_gaussians, 3, generator=gen) * (hi - lo) + lo,
               torch.nn.functional.normalize(torch.randn(num_gaussians, 4, generator=gen), dim=-1),
               torch.rand(num_gaussians, generator=gen) * 0.8 + 0.1,
               torch.softmax(torch.randn(num_gaussians, NUM_OCC_CLASSES, generator=gen), -1)]
    return [t.requires_grad_(True) for t in tensors]


def benchmark(sizes=(9_600, 76_800), pixels_per_camera: int = 2_000, repeats: int = 3,
              scale_range=(0.05, 0.4)):
    """Median wall time of forward and backward of a 6-camera render. -> list of dicts."""
    _, cam_from_ego, intrinsics = nuscenes_rig()
    gen = torch.Generator().manual_seed(1)
    pixels = [torch.rand(pixels_per_camera, 2, generator=gen)
              * torch.tensor([IMAGE_HW[1], IMAGE_HW[0]], dtype=torch.float32) for _ in range(6)]
    rows = []
    for size in sizes:
        forward, backward = [], []
        for repeat in range(repeats):
            params = random_gaussians(size, seed=repeat, scale_range=scale_range)
            t0 = time.perf_counter()
            results = render_cameras(*params, cam_from_ego, intrinsics, pixels, IMAGE_HW)
            t1 = time.perf_counter()
            loss = sum(r.depth.mean() + r.features.mean() + r.alpha.mean() for r in results)
            loss.backward()
            t2 = time.perf_counter()
            forward.append(t1 - t0)
            backward.append(t2 - t1)
        alpha = torch.cat([r.alpha.detach() for r in results])
        rows.append(dict(gaussians=size, forward_ms=1e3 * float(np.median(forward)),
                         backward_ms=1e3 * float(np.median(backward)),
                         mean_alpha=float(alpha.mean())))
    return rows


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", default="render_example.png", help="picture to write")
    parser.add_argument("--bench", action="store_true", help="time a training-size render")
    parser.add_argument("--threads", type=int, default=0, help="torch threads (0: keep)")
    args = parser.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    if args.bench:
        print(f"torch threads: {torch.get_num_threads()}")
        for scale_range in ((0.05, 0.4), (0.1, 1.0)):
            for row in benchmark(scale_range=scale_range):
                print(f"{row['gaussians']:>6} Gaussians, scales U{scale_range} m: forward "
                      f"{row['forward_ms']:.0f} ms, backward {row['backward_ms']:.0f} ms "
                      f"(6 cameras x 2000 pixels; mean alpha {row['mean_alpha']:.3f})")
        return 0
    names, cam_from_ego, intrinsics = nuscenes_rig()
    scene = street_scene()
    t0 = time.perf_counter()
    depth, features, alpha = render_images(scene, cam_from_ego, intrinsics)
    print(f"{len(scene['means'])} Gaussians, 6 x {IMAGE_HW[0]}x{IMAGE_HW[1]} pixels rendered in "
          f"{time.perf_counter() - t0:.2f} s")
    save_picture(args.out, names, depth, features, alpha)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
