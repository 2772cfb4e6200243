"""Small shared test utilities: a tiny model configuration, a tiny training split and checkpoint,
model inputs, a driving-like occupancy scene, and comparisons of outputs."""
import pickle

from odg_ros.model_config import load_preset


def tiny_config(**overrides):
    """A few-second model: every part of ODG, tiny sizes."""
    values = dict(name="tiny", backbone="resnet18", image_size=(64, 176), num_frames=3,
                  embed_dims=64, fpn_channels=64, ffn_dims=128, num_heads=4, num_static=20,
                  num_dynamic=6, points_per_layer=(1, 2, 2, 4, 4, 8), num_groups=4,
                  sampling_points=2, mixing_out_points=8)
    values.update(overrides)
    return load_preset("odg_cpu", **values)


def model_inputs(cfg, frames=None, seed=0, batch=1):
    """Random camera images of a ring rig with the ego moving 4 m forward per frame, 0.5 s
    apart -> (images, ego2img, ego_warp, time_delta), the model's positional inputs."""
    import torch

    from odg_ros.nuscenes_cameras import ring_ego2img
    frames = frames or cfg.num_frames
    g = torch.Generator().manual_seed(seed)
    images = torch.randn(batch, frames, cfg.num_cams, 3, *cfg.image_size, generator=g)
    ego2img = ring_ego2img(cfg.image_size, frames, cfg.num_cams, batch)
    warp = torch.eye(4).repeat(batch, frames, 1, 1)
    warp[:, :, 0, 3] = torch.arange(frames) * 4.0
    time_delta = torch.arange(frames, dtype=torch.float32).repeat(batch, 1) * 0.5
    return images, ego2img, warp, time_delta


def write_tiny_checkpoint(path, **overrides):
    """Random weights (seed 0) of tiny_config(**overrides) saved at ``path`` -> the path."""
    import torch

    from odg_ros.network import ODG
    from odg_ros.network.checkpoint import save_checkpoint
    torch.manual_seed(0)
    save_checkpoint(path, ODG(tiny_config(**overrides)))
    return path


def write_tiny_split(root, num_keyframes, yaw_rate=0.0):
    """A hand-made dataroot (test_dataset.build_world) and its infos pickle -> the pickle path."""
    from testing.tiny_world import build_world
    root.mkdir(parents=True, exist_ok=True)
    path = root / "infos.pkl"
    with open(path, "wb") as f:
        pickle.dump(build_world(root, num_keyframes=num_keyframes, yaw_rate=yaw_rate), f)
    return path


def published_grid(output, cfg):
    """Labels and confidence of a model output as the node publishes them: the batch's
    grids, padded when cfg.occupancy_padding."""
    from odg_ros.network.padding import pad_occupancy
    from odg_ros.network.postprocess import occupancy_grid
    grid, confidence = occupancy_grid(output, cfg)
    if cfg.occupancy_padding:
        grid, confidence = pad_occupancy(grid, confidence, cfg.num_classes, cfg.score_threshold)
    return grid, confidence


def assert_published_like(online, expected, cfg, atol):
    """An online step's result publishes what the model output ``expected`` does: the same
    labels (over enough occupied voxels to be a real comparison), confidence within one
    step, the same box labels and their centres within ``atol``."""
    import numpy as np
    from odg_ros.network.postprocess import box_list
    grid, confidence = published_grid(expected, cfg)
    assert (online.grid != cfg.num_classes).sum() > 50
    np.testing.assert_array_equal(online.grid, grid[0].numpy())
    assert np.abs(online.confidence.astype(int) - confidence[0].numpy()).max() <= 1
    boxes = box_list(expected, cfg)[0]
    assert [b["label"] for b in online.boxes] == [b["label"] for b in boxes]
    np.testing.assert_allclose([b["center"] for b in online.boxes],
                               [b["center"] for b in boxes], atol=atol)


def assert_layers_close(layers, expected, tol):
    """Every decoder layer's means, logits and boxes within ``tol`` (absolute and relative)."""
    import torch
    for a, b in zip(layers, expected, strict=True):
        for name in ("means", "logits", "boxes"):
            torch.testing.assert_close(getattr(a, name), getattr(b, name), atol=tol, rtol=tol)


def driving_scene(rng, shape=(200, 200, 16), free=17):
    """A driving-like label grid: ground, 25 cars at random, walls on two sides."""
    import numpy as np
    g = np.full(shape, free, dtype=np.uint8)
    g[:, :, :3] = 11
    g[:, 130:, :3] = 13
    for _ in range(25):
        x, y = rng.integers(20, 180, 2)
        g[x:x + 11, y:y + 5, 3:7] = rng.choice([4, 10, 3])
    g[:, 175:, 3:14] = 15
    g[:, :15, 3:12] = 16
    return g
