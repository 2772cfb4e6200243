"""DaS attention at the presets' sizes on a GPU: the compiled FlexAttention path (what the
node's compiled and graphs steps run on CUDA) and the SDPA path with a materialised bias
(eager, training), each under bf16 autocast, against a float64 attention of the same inputs,
and their times and peak memory.

    python -m tools.flex_attention_check [--queries 600 4800] [--heads 8] [--head-dim 32]
        [--iters 20] [--json OUT]

The inputs are as the decoder gives them under bf16 autocast: q, k, v in bf16 (the output of
an autocast projection), query centroids spread over +-40 m x +-40 m x +-3 m (where a bf16
distance steps by 0.25 m) and per-query, per-head tau in 0.2-1.0. Errors: the norm of the
difference over the norm of the float64 attention. ODG-T has 600 queries, ODG-L 4,800, both 8
heads of 32 channels. ``module``: the whole DaSAttention (projections, tau) as the decoder
runs it, compiled with FlexAttention under bf16 autocast, against its fp32 eager (SDPA) path;
if the compile fails, its error. ``--device cpu`` is a dry run (use small --queries).
"""
from __future__ import annotations

import argparse
import json
import math
import statistics
import sys
import time

import torch

from odg_ros.network import das_attention
from odg_ros.network.das_attention import DaSAttention, flex_das_attention, sdpa_das_attention
from tools.gpu_tool import parse_args, write_json

# the output's own bf16 rounding is ~2e-3 of its norm; a bias computed in bf16 gives ~3e-2
BF16_TOLERANCE = 5e-3


def attention_inputs(queries: int, heads: int, head_dim: int, device, seed: int = 5):
    g = torch.Generator().manual_seed(seed)
    q, k, v = (torch.randn(1, heads, queries, head_dim, generator=g).bfloat16()
               for _ in range(3))
    centroids = torch.rand(1, queries, 3, generator=g) * torch.tensor([80.0, 80.0, 6.0]) \
        - torch.tensor([40.0, 40.0, 3.0])
    tau = (0.2 + 0.8 * torch.rand(1, heads, queries, generator=g)).bfloat16().float()
    return [t.to(device) for t in (q, k, v, centroids, tau)]


def float64_attention(q, k, v, centroids, tau):
    q, k, v, centroids, tau = (t.double() for t in (q, k, v, centroids, tau))
    scores = q @ k.transpose(-1, -2) / math.sqrt(q.shape[-1])
    scores = scores - tau[..., None] * torch.cdist(centroids, centroids)[:, None]
    return torch.softmax(scores, -1) @ v


def relative_error(out, reference) -> float:
    return float((out.double() - reference).norm() / reference.norm())


def timed(function, inputs, iters: int, device) -> tuple[float, float]:
    """(median ms, peak memory MiB above the inputs) of ``function(*inputs)``."""
    cuda = device.type == "cuda"
    if cuda:
        torch.cuda.synchronize()
        torch.cuda.reset_peak_memory_stats()
        base = torch.cuda.memory_allocated()
    times = []
    for _ in range(iters):
        if cuda:
            start, end = (torch.cuda.Event(enable_timing=True) for _ in range(2))
            start.record()
            function(*inputs)
            end.record()
            end.synchronize()
            times.append(start.elapsed_time(end))
        else:
            start = time.perf_counter()
            function(*inputs)
            times.append(1e3 * (time.perf_counter() - start))
    peak = (torch.cuda.max_memory_allocated() - base) / 2**20 if cuda else 0.0
    return statistics.median(times), peak


