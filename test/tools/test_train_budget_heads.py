"""tools.train_budget_heads end to end on a tiny world: the written checkpoint has trained
budget heads, its report names the calibrated offset, and at the full budget it predicts
what its source does (the heads change nothing else)."""
import json

import torch

from odg_ros.network.checkpoint import load_model, read_checkpoint
from odg_ros.train import budget_heads as heads
from testing.helpers import model_inputs, write_tiny_checkpoint, write_tiny_split
from tools.train_budget_heads import main


def test_the_tool_writes_trained_heads_and_leaves_the_full_budget_alone(tmp_path):
    source = write_tiny_checkpoint(tmp_path / "tiny.pt", image_size=(32, 88), num_frames=3)
    data = write_tiny_split(tmp_path / "world", 4)
    out = tmp_path / "heads.pt"
    assert main(["--checkpoint", str(source), "--data", str(data), "--cache",
                 str(tmp_path / "cache"), "--out", str(out), "--skip-epochs", "1",
                 "--keep-epochs", "2", "--calibration-keyframes", "2"]) == 0
    report = read_checkpoint(out)["budget_heads"]
    assert report["keyframes"] == 4 and report["skip_logit_offset"] in heads.SKIP_OFFSETS
    assert len(report["skip_offset_agreement"]) == len(heads.SKIP_OFFSETS)
    assert "skip layer offset" in (tmp_path / "heads.pt.log").read_text()
    trained, cfg = load_model(out)
    original, _ = load_model(source)
    assert trained.decoder.budget_heads.is_trained and not original.decoder.budget_heads.is_trained
    inputs = model_inputs(cfg, seed=7)
    with torch.no_grad():
        a, b = original.eval()(*inputs).last, trained.eval()(*inputs).last
    assert torch.equal(a.means, b.means) and torch.equal(a.logits, b.logits)
    json.dumps(report)                                   # the report stays JSON
