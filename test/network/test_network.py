"""The ODG network: preset shapes and counts, DaS mixing, feature caching, hard cases,
post-processing."""
import pytest
import torch
from torch import nn

from odg_ros.nuscenes_cameras import online_inputs
from odg_ros.classes import FREE_LABEL
from odg_ros.model_config import PRESET_NAMES, load_preset
from odg_ros.network import ODG
from odg_ros.network.das_attention import DaSAttention
from odg_ros.rotation import normalise_quaternions
from odg_ros.network.outputs import LayerOutput, ODGOutput
from odg_ros.network.postprocess import box_list, decode_box_code, occupancy_grid
from odg_ros.nuscenes_cameras import ring_ego2img

from testing.helpers import model_inputs, tiny_config

PAPER_GAUSSIANS = {"odg_t": [600, 2400, 9600, 19200, 38400, 76800],
                   "odg_l": [4800, 9600, 19200, 38400, 76800, 76800],
                   "odg_waymo_t": [600, 2400, 9600, 19200, 38400, 76800]}


def run(model, cfg, batch=1, frames=None, seed=0, **decode_options):
    inputs = model_inputs(cfg, frames, seed, batch)
    return model(*inputs, **decode_options), inputs


@pytest.mark.parametrize("name", PRESET_NAMES)
def test_preset_shapes_and_counts(name):
    cfg = load_preset(name)
    if name in PAPER_GAUSSIANS:
        assert cfg.gaussians_per_layer == PAPER_GAUSSIANS[name]
        assert (cfg.backbone, cfg.image_size, cfg.num_frames, cfg.num_layers) == \
            ("resnet50", (256, 704), 8, 6)
    assert cfg.gaussians_per_layer[-1] == cfg.num_queries * cfg.points_per_layer[-1]
    # run the preset's decoder (its queries, points, groups) on a small image and backbone
    small = cfg.replace(backbone="resnet18", image_size=(32, 88), num_frames=2)
    model = ODG(small).eval()
    with torch.no_grad():
        out, _ = run(model, small, gaussian_attributes=True)
    Q, D = cfg.num_queries, cfg.num_dynamic
    assert out.init_means.shape == (1, Q, 1, 3)
    assert len(out.layers) == 6
    for K, layer in zip(cfg.points_per_layer, out.layers):
        assert layer.means.shape == (1, Q, K, 3)
        assert layer.logits.shape == (1, Q, K, cfg.num_classes)
        assert layer.scales.shape == (1, Q, K, 3) and layer.rotations.shape == (1, Q, K, 4)
        assert layer.opacities.shape == (1, Q, K)
        assert layer.boxes.shape == (1, D, 10) and layer.box_logits.shape == (1, D, 10)
        assert layer.means.shape[1] * layer.means.shape[2] == Q * K


def test_das_attention_mixes_dynamic_and_static_queries_both_ways():
    torch.manual_seed(0)
    attn = DaSAttention(32, 4, dropout=0.0).eval()
    D, S = 3, 5
    query = torch.randn(1, D + S, 32)
    centroids = torch.randn(1, D + S, 3) * 5
    base = attn(query, centroids, D)
    q2 = query.clone()
    q2[0, D + 2] += 1.0                        # change one static query
    assert not torch.allclose(attn(q2, centroids, D)[0, :D], base[0, :D])
    q3 = query.clone()
    q3[0, 1] += 1.0                            # change one dynamic query
    assert not torch.allclose(attn(q3, centroids, D)[0, D:], base[0, D:])
    # the ablation (separate sets) must NOT mix: the test above can fail
    separate = DaSAttention(32, 4, dropout=0.0, mix_sets=False).eval()
    separate.load_state_dict(attn.state_dict())
    base_sep = separate(query, centroids, D)
    torch.testing.assert_close(separate(q2, centroids, D)[0, :D], base_sep[0, :D])
    torch.testing.assert_close(separate(q3, centroids, D)[0, D:], base_sep[0, D:])


