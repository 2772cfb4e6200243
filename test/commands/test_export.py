"""``odg export`` / train.calibrate: the threshold table equals offline evaluation at each
threshold, the chosen one is the best (ties: the higher), and the shipped file holds it and
the compressed weights that were calibrated."""
import json

import numpy as np
import pytest
import torch

from odg_ros.commands import main
from odg_ros.network.checkpoint import load_model, save_checkpoint
from odg_ros.network.visibility import DEFAULT_MIN_CLEAR
from odg_ros.train.calibrate import calibrate_thresholds
from odg_ros.train.evaluate import evaluate

from testing.helpers import tiny_config, write_tiny_checkpoint, write_tiny_split


@pytest.fixture(scope="module")
def tiny_split(tmp_path_factory):
    root = tmp_path_factory.mktemp("world")
    checkpoint = write_tiny_checkpoint(root / "tiny.pt", image_size=(32, 88), num_frames=2)
    return write_tiny_split(root, 3), checkpoint


def test_threshold_table_equals_offline_evaluation(tiny_split):
    data, checkpoint = tiny_split
    model, cfg = load_model(checkpoint)
    thresholds = (0.3, 0.45, 0.5, 0.55, 0.7)
    found = calibrate_thresholds(model, cfg, str(data), thresholds, progress=False)
    assert found["samples"] == 3
    for t in thresholds:
        expected = evaluate(model, cfg.replace(score_threshold=t), str(data), rayiou=False,
                            progress=False)["mIoU"] or 0.0
        assert found["mIoU"][t] == expected, t
    best = max(found["mIoU"].values())
    assert found["mIoU"][found["best"]] == best


class OracleWithDecoys(torch.nn.Module):
    """Call i -> keyframe i: a point at every occupied GT voxel with its class at score 0.95,
    and decoys at free voxels inside the camera mask with the first GT class at 0.6.
    Threshold 0.5 keeps the decoys, 0.7 and 0.9 only the right points (a tie: the higher,
    0.9, wins), 0.97 nothing."""

    def __init__(self, dataset, decoys=5, with_boxes=False):
        super().__init__()
        samples = [dataset[i] for i in range(len(dataset))]
        self.gt_boxes = [s["gt_boxes"] for s in samples] if with_boxes else None
        self.grids = [s["occ_semantics"] for s in samples]
        self.masks = [s["occ_mask_camera"].bool() for s in samples]
        self.decoys, self.calls, self.cfg = decoys, 0, dataset.cfg

    def forward(self, images, *args, **kwargs):
        from odg_ros.network.outputs import LayerOutput, ODGOutput
        gt, mask = self.grids[self.calls], self.masks[self.calls]
        self.calls += 1
        right = (gt != 17).nonzero()
        decoy = ((gt == 17) & mask).nonzero()[:self.decoys]
        assert len(right) and len(decoy) == self.decoys
        voxels = torch.cat([right, decoy])
        labels = torch.cat([gt[tuple(right.T)].long(),
                            gt[tuple(right[0])].long().repeat(len(decoy))])
        scores = torch.cat([torch.full((len(right),), 0.95), torch.full((len(decoy),), 0.6)])
        lo = torch.tensor(self.cfg.pc_range[:3])
        means = (lo + (voxels.float() + 0.5) * self.cfg.voxel_size).view(1, -1, 1, 3)
        logits = torch.full((1, len(voxels), 1, 17), -10.0)
        logits[0, torch.arange(len(voxels)), 0, labels] = torch.logit(scores)
        if self.gt_boxes is None:
            return ODGOutput(means, [LayerOutput(means, logits, None, None, None)],
                             num_dynamic=0)
        # boxes: the GT car at score 0.9 and a car 20 m off at 0.2, one per dynamic query
        from odg_ros.losses.box import encode_boxes
        gt = self.gt_boxes[self.calls - 1]
        boxes = torch.cat([gt, gt + torch.tensor([20.0] + [0.0] * 8)])[None]
        box_logits = torch.full((1, 2 * len(gt), 10), -10.0)
        box_logits[0, :len(gt), 0] = torch.logit(torch.tensor(0.9))
        box_logits[0, len(gt):, 0] = torch.logit(torch.tensor(0.2))
        return ODGOutput(means, [LayerOutput(means, logits, None, None, None,
                                             encode_boxes(boxes), box_logits)],
                         num_dynamic=2 * len(gt))


