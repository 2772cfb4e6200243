"""``odg train --budget-heads`` end to end on a tiny world: the written checkpoint has trained
budget heads, its report names the calibrated offset, and at the full budget it predicts
what its source does (the heads change nothing else); options of the other mode are refused."""
import json

import pytest
import torch

from odg_ros.commands import main
from odg_ros.network.checkpoint import load_model, read_checkpoint
from odg_ros.train import budget_heads as heads
from testing.helpers import model_inputs, write_tiny_checkpoint, write_tiny_split


def test_odg_train_budget_heads_writes_trained_heads_and_leaves_the_full_budget_alone(
        tmp_path, capsys):
    source = write_tiny_checkpoint(tmp_path / "tiny.pt", image_size=(32, 88), num_frames=3)
    data = write_tiny_split(tmp_path / "world", 4)
    out = tmp_path / "heads"
    assert main(["train", "--budget-heads", "--init", str(source), "--data", str(data),
                 "--out", str(out), "--skip-epochs", "1", "--keep-epochs", "2",
                 "--calibration-keyframes", "2"]) == 0
    assert f"wrote {out / 'budget_heads.pt'}" in capsys.readouterr().out
    report = read_checkpoint(out / "budget_heads.pt")["budget_heads"]
    assert report["keyframes"] == 4 and report["skip_logit_offset"] in heads.SKIP_OFFSETS
    assert len(report["skip_offset_agreement"]) == len(heads.SKIP_OFFSETS)
    assert report["skip_epochs"] == 1 and report["keep_epochs"] == 2
    assert len(list((out / "cache").iterdir())) == 4          # the cached model pass
    assert "skip layer offset" in (out / "budget_heads.pt.log").read_text()
    trained, cfg = load_model(out / "budget_heads.pt")
    original, _ = load_model(source)
    assert trained.decoder.budget_heads.is_trained and not original.decoder.budget_heads.is_trained
    inputs = model_inputs(cfg, seed=7)
    with torch.no_grad():
        a, b = original.eval()(*inputs).last, trained.eval()(*inputs).last
    assert torch.equal(a.means, b.means) and torch.equal(a.logits, b.logits)
    json.dumps(report)                                   # the report stays JSON


@pytest.mark.parametrize("options, says", [
    (["--budget-heads"], "--budget-heads needs --init"),
    (["--budget-heads", "--init", "{source}", "--epochs", "3"], "--epochs do not apply"),
    (["--skip-epochs", "3"], "--skip-epochs train the budget heads: they need --budget-heads"),
])
def test_options_of_the_other_mode_are_refused(tmp_path, capsys, options, says):
    data = write_tiny_split(tmp_path / "world", 1)
    source = tmp_path / "model.pt"
    source.write_bytes(b"not read: the options are checked first")
    options = [o.format(source=source) for o in options]
    assert main(["train", "--data", str(data), "--out", str(tmp_path / "out"), *options]) == 2
    assert says in capsys.readouterr().err
    assert not (tmp_path / "out").exists()
