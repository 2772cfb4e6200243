"""The paper's mechanisms, pinned through the whole network: each test here fails when its
mechanism is switched off or turned around in the decoder, the sampler, DaS attention or the
model's forward (velocity warp, ego warp, attention locality, coarse-to-fine points, no
backbone gradient from history frames), and the shipped checkpoint's scores on a tiny fixed
world pin the network's function as a whole."""
import numpy as np
import pytest
import torch

from odg_ros.network import ODG
from odg_ros.network import sampling as sampling_module
from odg_ros.network.das_attention import DaSAttention
from odg_ros.network.decoder import PositionEncoder

from testing.helpers import model_inputs, tiny_config


def deterministic(model):
    model.eval()
    for m in model.modules():
        if isinstance(m, DaSAttention):
            m.dropout = 0.0
    return model


def record_warps(monkeypatch):
    """Wrap sampling.warp_points: every call's inputs and output, in call order."""
    calls = []
    original = sampling_module.warp_points

    def recording(points, velocity, time_delta, ego_warp):
        out = original(points, velocity, time_delta, ego_warp)
        calls.append((points.detach().clone(), out.detach().clone()))
        return out
    monkeypatch.setattr(sampling_module, "warp_points", recording)
    return calls


def rotation_z(yaw):
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def test_decoder_warps_dynamic_queries_by_velocity_and_every_query_by_ego_motion(monkeypatch):
    """In every layer, a sampling point x of a dynamic query with velocity v (the previous
    layer's box; the initial box in layer 1) is read in history frame t at
    P_t^-1 P_0 (x - v dt_t); a static query's point at P_t^-1 P_0 x (float64 reference)."""
    cfg = tiny_config()
    torch.manual_seed(1)
    model = deterministic(ODG(cfg))
    D = cfg.num_dynamic
    with torch.no_grad():   # a distinct, non-zero velocity per dynamic query for layer 1
        model.queries.init_box[:, 5:7] = torch.randn(D, 2) * 3.0
    images, ego2img, ego_warp, time_delta = model_inputs(cfg, seed=2)
    # an ego that also turns: the warp's rotation matters
    for t in range(cfg.num_frames):
        ego_warp[0, t, :3, :3] = torch.from_numpy(rotation_z(0.2 * t)).float()
    calls = record_warps(monkeypatch)
    with torch.no_grad():
        out = model(images, ego2img, ego_warp, time_delta)
    assert len(calls) == cfg.num_layers

    init_velocity = model.queries(1)[2][..., 8:10]
    velocities = [init_velocity] + [layer.boxes[..., 8:10] for layer in out.layers[:-1]]
    R = ego_warp[0, :, :3, :3].double()
    t = ego_warp[0, :, :3, 3].double()
    dt = time_delta[0].double()
    for (points, warped), velocity in zip(calls, velocities):
        x = points[0].double()                                          # [Q, M, 3]
        v = torch.zeros(x.shape[0], 2, dtype=torch.float64)
        v[:D] = velocity[0].double()
        moved = x[:, None].repeat(1, len(dt), 1, 1)                     # [Q, T, M, 3]
        moved[..., :2] -= v[:, None, None, :] * dt[None, :, None, None]
        expected = torch.einsum("tij,qtmj->qtmi", R, moved) + t[None, :, None, :]
        torch.testing.assert_close(warped[0].double(), expected, atol=1e-4, rtol=1e-5)
    assert velocities[1].abs().max() > 0.1   # the test exercises a real velocity warp


def test_initial_box_velocity_is_zero_and_detached():
    """Layer 1 warps with the initial box velocity: it starts at zero (a still object, as
    SparseBEV) and no loss moves it; the initial size and yaw do train."""
    cfg = tiny_config()
    model = ODG(cfg).train()
    _, _, boxes = model.queries(1)
    assert (boxes[..., 8:10] == 0).all()
    out = model(*model_inputs(cfg, seed=6))
    (out.layers[0].boxes.sum() + out.layers[0].means.sum() + out.last.logits.sum()).backward()
    grad = model.queries.init_box.grad
    assert (grad[:, 5:7] == 0).all()
    assert grad[:, :5].abs().sum() > 0