@pytest.mark.parametrize("mix_sets", [True, False])
def test_flex_attention_bias_equals_the_materialised_bias(monkeypatch, mix_sets):
    """The score_mod path (compiled, on CUDA in the node) against the SDPA path with the
    [B, H, Q, Q] bias, in float64; here FlexAttention runs eagerly on the CPU."""
    from odg_ros.network import das_attention
    torch.manual_seed(0)
    attn = DaSAttention(32, 4, dropout=0.0, mix_sets=mix_sets).double().eval()
    nn.init.normal_(attn.gen_tau.weight, std=0.3)         # tau differs per query and head
    query = torch.randn(2, 11, 32, dtype=torch.float64)
    centroids = torch.randn(2, 11, 3, dtype=torch.float64) * 5
    assert not das_attention.use_flex_attention(query, training=False)   # CPU, eager
    with torch.no_grad():                 # eager CPU FlexAttention has no backward
        expected = attn(query, centroids, 4)
        monkeypatch.setattr(das_attention, "use_flex_attention", lambda query, training: True)
        got = attn(query, centroids, 4)
    torch.testing.assert_close(got, expected, atol=1e-10, rtol=1e-10)


def test_online_step_over_cached_features_equals_recomputing_all_frames():
    cfg = tiny_config(num_frames=3)
    model = ODG(cfg).eval()
    stream = torch.randn(5, 1, cfg.num_cams, 3, *cfg.image_size)  # 5 consecutive frames
    ego2img = ring_ego2img(cfg.image_size, 3, cfg.num_cams)
    warp = torch.eye(4).repeat(1, 3, 1, 1)
    warp[:, :, 0, 3] = torch.tensor([0.0, 2.0, 4.0])
    dt = torch.tensor([[0.0, 0.5, 1.0]])
    with torch.no_grad():
        cache = []
        for t in range(5):                       # online: backbone once per frame
            cache.insert(0, model.extract_features(stream[t]))
            cache = cache[:3]
            if t < 2:
                continue
            online = model.decode(cache, ego2img, warp, dt)
            offline = model(torch.stack([stream[t], stream[t - 1], stream[t - 2]], 1),
                            ego2img, warp, dt)
            for a, b in zip(online.layers, offline.layers):
                torch.testing.assert_close(a.means, b.means, rtol=1e-4, atol=1e-4)
                torch.testing.assert_close(a.logits, b.logits, rtol=1e-4, atol=1e-4)
                torch.testing.assert_close(a.boxes, b.boxes, rtol=1e-4, atol=1e-4)


def test_fewer_frames_repeat_the_oldest():
    cfg = tiny_config(num_frames=3)
    model = ODG(cfg).eval()
    images = torch.randn(1, 2, cfg.num_cams, 3, *cfg.image_size)
    e2i = ring_ego2img(cfg.image_size, 3, cfg.num_cams)
    warp = torch.eye(4).repeat(1, 3, 1, 1)
    dt = torch.tensor([[0.0, 0.5, 0.5]])
    with torch.no_grad():
        short = model(images, e2i[:, :2], warp[:, :2], dt[:, :2])
        padded = model(torch.cat([images, images[:, 1:]], 1), e2i, warp, dt)
    torch.testing.assert_close(short.last.means, padded.last.means, rtol=1e-4, atol=1e-4)


def test_batch_of_one_and_two_give_identical_per_sample_results():
    cfg = tiny_config()
    model = ODG(cfg).eval()
    with torch.no_grad():
        out2, (images, e2i, warp, dt) = run(model, cfg, batch=2, seed=1)
        out1 = model(images[1:], e2i[1:], warp[1:], dt[1:])
    for a, b in zip(out1.layers, out2.layers):
        torch.testing.assert_close(a.means[0], b.means[1], rtol=1e-4, atol=1e-4)
        torch.testing.assert_close(a.logits[0], b.logits[1], rtol=1e-4, atol=1e-4)


