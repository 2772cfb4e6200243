"""ODGCriterion: term names, the weighted total, ablation switches, empty batches, NaN."""
import os
import socket
import subprocess
import sys

import pytest
import torch

from odg_ros.losses import LAMBDA_3D, ODGCriterion, encode_boxes
from odg_ros.losses.render_loss import one_call_per_scene

from testing.losses import B, CFG, all_output_tensors, make_batch, make_output
from testing import REPOSITORY


def expected_names(boxes=True, render=True, layers=6):
    names = {"loss", "occ_chamfer_l0"}
    for l in range(1, layers + 1):
        names |= {f"occ_chamfer_l{l}", f"occ_focal_l{l}"}
        if boxes:
            names |= {f"box_l1_l{l}", f"box_focal_l{l}"}
        if render:
            names |= {f"render_depth_l{l}", f"render_sem_l{l}"}
    return names


def recomputed_total(losses, layers=6):
    lam = [0.05, 0.01, 0.01, 0.01, 0.01, 0.05]
    total = losses["occ_chamfer_l0"]
    for l in range(1, layers + 1):
        total = total + losses[f"occ_chamfer_l{l}"] + losses[f"occ_focal_l{l}"]
        if f"box_l1_l{l}" in losses:
            total = total + LAMBDA_3D * (losses[f"box_l1_l{l}"] + losses[f"box_focal_l{l}"])
        if f"render_depth_l{l}" in losses:
            total = total + lam[l - 1] * (losses[f"render_depth_l{l}"] + losses[f"render_sem_l{l}"])
    return total


def test_full_criterion_terms_total_and_gradients():
    crit = ODGCriterion(CFG, render_pixels_per_camera=16)
    out = make_output()
    losses = crit(out, make_batch())
    assert set(losses) == expected_names()
    assert all(v.dim() == 0 and torch.isfinite(v) for v in losses.values())
    assert losses["loss"].item() == pytest.approx(recomputed_total(losses).item(), rel=1e-6)
    losses["loss"].backward()
    for t in all_output_tensors(out):
        assert t.grad is not None and torch.isfinite(t.grad).all()
    # the camera grids see the car and the cones, so some opacity receives render gradient
    assert any(layer.opacities.grad.abs().sum() > 0 for layer in out.layers)
    stats = crit.last_stats
    assert stats["boxes_matched"] == 6 * 3 and stats["nonfinite_box_targets"] == 6 * 2
    assert stats["render_pixels"] == 6 * B * (16 + 7)
    assert stats["samples_without_occ_gt"] == 0


def test_pixel_subsampling_is_seeded():
    a = ODGCriterion(CFG, render_pixels_per_camera=8, seed=1)(make_output(), make_batch())
    b = ODGCriterion(CFG, render_pixels_per_camera=8, seed=1)(make_output(), make_batch())
    c = ODGCriterion(CFG, render_pixels_per_camera=8, seed=2)(make_output(), make_batch())
    assert torch.equal(a["render_depth_l6"], b["render_depth_l6"])
    assert not torch.equal(a["render_depth_l6"], c["render_depth_l6"])


def test_ablation_switches():
    single = CFG.replace(dual_queries=False)
    losses = ODGCriterion(single)(make_output(single, boxes=False), make_batch())
    assert set(losses) == expected_names(boxes=False)
    losses = ODGCriterion(CFG, render=False)(make_output(), make_batch())
    assert set(losses) == expected_names(render=False)
    losses = ODGCriterion(single, render=False)(make_output(single, boxes=False), make_batch())
    assert set(losses) == expected_names(boxes=False, render=False)
    assert losses["loss"].item() == pytest.approx(recomputed_total(losses).item(), rel=1e-6)


def test_missing_boxes_with_dual_queries_is_an_error():
    with pytest.raises(ValueError, match="no boxes"):
        ODGCriterion(CFG, render=False)(make_output(boxes=False), make_batch())


def test_missing_gaussian_attributes_with_render_is_an_error():
    out = make_output()
    out.layers[3].scales = None
    with pytest.raises(ValueError, match="layer 4 has no scales"):
        ODGCriterion(CFG)(out, make_batch())
    ODGCriterion(CFG, render=False)(out, make_batch())      # fine without rendering


def test_empty_batch_is_finite():
    crit = ODGCriterion(CFG)
    out = make_output()
    losses = crit(out, make_batch(occupied=False, boxes=False, lidar=False))
    assert all(torch.isfinite(v) for v in losses.values())
    assert losses["occ_chamfer_l3"].item() == 0 and losses["box_l1_l3"].item() == 0
    assert losses["render_depth_l3"].item() == 0 and losses["render_sem_l3"].item() == 0
    assert crit.last_stats["samples_without_occ_gt"] == B
    losses["loss"].backward()
    assert torch.isfinite(out.layers[0].logits.grad).all()