def test_calibration_finds_the_threshold_that_drops_the_decoys(tiny_split):
    from odg_ros.data.dataset import OccDataset
    data, checkpoint = tiny_split
    _, cfg = load_model(checkpoint)
    oracle = OracleWithDecoys(OccDataset(str(data), cfg, train=False))
    found = calibrate_thresholds(oracle, cfg, str(data), (0.5, 0.7, 0.9, 0.97),
                                      progress=False)
    table = found["mIoU"]
    assert table[0.7] == table[0.9] == 100.0 > table[0.5] > table[0.97] == 0.0
    assert found["best"] == 0.9


def test_box_ap_and_box_threshold_from_an_oracle(tiny_split):
    """GT boxes returned as predictions score AP 100 up to the nuScenes interpolation quirk
    (a false positive after full recall gives the 100 % bin its precision, here 3/6); the
    calibrated box threshold falls between the right boxes (0.9) and the decoys (0.2)."""
    from odg_ros.data.dataset import OccDataset
    data, checkpoint = tiny_split
    _, cfg = load_model(checkpoint)
    assert cfg.num_dynamic
    oracle = lambda: OracleWithDecoys(OccDataset(str(data), cfg, train=False),  # noqa: E731
                                      with_boxes=True)
    result = evaluate(oracle(), cfg, str(data), rayiou=False, progress=False)["boxes"]
    expected = round(100 * (89 + (0.5 - 0.1) / 0.9) / 90, 2)
    assert result["mAP"] == result["per_class"]["car"]["AP@0.5"] == expected
    assert result["per_class"]["truck"]["AP"] is None
    assert (result["gt_boxes"], result["pred_boxes"]) == (3, 6)
    # the boxes reach the score whole (centre, w l h, yaw, velocity in the GT's order): the
    # true-positive errors of the GT returned as predictions are 0
    errors = [result[k] for k in ("mATE", "mASE", "mAOE", "mAVE")]
    assert errors == pytest.approx([0.0] * 4, abs=1e-4)
    found = calibrate_thresholds(oracle(), cfg, str(data), (0.5,), progress=False)["box"]
    assert found["threshold"] == pytest.approx(0.55)
    assert (found["precision"], found["recall"], found["f1"]) == (1.0, 1.0, 1.0)


def test_eval_command_reports_grid_and_boxes(tiny_split, capsys):
    data, checkpoint = tiny_split
    assert main(["eval", "--checkpoint", str(checkpoint), "--data", str(data),
                 "--no-rayiou", "--json"]) == 0
    result = json.loads(capsys.readouterr().out)
    assert result["samples"] == 3 and "mIoU" in result and "mIoU_dynamic" in result
    assert set(result["boxes"]) >= {"mAP", "AP@0.5", "AP@4", "mATE", "mAVE", "per_class",
                                    "gt_boxes"}
    assert result["boxes"]["gt_boxes"] == 3
    assert main(["eval", "--checkpoint", str(checkpoint), "--data", str(data),
                 "--no-rayiou"]) == 0
    table = capsys.readouterr().out
    assert "MEAN" in table and "boxes: mAP" in table


def test_eval_reports_what_a_planner_reads_per_split_and_together(tiny_split, capsys):
    """Two named splits: each scored alone and both together; the visibility beside the
    ground-truth grid's ceiling, calibration error and flips; in JSON and in the table. (The
    tiny world's mask_camera is a block, not what cameras see: the figures' values are
    checked in test/metrics/test_planner.py.)"""
    data, checkpoint = tiny_split
    assert main(["eval", "--checkpoint", str(checkpoint), "--data", f"one={data}",
                 f"two={data}", "--no-rayiou", "--json"]) == 0
    result = json.loads(capsys.readouterr().out)
    assert set(result["sets"]) == {"one", "two"} and result["samples"] == 6
    assert result["sets"]["one"]["mIoU"] == result["sets"]["two"]["mIoU"] == result["mIoU"]
    for scored in [result] + list(result["sets"].values()):
        visibility = scored["visibility"]
        assert visibility["min_clear"] == DEFAULT_MIN_CLEAR
        for grid in ("model", "ground_truth_grid"):
            assert set(visibility[grid]["voxels"]) == {
                "observed_precision", "observed_recall", "free_observed_precision",
                "free_observed_recall"}
            assert set(visibility[grid]["bev"]) == {"known_precision", "known_recall",
                                                    "free_precision", "free_recall"}
        truth = visibility["ground_truth_grid"]["voxels"]
        assert 0 < truth["observed_precision"] <= 1 and 0 < truth["observed_recall"] <= 1
        assert scored["confidence"]["calibrated"] is False      # the tiny model has none
        assert scored["confidence"]["free"]["samples"] > 0
        assert scored["stability"]["pairs"] == (4 if scored is result else 2)
    assert result["visibility"]["model"] == result["sets"]["one"]["visibility"]["model"]
    assert main(["eval", "--checkpoint", str(checkpoint), "--data", str(data), "--no-rayiou",
                 "--visibility-min-clear", "0.5"]) == 0
    table = capsys.readouterr().out
    assert "what a planner reads" in table and "truth grid" in table
    assert "visibility_min_clear 0.5" in table and "expected calibration error" in table
    assert main(["eval", "--checkpoint", str(checkpoint), "--data", f"a={data}", f"a={data}",
                 "--no-rayiou"]) == 2
    assert "NAME" in capsys.readouterr().err