def test_no_nan_or_inf_on_random_inputs_and_gradients_flow():
    cfg = tiny_config()
    model = ODG(cfg).train()
    out, _ = run(model, cfg, batch=2, seed=2)
    total = 0
    for layer in out.layers:
        for name in ("means", "logits", "scales", "rotations", "opacities", "boxes", "box_logits"):
            value = getattr(layer, name)
            assert torch.isfinite(value).all(), name
            total = total + value.float().mean()
        torch.testing.assert_close(layer.rotations.norm(dim=-1),
                                   torch.ones_like(layer.opacities))
        assert (layer.scales > 0).all() and ((layer.opacities > 0) & (layer.opacities < 1)).all()
    total.backward()
    grads = [p.grad for p in model.parameters() if p.requires_grad]
    assert all(g is None or torch.isfinite(g).all() for g in grads)
    assert model.decoder.layers[0].sampling.offsets.weight.grad is not None
    assert model.backbone.layer4[0].conv1.weight.grad is not None
    # the CPU preset (tiny_config's base) trains every stage; ImageNet presets freeze layer1
    assert cfg.frozen_stages == -1 and model.backbone.layer1[0].conv1.weight.grad is not None


def test_zero_and_denormal_quaternions_normalise_safely():
    q = torch.tensor([[0.0, 0, 0, 0], [1e-40, 0, 0, 0], [0, 3.0, 0, 4.0], [-2.0, 0, 0, 0]],
                     requires_grad=True)
    unit = normalise_quaternions(q)
    torch.testing.assert_close(unit.detach(), torch.tensor(
        [[1.0, 0, 0, 0], [1.0, 0, 0, 0], [0, 0.6, 0, 0.8], [-1.0, 0, 0, 0]]))
    unit.sum().backward()
    assert torch.isfinite(q.grad).all()


def make_output(means, logits, boxes=None, box_logits=None):
    layer = LayerOutput(means, logits, torch.ones_like(means), torch.zeros(*means.shape[:-1], 4),
                        torch.ones(means.shape[:-1]), boxes, box_logits)
    return ODGOutput(init_means=means[:, :, :1], layers=[layer], num_dynamic=0)


def test_postprocess_voxelises_confident_points_near_their_centroid():
    cfg = load_preset("odg_cpu")
    big = 10.0
    means = torch.tensor([[[[0.1, 0.1, 0.1], [0.3, 0.3, 0.3], [0.5, 0.1, 0.1], [0.2, 0.2, 0.15]],
                           [[10.1, 0.1, 0.1], [10.1, 0.1, 0.1], [14.5, 0.0, 0.0],
                            [10.1, 0.1, 0.1]]]])
    logits = torch.full((1, 2, 4, 17), -big)
    logits[0, 0, 0, 4] = big           # car at voxel (100, 100, 2)
    logits[0, 0, 1, 4] = 0.0           # score 0.5: not > 0.5, dropped
    logits[0, 0, 2, 7] = big           # pedestrian at voxel (101, 100, 2)
    logits[0, 0, 3, 4] = 1.0           # same voxel as point 0: averaged with it -> still car
    logits[0, 1, 0, 11] = 2.0          # two points in one voxel: classes averaged
    logits[0, 1, 1, 11] = -2.0
    logits[0, 1, 1, 12] = 3.0          # mean(11) = 0.5, mean(12) ~ 0.48 -> 11 wins
    logits[0, 1, 2, 15] = big          # 3.3 m from its query's centroid (11.2, ..): dropped
    grid, conf = occupancy_grid(make_output(means, logits), cfg)
    occupied = (grid[0] != FREE_LABEL).nonzero().tolist()
    assert occupied == [[100, 100, 2], [101, 100, 2], [125, 100, 2]]
    assert grid[0, 100, 100, 2] == 4 and grid[0, 101, 100, 2] == 7 and grid[0, 125, 100, 2] == 11
    assert conf[0, 101, 100, 2] == 255


def test_postprocess_ignores_nan_points_and_boxes_decode():
    cfg = load_preset("odg_cpu")
    means = torch.tensor([[[[float("nan"), 0.0, 0.0]]]])
    logits = torch.full((1, 1, 1, 17), 10.0)
    grid, _ = occupancy_grid(make_output(means, logits), cfg)
    assert (grid == FREE_LABEL).all()
    code = torch.tensor([1.0, 2.0, 0.5, 0.0, 1.0, 0.0, 1.0, 0.0, 3.0, -1.0])
    torch.testing.assert_close(decode_box_code(code), torch.tensor(
        [1.0, 2.0, 0.5, 1.0, 2.718282, 1.0, 1.570796, 3.0, -1.0]))
    box_logits = torch.tensor([[[-5.0] * 9 + [5.0], [-5.0] * 10]])
    out = make_output(means, logits, code.repeat(1, 2, 1), box_logits)
    boxes = box_list(out, cfg, score_threshold=0.3)[0]
    assert len(boxes) == 1 and boxes[0]["class_name"] == "traffic_cone"