def test_nan_output_raises_naming_the_term():
    out = make_output()
    with torch.no_grad():
        out.layers[2].logits[0, 0, 0, 0] = float("nan")
    with pytest.raises(FloatingPointError, match="occ_focal_l3"):
        ODGCriterion(CFG, render=False)(out, make_batch())


def test_all_layers_in_one_render_call_equal_one_call_per_layer():
    """The criterion renders every layer and sample in one call; each layer's render terms
    and the gradients of every output are those of one render_cameras call per layer and
    sample (float64 transmittance sums: last-bit differences only)."""
    from odg_ros.render import render_cameras
    calls = []

    def per_scene(*args, **kwargs):
        calls.append(1)
        return render_cameras(*args, **kwargs)

    results = []
    for renderer in (None, per_scene):
        out = make_output()
        losses = ODGCriterion(CFG, render_pixels_per_camera=16,
                              renderer=renderer and one_call_per_scene(renderer))(
            out, make_batch())
        losses["loss"].backward()
        results.append((losses, [t.grad for t in all_output_tensors(out)]))
    assert len(calls) == 6 * B
    (joint, joint_grads), (separate, separate_grads) = results
    assert all(joint[f"render_sem_l{l}"] > 0 for l in range(1, 7))
    for name in joint:
        torch.testing.assert_close(joint[name], separate[name], rtol=1e-6, atol=0)
    for a, b in zip(joint_grads, separate_grads):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-9)


@pytest.mark.parametrize("column", [2, 3])
def test_nonfinite_render_target_is_a_clear_error_read_with_the_losses(column):
    batch = make_batch()
    batch["render_targets"][1][0][3, column] = float("nan")
    with pytest.raises(ValueError, match="non-finite render target"):
        ODGCriterion(CFG, render_pixels_per_camera=0)(make_output(), batch)


def test_box_gt_encoding_consistency():
    """A prediction equal to the encoded GT has zero L1 (the criterion uses the same code)."""
    out = make_output()
    batch = make_batch()
    for layer in out.layers:
        with torch.no_grad():
            layer.boxes[0, 0] = encode_boxes(batch["gt_boxes"][0][0])
            layer.boxes[0, 1] = 1000.0           # no competition for the match
    losses = ODGCriterion(CFG, render=False)(out, {**batch, "gt_boxes": [batch["gt_boxes"][0],
                                                                            torch.zeros(0, 9)],
                                                    "gt_labels": [batch["gt_labels"][0],
                                                                  torch.zeros(0, dtype=torch.long)]})
    assert losses["box_l1_l1"].item() == pytest.approx(0.0, abs=1e-6)


def test_waymo_label_set_free_15_and_15_class_weights():
    """A Waymo config: 15 logits weighted by its 15 class weights, and 15 (not 17) is free."""
    cfg = CFG.replace(dataset="waymo", num_classes=15)
    batch = make_batch(lidar=False)
    batch["occ_semantics"][batch["occ_semantics"] == 17] = 15
    crit = ODGCriterion(cfg, render_pixels_per_camera=8)
    losses = crit(make_output(cfg), batch)
    assert torch.isfinite(losses["loss"]) and crit.last_stats["samples_without_occ_gt"] == 0
    batch["occ_semantics"][:] = 15                     # nothing occupied in either sample
    crit(make_output(cfg), batch)
    assert crit.last_stats["samples_without_occ_gt"] == B


ONE_RANK_DIVERGES = """
import datetime
import torch, torch.distributed as dist
from odg_ros.losses import ODGCriterion
from testing.losses import CFG, make_batch, make_output
dist.init_process_group("gloo", timeout=datetime.timedelta(seconds=20))
out = make_output()
if dist.get_rank() == 1:
    with torch.no_grad():
        out.layers[2].logits[0, 0, 0, 0] = float("nan")
try:
    ODGCriterion(CFG, render=False)(out, make_batch())
    print("finite")
except FloatingPointError:
    print("raised")
dist.destroy_process_group()
"""


def test_a_rank_with_a_nan_output_still_joins_the_box_all_reduces(tmp_path):
    """Under DDP, the process whose network output is non-finite raises before its box
    losses; it must still join the other processes' all-reduces of the matched count, or
    they wait in a collective it never enters (gloo then fails the run)."""
    port = free_port()
    # run from the repository root: `-c` puts it on the path, so testing/ imports
    ranks = [subprocess.Popen([sys.executable, "-c", ONE_RANK_DIVERGES], stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, text=True, cwd=REPOSITORY,
                              env=dict(os.environ, GLOO_SOCKET_IFNAME="lo", OMP_NUM_THREADS="1",
                                       MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port),
                                       RANK=str(rank), WORLD_SIZE="2"))
             for rank in range(2)]
    results = [rank.communicate(timeout=180) for rank in ranks]
    for rank, (stdout, stderr) in zip(ranks, results):
        assert rank.returncode == 0, stderr[-2000:]
    assert [stdout.split()[-1] for stdout, _ in results] == ["finite", "raised"]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]
