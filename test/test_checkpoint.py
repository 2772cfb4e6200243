"""Checkpoints: atomic round trip, and the compressed shipping formats."""
import torch

from odg_ros.network import ODG
from odg_ros.network.checkpoint import load_model, quantize_int8, dequantize_int8, save_checkpoint

from helpers import tiny_config


def test_round_trip_exact(tmp_path):
    model = ODG(tiny_config())
    save_checkpoint(tmp_path / "a.pt", model, extra={"step": 3})
    loaded, cfg = load_model(tmp_path / "a.pt")
    assert cfg == model.cfg
    for k, v in model.state_dict().items():
        assert torch.equal(v, loaded.state_dict()[k]), k


def test_int8_weights_within_half_a_step_per_channel():
    g = torch.Generator().manual_seed(0)
    w = torch.randn(16, 8, 3, 3, generator=g) * torch.logspace(-3, 1, 16)[:, None, None, None]
    back = dequantize_int8(quantize_int8(w))
    step = w.abs().reshape(16, -1).amax(1) / 127
    assert ((back - w).abs().reshape(16, -1).amax(1) <= step / 2 + 1e-9).all()
    zero = dequantize_int8(quantize_int8(torch.zeros(4, 4)))
    assert torch.equal(zero, torch.zeros(4, 4))


def test_int8_checkpoint_is_small_and_predicts_like_the_original(tmp_path):
    cfg = tiny_config()
    model = ODG(cfg).eval()
    save_checkpoint(tmp_path / "full.pt", model)
    save_checkpoint(tmp_path / "int8.pt", model, compress="int8")
    full_size, small_size = (tmp_path / "full.pt").stat().st_size, \
        (tmp_path / "int8.pt").stat().st_size
    assert small_size < 0.35 * full_size
    loaded, _ = load_model(tmp_path / "int8.pt")
    H, W = cfg.image_size
    from odg_ros.rig import ring_ego2img
    T = cfg.num_frames
    args = (torch.randn(1, T, 6, 3, H, W), ring_ego2img(cfg.image_size, T),
            torch.eye(4).repeat(1, T, 1, 1), torch.zeros(1, T))
    with torch.no_grad():
        a, b = model(*args), loaded(*args)
    assert (a.last.means - b.last.means).abs().max() < 0.5      # metres
    assert (a.last.logits - b.last.logits).abs().mean() < 0.1
