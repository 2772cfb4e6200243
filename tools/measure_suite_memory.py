"""Peak memory of a command and every process it starts (e.g. the test suite), sampled.

    python -m tools.measure_suite_memory [--every 0.5] [--json OUT] -- python -m pytest -q test

Every ``--every`` seconds it walks the command's process tree (through /proc, Linux) and sums
the resident set sizes (RSS: shared library pages count once per process) and the
proportional set sizes (PSS: shared pages split among the processes that map them, so the
sum is what the tree really holds). Printed at the end: the peak of each sum, when it
happened and which command lines held the most then, the largest single process, and the
command's exit code (also this script's). A sampler misses peaks shorter than the interval.

``--stop-below GB``: stop the command (its process group) when the machine's available
memory falls under this, so that a measurement on a shared machine cannot starve the others.
"""
from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path


def _children() -> dict[int, list[int]]:
    tree: dict[int, list[int]] = {}
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            stat = (entry / "stat").read_text()
        except OSError:
            continue
        parent = int(stat[stat.rindex(")") + 2:].split()[1])
        tree.setdefault(parent, []).append(int(entry.name))
    return tree


def process_tree(root: int) -> list[int]:
    """``root`` and all its descendants alive now."""
    tree, found, todo = _children(), [], [root]
    while todo:
        pid = todo.pop()
        found.append(pid)
        todo += tree.get(pid, [])
    return found


def memory_kib(pid: int) -> tuple[int, int] | None:
    """(RSS, PSS) of one process in KiB; None once it is gone."""
    try:
        rss = next(int(line.split()[1]) for line in
                   Path(f"/proc/{pid}/status").read_text().splitlines()
                   if line.startswith("VmRSS:"))
        pss = next(int(line.split()[1]) for line in
                   Path(f"/proc/{pid}/smaps_rollup").read_text().splitlines()
                   if line.startswith("Pss:"))
    except (OSError, StopIteration, ValueError):
        return None                      # exited, or a kernel thread without memory
    return rss, pss


def command_line(pid: int) -> str:
    try:
        text = Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode()
    except OSError:
        return "?"
    return text.strip()[:120]


def available_gib() -> float:
    for line in Path("/proc/meminfo").read_text().splitlines():
        if line.startswith("MemAvailable:"):
            return int(line.split()[1]) / 2 ** 20
    return float("inf")


def measure(command: list[str], every: float = 0.5, stop_below: float = 0.0) -> dict:
    start = time.monotonic()
    process = subprocess.Popen(command, start_new_session=True)
    peak = {"rss_gib": 0.0, "pss_gib": 0.0, "largest_process_gib": 0.0}
    stopped = None
    while process.poll() is None:
        sample = {pid: m for pid in process_tree(process.pid)
                  if (m := memory_kib(pid)) is not None}
        rss = sum(m[0] for m in sample.values()) / 2 ** 20
        pss = sum(m[1] for m in sample.values()) / 2 ** 20
        largest = max((m[0] for m in sample.values()), default=0) / 2 ** 20
        if pss > peak["pss_gib"]:
            top = sorted(sample, key=lambda pid: -sample[pid][1])[:3]
            peak.update(pss_gib=pss, pss_at_s=round(time.monotonic() - start),
                        processes_at_pss_peak=len(sample),
                        top_at_pss_peak=[f"{sample[p][1] / 2 ** 20:.2f} GiB {command_line(p)}"
                                         for p in top])
        peak["rss_gib"] = max(peak["rss_gib"], rss)
        peak["largest_process_gib"] = max(peak["largest_process_gib"], largest)
        if stop_below and available_gib() < stop_below:
            stopped = f"available memory under {stop_below} GiB"
            os.killpg(process.pid, signal.SIGTERM)
            break
        time.sleep(every)
    code = process.wait()
    return {"command": command, "exit_code": code, "seconds": round(time.monotonic() - start),
            "every_s": every, "stopped": stopped,
            **{k: round(v, 2) if isinstance(v, float) else v for k, v in peak.items()}}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--every", type=float, default=0.5, help="seconds between samples")
    parser.add_argument("--stop-below", type=float, default=0.0, metavar="GB",
                        help="stop the command when available memory falls under this")
    parser.add_argument("--json", default=None, help="also write the result here")
    parser.add_argument("command", nargs=argparse.REMAINDER)
    args = parser.parse_args(argv)
    command = args.command[1:] if args.command[:1] == ["--"] else args.command
    if not command:
        parser.error("give the command to measure after --")
    result = measure(command, args.every, args.stop_below)
    print(json.dumps(result, indent=1))
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=1))
    return result["exit_code"] or (1 if result["stopped"] else 0)


if __name__ == "__main__":
    sys.exit(main())