def test_das_attention_is_local_and_the_distance_bias_pulls_towards_near_queries():
    """With q = k = 0 the attention weights are softmax(-tau * distance): every query reads
    its own value most and a near query's far more than a far one's (float64 reference)."""
    E, H = 8, 2
    attn = DaSAttention(E, H, dropout=0.0).eval().double()
    with torch.no_grad():
        attn.qkv.weight.zero_()
        attn.qkv.bias.zero_()
        attn.qkv.weight[2 * E:] = torch.eye(E, dtype=torch.float64)     # v = query
        attn.proj.weight.copy_(torch.eye(E, dtype=torch.float64))
        attn.proj.bias.zero_()
        attn.gen_tau.bias.fill_(1.5)                                    # tau = 1.5 per metre
    g = torch.Generator().manual_seed(0)
    Q = 7
    query = torch.randn(1, Q, E, generator=g, dtype=torch.float64)
    centroids = torch.rand(1, Q, 3, generator=g, dtype=torch.float64) * 6.0
    out = attn(query, centroids, num_dynamic=3)
    distance = torch.cdist(centroids, centroids)[0]
    weights = torch.softmax(-1.5 * distance, dim=-1)                   # [Q, Q]
    torch.testing.assert_close(out[0], weights @ query[0])
    assert (weights.diagonal() > 0.5 * weights.sum(dim=1)).sum() >= Q // 2
    nearest = distance.fill_diagonal_(float("inf")).argmin(dim=1)
    farthest = distance.masked_fill(distance == float("inf"), -1.0).argmax(dim=1)
    rows = torch.arange(Q)
    assert (weights[rows, nearest] > 5 * weights[rows, farthest]).all()


def test_coarse_to_fine_points_feed_the_next_layer(monkeypatch):
    """Layer l predicts K_l points per query (points_per_layer) and layer l + 1 encodes and
    samples around exactly those points; layer 1 around the learnable initial points."""
    cfg = tiny_config()
    model = deterministic(ODG(cfg))
    seen = []
    original = PositionEncoder.forward

    def recording(self, means):
        seen.append(means.detach().clone())
        return original(self, means)
    monkeypatch.setattr(PositionEncoder, "forward", recording)
    with torch.no_grad():
        out = model(*model_inputs(cfg, seed=3))
    assert [layer.means.shape[2] for layer in out.layers] == list(cfg.points_per_layer)
    assert [m.shape[2] for m in seen] == [1] + list(cfg.points_per_layer[:-1])
    torch.testing.assert_close(seen[0], out.init_means)
    for layer, encoded in zip(out.layers[:-1], seen[1:]):
        torch.testing.assert_close(encoded, layer.means)


@pytest.mark.parametrize("history_grad", [False, True])
def test_no_backbone_gradient_from_history_frames(history_grad):
    """history_grad=False (SparseBEV's stop_prev_grad): the loss reaches the images of the
    current frame only; with history_grad=True every frame's images get a gradient (so the
    assertion can fail)."""
    cfg = tiny_config(norm_eval=True)
    model = ODG(cfg).train()
    images, *geometry = model_inputs(cfg, seed=5)
    images.requires_grad_(True)
    out = model(images, *geometry, history_grad=history_grad)
    (out.last.logits.sum() + out.last.means.sum()).backward()
    per_frame = images.grad.abs().flatten(2).amax(dim=2)[0]             # [T]
    assert per_frame[0] > 0
    if history_grad:
        assert (per_frame[1:] > 0).all()
    else:
        assert (per_frame[1:] == 0).all(), per_frame


# The shipped checkpoint on a two-keyframe world (`odg synth --scenes 1 --seconds 1
# --seed 18 --image-size 54 96`), scored without RayIoU: any change of the network's function
# (or of the data path feeding it) moves the IoUs at the second decimal. Measured with one
# torch thread; two threads move them by <= 0.005 and the box mAP of so few boxes (a last-bit
# change can swap a ranking) by up to 0.14, hence its wider tolerance. Without the velocity
# warp: mIoU 16.17, IoU_geometry 74.14, mAVE 2.86 (evaluate's default mIoU convention).
SHIPPED_SCORES = {"mIoU": 16.21, "IoU_geometry": 74.18, "mAVE": 2.83}
SHIPPED_BOX_MAP = 4.34


def test_shipped_checkpoint_scores_on_a_tiny_fixed_world(tmp_path):
    from odg_ros.data.prepare import build_infos, save_infos
    from odg_ros.data.synth.generate import generate
    from odg_ros.network.checkpoint import load_model
    from odg_ros.resources import resource_path
    from odg_ros.train.evaluate import evaluate
    generate(str(tmp_path), scenes=1, seconds=1.0, seed=18, image_hw=(54, 96), progress=False)
    save_infos(build_infos(tmp_path, None, "v1.0-trainval", "all"), tmp_path / "infos.pkl")
    model, cfg = load_model(resource_path("model/odg_cpu.pt"), device="cpu")
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        result = evaluate(model, cfg, tmp_path / "infos.pkl", rayiou=False, progress=False)
    finally:
        torch.set_num_threads(threads)
    assert result["samples"] == 2
    got = {"mIoU": result["mIoU"], "IoU_geometry": result["IoU_geometry"],
           "mAVE": result["boxes"]["mAVE"]}
    assert got == pytest.approx(SHIPPED_SCORES, abs=0.01), got
    assert result["boxes"]["mAP"] == pytest.approx(SHIPPED_BOX_MAP, abs=0.2)