def module_check(queries: int, args, device) -> dict:
    """DaSAttention as the decoder runs it (its projections and tau in bf16 under autocast)
    compiled with FlexAttention, against its eager SDPA path in fp32: the relative error,
    or the first line of the error the compile raised."""
    torch.manual_seed(0)
    embed = args.heads * args.head_dim
    module = DaSAttention(embed, args.heads, dropout=0.0).to(device).eval()
    torch.nn.init.normal_(module.gen_tau.weight, std=0.01)        # tau differs per query
    g = torch.Generator().manual_seed(1)
    query = torch.randn(1, queries, embed, generator=g).to(device)
    centroids = (torch.rand(1, queries, 3, generator=g) * torch.tensor([80.0, 80.0, 6.0])
                 - torch.tensor([40.0, 40.0, 3.0])).to(device)
    original = das_attention.use_flex_attention
    das_attention.use_flex_attention = \
        lambda q, training: not training and torch.compiler.is_compiling()
    torch._dynamo.reset()
    try:
        with torch.no_grad():
            reference = module(query, centroids, 0)
            compiled = torch.compile(lambda q, c: module(q, c, 0), fullgraph=True,
                                     dynamic=False)
            with torch.autocast(device.type, dtype=torch.bfloat16):
                out = compiled(query, centroids)
        return {"error": relative_error(out, reference.double()), "dtype": str(out.dtype)}
    except Exception as error:                   # what a compile on this machine raises
        return {"failed": f"{type(error).__name__}: {str(error).splitlines()[0][:300]}"}
    finally:
        das_attention.use_flex_attention = original
        torch._dynamo.reset()


def check(queries: int, args, device) -> dict:
    inputs = attention_inputs(queries, args.heads, args.head_dim, device)
    reference = float64_attention(*inputs)

    def flex(*xs):
        with torch.autocast(device.type, dtype=torch.bfloat16):
            return flex_das_attention(*xs, None)

    def sdpa(*xs):
        with torch.autocast(device.type, dtype=torch.bfloat16):
            return sdpa_das_attention(*xs, None)

    result = {"queries": queries, "heads": args.heads, "head_dim": args.head_dim,
              "module": module_check(queries, args, device)}
    torch._dynamo.reset()
    compiled = torch.compile(flex, fullgraph=True, dynamic=False)
    with torch.no_grad():
        start = time.perf_counter()
        flex_out = compiled(*inputs)
        if device.type == "cuda":
            torch.cuda.synchronize()
        result["compile_s"] = round(time.perf_counter() - start, 1)
        sdpa_out = sdpa(*inputs)
        for name, out in (("flex", flex_out), ("sdpa", sdpa_out)):
            result[f"{name}_dtype"] = str(out.dtype).removeprefix("torch.")
            result[f"{name}_error"] = relative_error(out, reference)
        for name, function in (("flex", compiled), ("sdpa", sdpa)):
            ms, peak = timed(function, inputs, args.iters, device)
            result[f"{name}_ms"] = round(ms, 4)
            result[f"{name}_peak_mib"] = round(peak, 1)
    result["within_tolerance"] = all(result[f"{n}_error"] < BF16_TOLERANCE
                                     for n in ("flex", "sdpa"))
    # the module in bf16 against fp32 carries bf16's error of the projections too
    result["module_ok"] = result["module"].get("error", 1.0) < 10 * BF16_TOLERANCE
    return result


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--queries", type=int, nargs="+", default=[600, 4800],
                        help="query counts (default: ODG-T's and ODG-L's)")
    parser.add_argument("--heads", type=int, default=8)
    parser.add_argument("--head-dim", type=int, default=32)
    parser.add_argument("--iters", type=int, default=20)
    parser.add_argument("--device", default="cuda", choices=("cuda", "cpu"),
                        help="cuda; cpu: a dry run")
    args = parse_args(parser, argv, "flex_attention_check", "--device cpu: a dry run")
    if args is None:
        return 2
    device = torch.device(args.device)
    results = {"device": torch.cuda.get_device_name() if device.type == "cuda" else "cpu",
               "torch": torch.__version__, "tolerance": BF16_TOLERANCE, "sizes": []}
    for queries in args.queries:
        results["sizes"].append(check(queries, args, device))
        print(f"flex_attention_check: {json.dumps(results['sizes'][-1])}", flush=True)
        write_json(args.json, results)         # each size as soon as it is measured
    return 0 if all(r["within_tolerance"] and r["module_ok"] for r in results["sizes"]) else 1


if __name__ == "__main__":
    sys.exit(main())
