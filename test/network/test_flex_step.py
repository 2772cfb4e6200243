"""The node's whole online step compiled with FlexAttention, as the compiled and graphs steps
run on CUDA, here compiled by Inductor for the CPU: ODG-T's attention (600 queries, 8 heads of
32) under bf16 weights and autocast, against the eager SDPA step in fp32.

Which error is acceptable: FlexAttention and the SDPA path both compute the distance bias and
the softmax in float32, so FlexAttention adds no error of its own; what differs from fp32 is
bf16's rounding of the weights and activations. The reference for that is the eager bf16 step
(SDPA) against fp32: the compiled FlexAttention step must lie as close to fp32 as it does,
within a margin for Inductor's different (fused) rounding order. The step's backbone is a
ResNet-18 at 32 x 88 over 2 frames and the decoder has 2 layers (ODG-T's first two), which
keeps the compile short; the attention has ODG-T's sizes.

Not run by default (ODG_FLEX_STEP_TEST=1, as the benchmarks' tests): it compiles for minutes
on 2 cores. Inductor's CPU template for FlexAttention (PyTorch 2.11 and 2.13) reads the
tensors a score function captures before it realises them, so a captured tensor that is still
an unmaterialised expression (the centroids, a mean over one point; tau, cast from the bf16
projection) fails the compile with "NoValidChoicesError". The CUDA lowering realises them
first, so the fixture does the same before the CPU template runs (`realised_captures`); the
step itself is compiled as it is. So one DaS layer compiles and matches SDPA in fp32 to bf16
rounding (and is 2 off when the bias's sign is flipped). The whole step now compiles too,
but on PyTorch 2.13 its compiled code aborts the process in a later fused CPU kernel (the
grid's and boxes' post-processing), not yet understood: the test does not pass today. On
CUDA the same is checked by tools/flex_attention_check.py (part first of
tools/gpu_checks.sh)."""
import os

import numpy as np
import pytest
import torch
from torch._inductor.kernel.flex import flex_attention as flex_lowering
from torch._inductor.kernel.flex.common import maybe_realize

from odg_ros.model_config import load_preset
from odg_ros.network import ODG, das_attention
from odg_ros.online.step import OnlineStep
from testing.online import make_sets
from odg_ros.online.predictor import OnlinePredictor

QUERIES, HEAD_DIM = 600, 32
pytestmark = pytest.mark.skipif(os.environ.get("ODG_FLEX_STEP_TEST") != "1",
                                reason="compiles the step with FlexAttention for minutes; set "
                                       "ODG_FLEX_STEP_TEST=1")


def odg_t_attention():
    cfg = load_preset("odg_t", backbone="resnet18", image_size=(32, 88), num_frames=2,
                      num_layers=2, points_per_layer=(1, 4), score_threshold=0.0,
                      box_score_threshold=0.0)
    assert cfg.num_queries == QUERIES and cfg.embed_dims // cfg.num_heads == HEAD_DIM
    torch.manual_seed(0)
    return ODG(cfg).eval(), cfg


def step_inputs(cfg, predictor, camera_set):
    """One camera set packed as the node packs it -> (images, packed) of the step."""
    predictor.step(*camera_set)                        # fills the history and the layout
    return torch.from_numpy(camera_set[0]), predictor._packed.clone()


def outputs_of(step, images, packed):
    with torch.inference_mode():
        labels, confidence, boxes, score, *_ = step(images, packed)
    return labels.numpy().copy(), confidence.numpy().astype(int), boxes.float().numpy()


def realised_captures(lower_cpu):
    """Inductor's CPU FlexAttention lowering, with the score function's captured tensors
    realised first, as the CUDA lowering does."""
    def lower(query, key, value, subgraph, block_mask, scale, kernel_options, score_others,
              mask_others):
        return lower_cpu(query, key, value, subgraph, block_mask, scale, kernel_options,
                         maybe_realize(list(score_others)), maybe_realize(list(mask_others)))
    return lower


@pytest.fixture(scope="module")
def steps():
    """(fp32 eager SDPA, bf16 eager SDPA, bf16 compiled FlexAttention) outputs of two steps,
    and how many attention calls the compile traced with FlexAttention."""
    model, cfg = odg_t_attention()
    sets = make_sets(cfg, 2)
    predictor = OnlinePredictor(model, cfg, "cpu", max_gap=1.0)
    inputs = [step_inputs(cfg, predictor, s) for s in sets]
    fp32, bf16 = (OnlineStep(model, cfg, cfg.num_frames, "cpu", p).eval()
                  for p in ("fp32", "bf16"))
    flex = OnlineStep(model, cfg, cfg.num_frames, "cpu", "bf16").eval()
    traced = []
    original = das_attention.flex_das_attention

    def counted(*args):
        traced.append(args[0].shape)
        return original(*args)

    patch = pytest.MonkeyPatch()
    patch.setattr(das_attention, "use_flex_attention",
                  lambda query, training: not training and torch.compiler.is_compiling())
    patch.setattr(das_attention, "flex_das_attention", counted)
    patch.setattr(flex_lowering, "lower_cpu", realised_captures(flex_lowering.lower_cpu))
    torch._dynamo.reset()
    try:
        compiled = torch.compile(flex, fullgraph=True, dynamic=False)
        results = {"fp32": [], "bf16": [], "flex": []}
        for images, packed in inputs:      # each step writes its ring slot, as in the node
            results["fp32"].append(outputs_of(fp32, images, packed))
            results["bf16"].append(outputs_of(bf16, images, packed))
            results["flex"].append(outputs_of(compiled, images, packed))
    finally:
        patch.undo()
        torch._dynamo.reset()
    return results, traced, cfg


def agreement(a, b) -> float:
    return float((a[0] == b[0]).mean())


def test_the_compiled_step_traced_flex_attention_at_odg_t_sizes(steps):
    _, traced, cfg = steps
    # every layer's attention, once per trace (Dynamo may trace the step more than once)
    assert len(traced) >= cfg.num_layers and len(traced) % cfg.num_layers == 0, len(traced)
    assert all(tuple(s) == (1, cfg.num_heads, QUERIES, HEAD_DIM) for s in traced)


def test_flex_attention_in_bf16_is_as_close_to_fp32_as_eager_bf16(steps):
    results, _, cfg = steps
    for fp32, bf16, flex in zip(results["fp32"], results["bf16"], results["flex"]):
        occupied = (fp32[0] != cfg.num_classes).mean()
        assert occupied > 0.01                                    # a real comparison
        sdpa_agreement, flex_agreement = agreement(bf16, fp32), agreement(flex, fp32)
        assert sdpa_agreement > 0.99, sdpa_agreement
        assert flex_agreement >= sdpa_agreement - 0.002, (flex_agreement, sdpa_agreement)
        sdpa_error = np.abs(bf16[2] - fp32[2]).max()
        flex_error = np.abs(flex[2] - fp32[2]).max()               # boxes, metres
        assert flex_error <= 2 * sdpa_error + 1e-2, (flex_error, sdpa_error)
