"""Host syncs and CPU time of one renderer call (forward + backward), this code against an
earlier revision of odg_ros/render/splat.py, in one process, interleaved, medians.

    python -m tools.bench_render [--against main] [--gaussians 3000] [--pixels 400]
        [--chunk 1000000] [--repeats 12] [--scenes 1]

Scene: six cameras around the ego, random Gaussians in a 20 x 20 x 4 m box, random pixels.
Host syncs are counted with the CUDA paths forced (odg_ros.bench.census); a smaller --chunk
makes more depth batches. --scenes K renders K such scenes of their own Gaussians (as the
render loss renders its decoder layers): in one render_scenes call where the code has it,
else in K render_cameras calls.
"""
import argparse
import math
import statistics
import time

import torch

from tools.revision import module_at
from odg_ros.render import splat
from odg_ros.bench.census import Census, CensusMode

HEIGHT, WIDTH = 64, 176


def scene(num_gaussians: int, num_pixels: int, num_cameras: int = 6, seed: int = 1):
    g = torch.Generator().manual_seed(seed)
    means = (torch.rand(num_gaussians, 3, generator=g) - 0.5) * torch.tensor([20.0, 20.0, 4.0])
    scales = torch.rand(num_gaussians, 3, generator=g) * 0.8 + 0.05
    rotations = torch.randn(num_gaussians, 4, generator=g)
    opacities = torch.rand(num_gaussians, generator=g)
    features = torch.rand(num_gaussians, 5, generator=g)
    cams = []
    for n in range(num_cameras):
        s, c = math.sin(2 * math.pi * n / num_cameras), math.cos(2 * math.pi * n / num_cameras)
        cam = torch.eye(4)
        cam[:3, :3] = torch.tensor([[s, -c, 0.0], [0.0, 0.0, -1.0], [c, s, 0.0]])
        cams.append(cam)
    k = torch.tensor([[80.0, 0, WIDTH / 2], [0, 80.0, HEIGHT / 2], [0, 0, 1]])
    pixels = [torch.rand(num_pixels, 2, generator=g) * torch.tensor([WIDTH, HEIGHT])
              for _ in range(num_cameras)]
    gaussians = [t.requires_grad_() for t in (means, scales, rotations, opacities, features)]
    return gaussians, torch.stack(cams), k.expand(num_cameras, 3, 3).contiguous(), pixels


def call(module, args) -> tuple[float, float]:
    module.CANDIDATE_CHUNK = args.chunk
    scenes = [scene(args.gaussians, args.pixels, seed=1 + i) for i in range(args.scenes)]
    _, cams, k, pixels = scenes[0]              # the same cameras and pixels for every scene
    start, start_cpu = time.perf_counter(), time.process_time()
    if hasattr(module, "render_scenes"):
        results = module.render_scenes([gaussians for gaussians, *_ in scenes],
                                       cams.expand(len(scenes), -1, -1, -1),
                                       k.expand(len(scenes), -1, -1, -1),
                                       [pixels] * len(scenes), (HEIGHT, WIDTH))
    else:
        results = [module.render_cameras(*gaussians, cams, k, pixels, (HEIGHT, WIDTH))
                   for gaussians, *_ in scenes]
    sum(r.depth.sum() + r.features.sum() + r.alpha.sum()
        for per_scene in results for r in per_scene).backward()
    return time.perf_counter() - start, time.process_time() - start_cpu


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--against", default="main")
    parser.add_argument("--gaussians", type=int, default=3000)
    parser.add_argument("--pixels", type=int, default=400, help="per camera")
    parser.add_argument("--chunk", type=int, default=splat.CANDIDATE_CHUNK)
    parser.add_argument("--repeats", type=int, default=12)
    parser.add_argument("--scenes", type=int, default=1)
    args = parser.parse_args()
    versions = {"before": module_at(args.against, "odg_ros/render/splat.py"), "this": splat}
    seconds = {name: [] for name in versions}
    for name, module in versions.items():
        census = Census(steps=1)
        with CensusMode(census, None):
            call(module, args)
        print(f"{name:7s} host syncs per call: {sum(census.syncs.values())}")
    for i in range(args.repeats):
        for name in (list(versions) if i % 2 else list(versions)[::-1]):
            seconds[name].append(call(versions[name], args))
    for clock, column in (("wall", 0), ("CPU", 1)):     # CPU time: less hurt by a loaded machine
        median = {name: statistics.median(t[column] for t in times[2:])   # 2 warm-ups
                  for name, times in seconds.items()}
        print(f"median {clock} seconds per call: before {median['before']:.3f}, "
              f"this {median['this']:.3f}, this / before {median['this'] / median['before']:.2f}")


if __name__ == "__main__":
    main()
