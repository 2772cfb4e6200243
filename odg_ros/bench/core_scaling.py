"""How much faster this machine runs a matrix product on all its cores than on one, measured
just before and after a timing: on a shared virtual machine the other cores come and go with
the neighbours' load, and a step time means little without it.

The product runs in a child process: once torch has run a parallel region here, an OpenMP
worker can be left spinning and add its time to the caller's later one-thread steps."""
from __future__ import annotations

import json
import os
import subprocess
import sys

# one fp32 product of SIZE x SIZE matrices: 25 to 30 ms on one core of this project's
# machine, large enough for every core to get whole blocks of it; the probe about 3 s
SIZE = 1024
REPEATS = 9

_CHILD = """
import json, statistics, sys, time
import torch
size, repeats, threads = (int(v) for v in sys.argv[1:4])
a = torch.randn(size, size, generator=torch.Generator().manual_seed(0))
times = {1: [], threads: []}
for _ in range(repeats):                 # the thread counts take turns
    for n in times:
        torch.set_num_threads(n)
        a @ a                            # the pool at this size, warm
        start = time.perf_counter()
        a @ a
        times[n].append(time.perf_counter() - start)
print(json.dumps({str(n): statistics.median(v) for n, v in times.items()}))
"""


def core_scaling(threads: int | None = None, size: int = SIZE, repeats: int = REPEATS) -> dict:
    """{"threads": n, "one_thread_ms", "threads_ms", "scaling"}: the median time of one
    product on one thread and on ``threads`` (default: one per core), and their ratio (n on
    n free cores, about 1 where the other cores are taken; it swung by 0.2 either way from
    one probe to the next on this project's 2-core machine)."""
    threads = int(threads or os.cpu_count() or 1)
    env = {**os.environ, "OMP_NUM_THREADS": str(threads)}
    done = subprocess.run([sys.executable, "-c", _CHILD, str(size), str(repeats), str(threads)],
                          capture_output=True, text=True, env=env, check=False)
    if done.returncode != 0:
        raise RuntimeError(f"the core-scaling probe failed: {done.stderr.strip()[-500:]}")
    medians = json.loads(done.stdout.strip().splitlines()[-1])
    one, many = medians["1"], medians[str(threads)]
    return {"threads": threads, "one_thread_ms": round(one * 1e3, 2),
            "threads_ms": round(many * 1e3, 2), "scaling": round(one / many, 2)}


def format_scaling(before: dict, after: dict) -> str:
    return (f"cores: a matrix product ran {before['scaling']:.2f}x as fast on "
            f"{before['threads']} threads as on one before, {after['scaling']:.2f}x after "
            f"({before['threads']:.0f}x: every core free)")
