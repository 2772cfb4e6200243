"""odg ablation: variants against the reference's seed mean, on hand-made eval results."""
import json

import pytest

from odg_ros.bench.ablation import ablation_table, summarize_ablation
from odg_ros.commands import main as odg


def result(miou, rayiou, box_map=None, dynamic=1.0):
    out = {"mIoU": miou, "RayIoU": rayiou, "RayIoU@1": rayiou - 1, "RayIoU@2": rayiou,
           "RayIoU@4": rayiou + 1, "IoU_geometry": 50.0, "mIoU_dynamic": dynamic,
           "samples": 4, "per_class": {}}
    if box_map is not None:
        out["boxes"] = {"mAP": box_map}
    return out


def test_seeds_average_and_deltas_are_against_the_reference_mean():
    summary = summarize_ablation([("full", result(10.0, 20.0, 3.0)), ("no_render", result(9.0, 17.0)),
                         ("full", result(12.0, 22.0, 5.0))])
    full, no_render = summary["variants"]
    assert summary["reference"] == "full" and full["seeds"] == 2
    assert full["mean"]["mIoU"] == 11.0 and full["range"]["mIoU"] == [10.0, 12.0]
    assert full["delta"]["mIoU"] == 0.0
    assert no_render["delta"]["mIoU"] == -2.0 and no_render["delta"]["RayIoU@4"] == -4.0
    # a variant without boxes (single query set) has no box mAP and no box delta
    assert no_render["mean"]["box_mAP"] is None and no_render["delta"]["box_mAP"] is None
    table = ablation_table(summary)
    assert "| full | 2 | 11.00 | 21.00 |" in table
    assert "| no_render | 1 | 9.00 (-2.00) | 17.00 (-4.00) |" in table
    assert "mIoU 2.00, RayIoU 2.00" in table          # the reference's seed-to-seed range


def test_missing_values_are_not_averaged_as_zero():
    summary = summarize_ablation([("full", result(10.0, 20.0, None)), ("full", result(12.0, 20.0, 4.0))])
    assert summary["variants"][0]["mean"]["box_mAP"] == 4.0


def test_command_writes_json_markdown_and_png(tmp_path):
    paths = []
    for i, r in enumerate([result(10.0, 20.0, 3.0), result(11.0, 21.0, 3.5),
                           result(8.0, 19.0, 2.0)]):
        paths.append(tmp_path / f"eval{i}.json")
        paths[-1].write_text(json.dumps(r))
    stem = tmp_path / "out" / "ablation"
    assert odg(["ablation", f"full={paths[0]}", f"full={paths[1]}", f"no_das={paths[2]}",
                "--out", str(stem)]) == 0
    summary = json.loads(stem.with_suffix(".json").read_text())
    assert [v["name"] for v in summary["variants"]] == ["full", "no_das"]
    assert summary["variants"][1]["delta"]["mIoU"] == pytest.approx(-2.5)
    assert stem.with_suffix(".png").stat().st_size > 1000
    assert "no_das" in stem.with_suffix(".md").read_text()


def test_bad_arguments_are_refused():
    with pytest.raises(ValueError):
        summarize_ablation([])
    assert odg(["ablation", "full", "--out", "x"]) == 2