def test_eval_overrides_reach_the_model(tiny_split, capsys, tmp_path):
    data, checkpoint = tiny_split
    args = ["eval", "--checkpoint", str(checkpoint), "--data", str(data), "--no-rayiou", "--json"]

    def occupied_voxels(threshold):
        out = tmp_path / str(threshold)
        assert main(args + ["--save-pred", str(out), "--set", f"score_threshold={threshold}"]) == 0
        assert f"wrote 3 predictions (<token>.npz, for odg score --pred) to {out}" in \
            capsys.readouterr().err
        return sum(int((np.load(f)["semantics"] != 17).sum()) for f in out.glob("*.npz"))

    # every point inside the grid counts at threshold 0, none at 1 (the highest allowed)
    assert occupied_voxels(0.0) > 0 and occupied_voxels(1.0) == 0
    # a knock-out of a trained component runs on the same weights
    assert main(args + ["--set", "ego_compensation=false", "--set", "das_attention=false"]) == 0
    assert json.loads(capsys.readouterr().out)["samples"] == 3


def test_eval_reports_the_mean_query_budget(tiny_split, capsys, tmp_path):
    """--query-budget: the result says how many queries were refined, names each budget in
    words and gives the change against every query refined on the same keyframes; a
    checkpoint whose budget heads are untrained is one error line."""
    from odg_ros.network.budget import budget_of
    data, checkpoint = tiny_split
    args = ["eval", "--data", str(data), "--no-rayiou", "--json"]
    assert main(args + ["--checkpoint", str(checkpoint), "--query-budget", "auto"]) == 2
    assert "heads are not trained; use query_budget full" in capsys.readouterr().err
    model, cfg = load_model(checkpoint)
    model.decoder.budget_heads.set_trained(True)
    trained = tmp_path / "heads.pt"
    save_checkpoint(trained, model)
    assert main(args + ["--checkpoint", str(trained), "--query-budget", "full"]) == 0
    full = json.loads(capsys.readouterr().out)
    assert "query_budget" not in full
    assert main(args + ["--checkpoint", str(trained), "--query-budget", "0.5"]) == 0
    result = json.loads(capsys.readouterr().out)
    use, half = result["query_budget"], budget_of(cfg, 0.5)
    change = use.pop("against_full")
    assert use == {"mode": half.name, "keyframes_per_budget": {half.name: 3},
                   "mean_refined_fraction": round(half.refined_fraction(cfg), 4),
                   "budgets": {half.name: half.describe(cfg)}}
    assert f"{half.static} of {cfg.static_queries} (" in use["budgets"][half.name]
    for metric in ("mIoU", "IoU_geometry"):          # the full run of the same call
        assert change[metric] == {"full": full[metric],
                                  "change": round(result[metric] - full[metric], 2)}
    assert main(args[:-1] + ["--checkpoint", str(trained), "--query-budget", "auto"]) == 0
    text = capsys.readouterr().out
    assert "query budget auto: on average" in text and "every query (full)" in text
    assert "against full (every query refined, the same keyframes in this run): mIoU" in text


def test_single_query_set_has_no_box_score(tmp_path):
    """One query set (dual_queries false, its config still holding num_dynamic) has no box
    head: eval reports no box mAP (not 0) and calibration picks no box threshold."""
    from odg_ros.network import ODG
    cfg = tiny_config(dual_queries=False)
    assert cfg.num_dynamic and (cfg.dynamic_queries, cfg.static_queries) == (0, cfg.num_queries)
    data = str(write_tiny_split(tmp_path / "split", 2))
    model = ODG(cfg).eval()
    result = evaluate(model, cfg, data, rayiou=False, progress=False)
    assert "boxes" not in result and result["samples"] > 0
    assert calibrate_thresholds(model, cfg, data, (0.5,), progress=False)["box"] is None


def test_no_thresholds_is_an_error(tiny_split):
    data, checkpoint = tiny_split
    model, cfg = load_model(checkpoint)
    with pytest.raises(ValueError, match="no thresholds"):
        calibrate_thresholds(model, cfg, str(data), (), progress=False)


