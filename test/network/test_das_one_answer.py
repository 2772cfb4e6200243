"""DaS attention gives one answer in every mode: the compiled FlexAttention path (the node's
compiled and graphs steps) and the SDPA path (eager, training) both compute the distance bias
and the softmax in float32, in fp32 and with bf16 q, k, v alike. FlexAttention is compiled by
Inductor here on the CPU (one graph, ~1 minute). Queries spread over +-40 m, where a bf16
distance steps by 0.25 m; both are held to a float64 attention of the same inputs."""
import math

import pytest
import torch

from odg_ros.network.das_attention import (DaSAttention, flex_das_attention,
                                           sdpa_das_attention)

HEADS, QUERIES, DIM, DYNAMIC = 2, 48, 16, 12
# the norm of the error over the norm of the float64 attention of the same inputs
FP32_TOLERANCE = 1e-5
BF16_TOLERANCE = 5e-3    # the output's own bf16 rounding: ~2e-3; with a bf16 bias: ~3e-2


def attention_inputs(bf16: bool):
    """q, k, v [1, H, Q, d] (bf16: rounded to bf16, as the autocast projection gives them),
    centroids [1, Q, 3] and tau [1, H, Q] (float32, the values of a bf16 tau when bf16)."""
    g = torch.Generator().manual_seed(5)
    q, k, v = (torch.randn(1, HEADS, QUERIES, DIM, generator=g) for _ in range(3))
    centroids = torch.rand(1, QUERIES, 3, generator=g) * torch.tensor([80.0, 80.0, 6.0]) \
        - torch.tensor([40.0, 40.0, 3.0])
    tau = 0.2 + 0.8 * torch.rand(1, HEADS, QUERIES, generator=g)
    if bf16:
        q, k, v = (t.bfloat16() for t in (q, k, v))
        tau = tau.bfloat16().float()
    return q, k, v, centroids, tau


def float64_attention(q, k, v, centroids, tau, num_dynamic):
    q, k, v, centroids, tau = (t.double() for t in (q, k, v, centroids, tau))
    scores = q @ k.transpose(-1, -2) / math.sqrt(q.shape[-1])
    scores = scores - tau[..., None] * torch.cdist(centroids, centroids)[:, None]
    if num_dynamic is not None:
        is_dynamic = torch.arange(q.shape[2]) < num_dynamic
        scores = scores.masked_fill(is_dynamic[:, None] != is_dynamic[None, :], -math.inf)
    return torch.softmax(scores, -1) @ v


def error(out, reference) -> float:
    return float((out.double() - reference).norm() / reference.norm())


CASES = {"fp32": (False, None), "bf16": (True, None), "bf16 within the sets": (True, DYNAMIC)}


def flex_of_every_case(*inputs):
    return [flex_das_attention(*inputs[5 * i:5 * i + 5], num_dynamic)
            for i, (_, num_dynamic) in enumerate(CASES.values())]


@pytest.fixture(scope="module")
def answers():
    """{case: (float64 attention, SDPA path, compiled FlexAttention)}."""
    inputs = {name: attention_inputs(bf16) for name, (bf16, _) in CASES.items()}
    torch._dynamo.reset()
    compiled = torch.compile(flex_of_every_case, fullgraph=True, dynamic=False)
    with torch.no_grad():
        flex = compiled(*(t for case in inputs.values() for t in case))
    torch._dynamo.reset()
    return {name: (float64_attention(*inputs[name], num_dynamic),
                   sdpa_das_attention(*inputs[name], num_dynamic), out)
            for (name, (_, num_dynamic)), out in zip(CASES.items(), flex)}


@pytest.mark.parametrize("case", list(CASES))
def test_flex_and_sdpa_attend_as_float64_does(answers, case):
    reference, sdpa, flex = answers[case]
    tolerance = FP32_TOLERANCE if case == "fp32" else BF16_TOLERANCE
    assert sdpa.dtype == flex.dtype == (torch.float32 if case == "fp32" else torch.bfloat16)
    assert error(sdpa, reference) < tolerance, error(sdpa, reference)
    assert error(flex, reference) < tolerance, error(flex, reference)


def test_the_module_takes_the_sdpa_path_in_float32_under_autocast():
    """DaSAttention under bf16 autocast on the CPU: q, k, v in bf16, the bias and softmax in
    float32, the same as the SDPA function on the same inputs."""
    torch.manual_seed(0)
    module = DaSAttention(32, HEADS, dropout=0.0).eval()
    query, centroids = torch.randn(1, QUERIES, 32), torch.rand(1, QUERIES, 3) * 80 - 40
    with torch.no_grad(), torch.autocast("cpu", dtype=torch.bfloat16):
        out = module(query, centroids, DYNAMIC)
        q, k, v = module.qkv(query).view(1, QUERIES, 3, HEADS, -1).permute(2, 0, 3, 1, 4)
        tau = module.gen_tau(query).permute(0, 2, 1)
        expected = module.proj(sdpa_das_attention(q, k, v, centroids, tau, None)
                               .transpose(1, 2).reshape(1, QUERIES, 32))
    assert q.dtype == torch.bfloat16
    torch.testing.assert_close(out, expected, rtol=0, atol=0)