def test_online_inputs_geometry_is_consistent():
    """The benchmark's drive: 10 m/s straight ahead, so a static point x metres ahead now was
    x + 10 dt ahead of the past ego; a point straight ahead of the front camera projects to
    its image centre in every frame."""
    from odg_ros.nuscenes_cameras import ring_cameras
    cfg = tiny_config()
    _, e2i, warp, dt = online_inputs(cfg, 3, "cpu")
    assert e2i.shape == (1, 3, 6, 4, 4) and warp.shape == (1, 3, 4, 4) and dt.shape == (1, 3)
    torch.testing.assert_close(dt[0], torch.tensor([0.0, 0.5, 1.0]))
    mount = ring_cameras(cfg.image_size)[1][0][:3, 3]
    point = torch.tensor([20.0, float(mount[1]), float(mount[2]), 1.0])
    for t in range(3):
        past = warp[0, t] @ point
        torch.testing.assert_close(past, point + torch.tensor([10.0 * dt[0, t], 0, 0, 0]))
        u, v, d = (e2i[0, t, 0] @ past)[:3]
        H, W = cfg.image_size
        torch.testing.assert_close(torch.stack([u / d, v / d]), torch.tensor([W / 2, H / 2]))
        assert d == pytest.approx(20.0 + 10.0 * float(dt[0, t]) - float(mount[0]), rel=1e-5)


def test_every_trainable_parameter_gets_a_gradient():
    """A parameter without gradient is dead weight, and breaks DDP's all-reduce."""
    cfg = tiny_config()
    model = ODG(cfg).train()
    out, _ = run(model, cfg, seed=4)
    total = out.init_means.sum()
    for layer in out.layers:
        for t in (layer.means, layer.logits, layer.scales, layer.rotations, layer.opacities,
                  layer.boxes, layer.box_logits):
            total = total + t.sum()
    total.backward()
    dead = [n for n, p in model.named_parameters() if p.requires_grad and p.grad is None]
    assert not dead, dead


def test_history_without_grad_gives_the_same_output_and_no_backbone_grad_from_the_past():
    # fixed BN statistics: with training-mode BN the batch (current frame alone vs all
    # frames) changes the statistics, which is the only difference between the two paths
    cfg = tiny_config(norm_eval=True)
    model = ODG(cfg).train()
    for m in model.modules():  # deterministic training-mode forward
        if isinstance(m, torch.nn.Dropout):
            m.p = 0.0
        if isinstance(m, DaSAttention):
            m.dropout = 0.0
    _, (images, *geometry) = run(model, cfg, seed=5)
    assert images.shape[1] > 1                          # a history to take gradients from
    grads = {}
    for history_grad in (True, False):
        model.zero_grad(set_to_none=True)
        frames = images.clone().requires_grad_(True)
        out = model(frames, *geometry, history_grad=history_grad)
        out.last.logits.sum().backward()
        grads[history_grad] = (out.last.means.detach(), frames.grad,
                               model.backbone.layer4[0].conv1.weight.grad)
    (full, full_images, _), (cheap, cheap_images, cheap_backbone) = grads[True], grads[False]
    torch.testing.assert_close(full, cheap, rtol=1e-4, atol=1e-4)
    # the only way from the loss to a past frame's pixels is back through the backbone
    assert full_images[:, 1:].abs().amax() > 0          # with history grad it flows there
    assert cheap_images[:, 1:].abs().amax() == 0        # without, none from the past
    assert cheap_images[:, 0].abs().amax() > 0          # the current frame still trains it
    assert cheap_backbone is not None and cheap_backbone.abs().amax() > 0