def test_export_writes_the_calibrated_threshold_and_the_int8_weights(tiny_split, tmp_path,
                                                                     capsys):
    data, checkpoint = tiny_split
    out = tmp_path / "shipped.pt"
    assert main(["export", "--checkpoint", str(checkpoint), "--out", str(out),
                 "--compress", "int8", "--calibrate", str(data),
                 "--thresholds", "0.3", "0.5", "0.7"]) == 0
    report = json.loads(capsys.readouterr().out)
    model, cfg = load_model(out)
    assert cfg.score_threshold == report["score_threshold"] in (0.3, 0.5, 0.7)
    assert cfg.box_score_threshold == report["box_score_threshold"] \
        == report["box_f1"]["threshold"]
    assert 0.0 <= cfg.box_score_threshold <= 1.0
    table = report["mIoU_by_threshold"]
    assert table[str(cfg.score_threshold)] == max(table.values())
    assert torch.load(out, weights_only=False)["compression"] == "int8"
    # the shipped weights are the int8 weights that were calibrated, not quantised twice
    direct = tmp_path / "direct.pt"
    save_checkpoint(direct, load_model(checkpoint)[0], compress="int8")
    reference = load_model(direct)[0].state_dict()
    for key, value in model.state_dict().items():
        torch.testing.assert_close(value, reference[key], rtol=0, atol=1e-6, msg=key)
    assert out.stat().st_size < checkpoint.stat().st_size / 2


def test_export_calibrates_the_probabilities_and_keeps_the_shipped_grid(tiny_split, tmp_path,
                                                                        capsys):
    """--keep-thresholds on a shipped (int8) checkpoint: the same stored weights, bit for bit,
    the same thresholds and so the same grid; a calibration added, what else the file
    recorded kept."""
    data, checkpoint = tiny_split
    shipped = tmp_path / "shipped.pt"
    save_checkpoint(shipped, load_model(checkpoint)[0], compress="int8",
                    extra={"budget_heads": {"steps": 7}})
    out = tmp_path / "calibrated.pt"
    assert main(["export", "--checkpoint", str(shipped), "--out", str(out), "--compress", "int8",
                 "--calibrate", str(data), str(data), "--keep-thresholds"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["fitted"]["keyframes"] == 6 and "mIoU_by_threshold" not in report
    before, after = (torch.load(p, weights_only=False) for p in (shipped, out))
    assert before["model"].keys() == after["model"].keys()
    for key, value in before["model"].items():
        stored = after["model"][key]
        if isinstance(value, dict):                                # int8: q and scale
            assert all(torch.equal(value[k], stored[k]) for k in value), key
        else:
            assert torch.equal(value, stored), key
    assert after["budget_heads"] == {"steps": 7}
    cfg_before, cfg_after = load_model(shipped)[1], load_model(out)[1]
    assert cfg_after.calibration is not None and cfg_before.calibration is None
    assert cfg_after.replace(calibration=None) == cfg_before
    # the grid: the same labels from both files
    from odg_ros.data.dataset import OccDataset
    from odg_ros.train.evaluate import padded_grid, predict_split
    grids = []
    for path in (shipped, out):
        model, cfg = load_model(path)
        dataset = OccDataset(str(data), cfg)
        grids.append([padded_grid(o, cfg)[0].numpy() for _, _, o in
                      predict_split(model, dataset, progress=False)])
    for a, b in zip(*grids):
        np.testing.assert_array_equal(a, b)


def test_keep_thresholds_needs_calibrate(tiny_split, tmp_path, capsys):
    _, checkpoint = tiny_split
    assert main(["export", "--checkpoint", str(checkpoint), "--out", str(tmp_path / "a.pt"),
                 "--keep-thresholds"]) == 2
    assert "--calibrate" in capsys.readouterr().err


def test_eval_precision_scores_the_node_arithmetic(tiny_split, capsys):
    """--precision fp32 scores the node step's own modules (folded backbone): the grid of
    the training model within a voxel or two; bf16 runs and says so."""
    data, checkpoint = tiny_split
    args = ["eval", "--checkpoint", str(checkpoint), "--data", str(data), "--no-rayiou", "--json"]
    assert main(args) == 0
    training = json.loads(capsys.readouterr().out)
    assert main(args + ["--precision", "fp32"]) == 0
    node = json.loads(capsys.readouterr().out)
    assert node["precision"] == "fp32 (the node's arithmetic)" and "precision" not in training
    assert node["mIoU"] == pytest.approx(training["mIoU"], abs=0.5)
    assert main(args + ["--precision", "bf16"]) == 0
    assert json.loads(capsys.readouterr().out)["precision"].startswith("bf16")
