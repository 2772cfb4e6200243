"""The markdown tables of a GPU report (docs/reports/YYYY-MM-DD-<device>.md) from the results
of ``tools/gpu_checks.sh`` in OUT: paste them, then write what they say.

    python -m tools.gpu_report OUT [--skip-steps 4] > tables.md
    python -m tools.gpu_report WORK --first [--summary-json SUMMARY] > summary.md
    python -m tools.gpu_report --machine > machine.json

Reads what is there (every part is optional): machine.json, tests*.xml, train_*.csv,
gpu_util_*.csv, profile_*.json, sync_debug_*.json, node_*.json, backbone.json, bench.json,
eval_*.json, demo.json. A file that cannot be read is named in one line in the output instead
of its table. ``--first``: the summary of the ``first`` part of tools/gpu_checks.sh (its
checks, and the figures it is for against their targets), readable without the archive.
``--machine``: what this machine is (GPU, torch, CUDA, Python, numpy, gsplat) as JSON.
"""
from __future__ import annotations

import argparse
import csv
import json
import re
import statistics
import sys
import xml.etree.ElementTree as ET
from pathlib import Path


def table(header: list[str], rows: list[list]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join("" if v is None else str(v) for v in row) + " |" for row in rows]
    return "\n".join(lines)


def fmt(value, digits=2) -> str:
    if value is None:
        return "-"
    if isinstance(value, float):
        return f"{value:,.{digits}f}"
    return f"{value:,}" if isinstance(value, int) else str(value)


def machine(out: Path) -> str:
    m = json.loads((out / "machine.json").read_text())
    gpu = m.get("device") or "no GPU"
    extra = f", {m['memory_gib']} GiB, capability {m['capability']}" if m.get("device") else ""
    return (f"Machine: **{gpu}**{extra}; PyTorch {m['torch']} (CUDA {m.get('cuda')}), "
            f"Python {m['python']}, gsplat {m.get('gsplat', 'not installed')}.")


def tests(out: Path) -> str:
    rows = []
    for path in sorted(out.glob("tests*.xml")):
        suite = ET.parse(path).getroot()
        suite = suite if suite.tag == "testsuite" else suite.find("testsuite")
        n = {k: int(suite.get(k, 0)) for k in ("tests", "failures", "errors", "skipped")}
        failed = [f"{c.get('name')}" for c in suite.iter("testcase")
                  if c.find("failure") is not None or c.find("error") is not None]
        rows.append([path.name, n["tests"] - n["failures"] - n["errors"] - n["skipped"],
                     n["failures"] + n["errors"], n["skipped"], ", ".join(failed) or "-"])
    return table(["junit file", "passed", "failed", "skipped", "failed tests"], rows)


def batch_of(name: str) -> int:
    match = re.search(r"_b(\d+)$", name)
    return int(match.group(1)) if match else 1


def train(out: Path, skip_steps: int) -> str:
    """Seconds per step: the median over the steps after the first ``skip_steps`` (warm-up,
    compiling). The log's seconds are per step, averaged between two reads of the losses."""
    rows = []
    for path in sorted(out.glob("train_*.csv")):
        with path.open() as f:
            log = list(csv.DictReader(f))
        name = path.stem[len("train_"):]
        timed = [float(r["seconds"]) for r in log[skip_steps:] if r.get("seconds")]
        first = [float(r["seconds"]) for r in log[:skip_steps] if r.get("seconds")]
        if not timed:
            rows.append([name, len(log), "-", "-", "-", "-", "too few steps"])
            continue
        seconds = statistics.median(timed)
        batch = batch_of(name)
        skipped = log[-1].get("skipped_total", "0") if log else "0"
        rows.append([name, len(log), batch, fmt(seconds, 3), fmt(seconds / batch, 3),
                     fmt(batch / seconds), fmt(sum(first), 1) + " s" if first else "-",
                     f"{skipped} skipped"])
    return table(["run", "steps", "batch", "s/step (median)", "s/sample", "samples/s",
                  f"first {skip_steps} steps", "notes"], rows)


def gpu_util(out: Path) -> str:
    rows = []
    for path in sorted(out.glob("gpu_util_*.csv")):
        samples = []
        with path.open() as f:
            for line in f:
                fields = [x.strip() for x in line.split(",")]
                try:
                    samples.append((float(fields[1]), float(fields[2])))
                except (IndexError, ValueError):
                    continue   # the header, a truncated last line
        if not samples:
            rows.append([path.stem, 0, "-", "-", "-"])
            continue
        util = [u for u, _ in samples]
        busy = [u for u in util if u > 0]
        rows.append([path.stem[len("gpu_util_"):], len(samples), fmt(statistics.mean(util), 0),
                     fmt(statistics.median(busy), 0) if busy else "-",
                     fmt(max(m for _, m in samples) / 1024, 1)])
    return table(["part", "samples (200 ms)", "mean GPU util %", "median util % while busy",
                  "peak memory GiB"], rows)


def profile(out: Path) -> str:
    rows, kernels = [], []
    for path in sorted(out.glob("profile_*.json")):
        p = json.loads(path.read_text())
        gpu = p.get("gpu") or {}
        phases = ", ".join(f"{k} {v['ops']:,.0f}/{v['syncs']:,.0f}"
                           for k, v in p.get("by_phase", {}).items() if v["ops"] or v["syncs"])
        rows.append([p["preset"], f"{p['image_size'][0]} x {p['image_size'][1]}",
                     p.get("device", "-"), fmt(p["ops_per_step"], 0), fmt(p["syncs_per_step"], 0),
                     fmt(gpu.get("wall_s"), 3), fmt(gpu.get("kernel_s"), 3),
                     fmt(100 * gpu["busy"], 0) if "busy" in gpu else "-", phases])
        for k in gpu.get("top_kernels", [])[:5]:
            kernels.append([p["preset"], k["name"][:60], k["calls"], fmt(1e3 * k["seconds"], 1)])
    text = table(["preset", "input", "device", "ops/step", "host syncs/step", "wall s",
                  "kernel s", "busy %", "ops/syncs by phase"], rows)
    if kernels:
        text += "\n\n" + table(["preset", "kernel", "calls", "ms"], kernels)
    return text


def host_waits(out: Path) -> str:
    """A training step's host waits: CUDA's sync-debug warnings against the census."""
    rows, differing = [], []
    runs = []
    for path in sorted(out.glob("sync_debug_*.json")):
        data = json.loads(path.read_text())
        runs += data if isinstance(data, list) else [data]     # one batch size or several
    for r in runs:
        warned = r.get("sync_debug_waits")
        census = r.get("census_cuda_paths_waits", r.get("census_cuda_waits"))
        rows.append([f"{r['preset']} {r['image_size'][0]} x {r['image_size'][1]}, "
                     f"{r['frames']} frames", r["batch_size"], fmt(warned),
                     fmt(r.get("census_cuda_waits"), 0), fmt(r.get("census_cuda_paths_waits"), 0),
                     fmt(r.get("census_cuda_paths_ops"), 0),
                     "-" if warned is None or census is None else
                     ("yes" if warned == census else "no")])
        lines = {"sync-debug": r.get("sync_debug_lines") or {},
                 "census": r.get("census_cuda_paths_lines") or r.get("census_cuda_lines") or {}}
        for line in sorted(set().union(*lines.values())):
            counts = [lines[k].get(line, 0) for k in lines]
            if warned is not None and counts[0] != counts[1]:
                differing.append([r["batch_size"], line] + [fmt(c, 0) for c in counts])
    text = table(["step", "batch", "sync-debug warnings", "census on CUDA",
                  "census, CUDA paths on the CPU", "launched ops (census)",
                  "sync-debug = census"], rows)
    if differing:
        text += ("\n\nSource lines where the counts differ:\n\n"
                 + table(["batch", "line", "sync-debug", "census"], differing))
    return text


def backbone(out: Path) -> str:
    r = json.loads((out / "backbone.json").read_text())
    rows = [[mode] + [fmt(v, 3) for v in times.values()] for mode, times in r["ms"].items()]
    header = ["mode"] + [f"{k} ms" if "/" not in k else k
                         for k in next(iter(r["ms"].values()))]
    return (f"{r['preset']}, {r['precision']}, input {' x '.join(map(str, r['input']))}, "
            f"{r['device']}; target: ours / fastest reference <= 1.2\n\n"
            + table(header, rows))


def node(out: Path) -> str:
    rows, errors = [], []
    for path in sorted(out.glob("node_*.json")):
        r = json.loads(path.read_text())
        for name, m in r["modes"].items():
            lat = m["latency_ms"]
            rows.append([path.stem[len("node_"):], name, f"{r['input'][2]} x {r['input'][3]}",
                         r["frames"], fmt(lat["step"], 1), fmt(lat["model"], 1), fmt(m["fps"], 1),
                         fmt(m["speedup"]), fmt(m["startup_s"], 1),
                         fmt(m["grid_agreement_min"], 4), fmt(m["occupied_agreement_min"], 4)])
            if "max_difference" in m:
                errors.append([path.stem[len("node_"):], name] + [
                    ", ".join(f"{k} {v:.3g}" for k, v in m["max_difference"].items())])
    text = table(["run", "variant", "input", "frames", "step ms", "model ms", "FPS",
                  "speedup", "start-up s", "grid agreement (min)", "occupied agreement (min)"],
                 rows)
    if errors:
        text += ("\n\nLargest differences against each run's first variant:\n\n"
                 + table(["run", "variant", "max |difference|"], errors))
    return text


def bench(out: Path) -> str:
    rows = []
    for name, r in sorted(json.loads((out / "bench.json").read_text()).items()):
        if "modes" in r:                     # odg bench: the node's step, one variant
            mode, m = next(iter(r["modes"].items()))
            name, lat, fps, total = f"{name} ({mode})", m["latency_ms"], m["fps"], "step"
        else:                                # before the bench timed the node's own step
            lat, fps, total = r["latency_ms"], r["fps"], "total"
        stages = " / ".join(fmt(lat.get(k), 1) for k in ("backbone", "decoder", "postprocess"))
        rows.append([name, f"{r['input'][2]} x {r['input'][3]}", r["frames"], fmt(fps, 1),
                     f"{lat[total]:.1f} ({stages})", fmt(r.get("peak_memory_mb", 0) / 1024, 1)])
    return table(["model-precision", "input", "frames", "FPS",
                  "ms (backbone / decoder / post)", "peak memory GB"], rows)


def scores(out: Path) -> str:
    rows = []
    for path in sorted(out.glob("eval_*.json")):
        e = json.loads(path.read_text())
        rows.append([path.stem[len("eval_"):], fmt(e["mIoU"]), fmt(e["RayIoU"]),
                     fmt(e["IoU_geometry"]), fmt((e.get("boxes") or {}).get("mAP"))])
    return table(["eval on", "mIoU", "RayIoU", "geometry IoU", "box mAP"], rows)


def demo(out: Path) -> str:
    d = json.loads((out / "demo.json").read_text())
    keys = ["frames_in", "frames_out", "dropped", "fps", "latency_ms_p50", "latency_ms_p95",
            "mIoU", "RayIoU", "keyframes_scored"]
    return table(keys, [[fmt(d.get(k)) for k in keys]])


def report(out: Path, skip_steps: int = 4) -> str:
    sections = [("Machine", "machine.json", machine), ("Tests", "tests*.xml", tests),
                ("Training speed", "train_*.csv", lambda out: train(out, skip_steps)),
                ("GPU utilisation", "gpu_util_*.csv", gpu_util),
                ("Training step on the GPU (odg profile train)", "profile_*.json", profile),
                ("Host waits of a training step: CUDA's sync-debug mode against the census",
                 "sync_debug_*.json", host_waits),
                ("The node's step (odg bench --compile)", "node_*.json", node),
                ("The node step's backbone against a plain forward", "backbone.json",
                 backbone),
                ("The node's step per stage (odg bench)", "bench.json", bench),
                ("The shipped checkpoint scored", "eval_*.json", scores),
                ("odg demo end to end", "demo.json", demo)]
    parts = []
    for title, pattern, make in sections:
        if not any(out.glob(pattern)):
            continue
        try:
            body = make(out)
        except (OSError, ValueError, KeyError, TypeError, ET.ParseError) as error:
            body = f"(not summarised: {pattern}: {type(error).__name__}: {error})"
        parts.append(f"### {title}\n\n{body}")
    return "\n\n".join(parts) + "\n"


def machine_info() -> dict:
    """What this machine is: Python, torch, CUDA, numpy, the GPU, gsplat's version."""
    import platform

    import numpy
    import torch
    info = {"python": platform.python_version(), "torch": torch.__version__,
            "cuda": torch.version.cuda, "numpy": numpy.__version__, "device": None}
    if torch.cuda.is_available():
        p = torch.cuda.get_device_properties(0)
        info.update(device=p.name, memory_gib=round(p.total_memory / 2**30, 1),
                    capability=f"{p.major}.{p.minor}", multiprocessors=p.multi_processor_count)
    try:
        import gsplat
        info["gsplat"] = gsplat.__version__
    except ImportError:
        pass
    return info


# the first call's figures and their targets (an H100; docs/gpu_checks.md)
TARGETS = {"node_step_fps": 100.0, "open_road_decoder_speedup": 1.5, "training_waits": 8}


def _read(path: Path):
    return json.loads(path.read_text()) if path.is_file() else None


def first_figures(work: Path) -> dict:
    """The figures of a ``first`` run (its WORK folder), as one dictionary; what a check did
    not make is missing."""
    figures = {"checks": [json.loads(line) for line in
                          (work / "checks.jsonl").read_text().splitlines() if line.strip()]
               if (work / "checks.jsonl").is_file() else [],
               "targets": TARGETS}
    for name in ("machine", "node_step", "budgets", "training_step", "flex_attention"):
        try:
            value = _read(work / f"{name}.json")
        except ValueError as error:
            figures.setdefault("unreadable", []).append(f"{name}.json: {error}")
            continue
        if value is not None:
            figures[name] = value
    node_step = figures.get("node_step")
    if node_step:
        figures["node_step"] = {
            "preset": node_step.get("preset"), "precision": node_step.get("precisions"),
            "modes": {name: {"fps": m.get("fps"), "step_ms": m.get("latency_ms", {}).get("step"),
                             "startup_s": m.get("startup_s"),
                             "grid_agreement_min": m.get("grid_agreement_min")}
                      for name, m in node_step.get("modes", {}).items()}}
    return figures


def first_summary(figures: dict) -> str:
    """The markdown summary of ``first_figures``."""
    lines = ["# tools/gpu_checks.sh first"]
    m = figures.get("machine")
    if m:
        lines.append(f"Machine: **{m.get('device') or 'no GPU'}**, torch {m.get('torch')} "
                     f"(CUDA {m.get('cuda')}), Python {m.get('python')}, numpy "
                     f"{m.get('numpy')}.")
    lines.append("## Checks\n\n" + table(
        ["check", "status", "seconds", "limit s"],
        [[c.get("check"), c.get("status"), c.get("seconds"), c.get("limit")]
         for c in figures["checks"]]))
    rows = []
    node_step = figures.get("node_step")
    for name, mode in (node_step or {}).get("modes", {}).items():
        rows.append([f"node step {node_step['preset']}, {name} (bf16)", fmt(mode["fps"], 1),
                     ">= 100 FPS (H100)" if name.startswith("graphs") else "",
                     f"step {fmt(mode['step_ms'], 2)} ms, start-up {fmt(mode['startup_s'], 1)} "
                     f"s, grids agree {fmt(mode['grid_agreement_min'], 4)}"])
    for b in figures.get("budgets") or []:
        road = b["open_road"]
        full = b["predictors"]["full"]["step_ms"].get("full")
        rows.append([f"{b['preset']} step, full budget, graphs of the eager step",
                     fmt(1e3 / full, 1) if full else "-", "", "FPS"])
        rows.append([f"{b['preset']} decoder: full / auto on the open road",
                     fmt(road["speedup"]), ">= 1.5 (ODG-L)" if b["preset"] == "odg_l" else "",
                     f"{fmt(road['full_decoder_ms'], 2)} / {fmt(road['auto_decoder_ms'], 2)} ms "
                     f"({fmt(100 * road['refined'], 0)} % refined)"])
    for r in figures.get("training_step") or []:
        rows.append([f"training step {r['preset']} {r['image_size'][0]} x {r['image_size'][1]}, "
                     f"{r['frames']} frames, batch {r['batch_size']}",
                     fmt(r.get("seconds_per_sample"), 3), "s per sample",
                     f"host waits: sync-debug {fmt(r.get('sync_debug_waits'))}, census "
                     f"{fmt(r.get('census_cuda_waits'), 0)} (target <= 8)"])
    if rows:
        lines.append("## Figures\n\n" + table(["what", "value", "target", "notes"], rows))
    details = []
    for b in figures.get("budgets") or []:
        for setting, p in b["predictors"].items():
            details.append([b["preset"], setting, p["captures"], ", ".join(p["budgets"]),
                            fmt(p["grid_agreement_min"], 4),
                            ", ".join(f"{k} {v:.2f}" for k, v in p.get("step_ms", {}).items())])
    if details:
        lines.append("## Query budgets as CUDA graphs (one capture per budget)\n\n" + table(
            ["preset", "query_budget", "graphs", "budgets", "grid agreement with eager (min)",
             "step ms"], details) + "\n\nDecoder ms by budget: " + "; ".join(
            f"{b['preset']}: " + ", ".join(f"{k} {v:.2f}" for k, v in b["decoder_ms"].items())
            for b in figures["budgets"]))
    flex = figures.get("flex_attention")
    if flex:
        lines.append("## DaS attention, bf16 autocast: compiled FlexAttention and SDPA\n\n"
                     + table(["queries", "compile s", "flex error", "sdpa error", "flex ms",
                              "sdpa ms", "flex peak MiB", "sdpa peak MiB",
                              "module compiled, bf16 vs fp32"],
                             [[s["queries"], s["compile_s"], f"{s['flex_error']:.1e}",
                               f"{s['sdpa_error']:.1e}", s["flex_ms"], s["sdpa_ms"],
                               s["flex_peak_mib"], s["sdpa_peak_mib"],
                               f"{s['module']['error']:.1e}" if "error" in s.get("module", {})
                               else s.get("module", {}).get("failed", "-")]
                              for s in flex["sizes"]])
                     + f"\n\nError: relative to a float64 attention; tolerance "
                       f"{flex['tolerance']}.")
    for problem in figures.get("unreadable", []):
        lines.append(f"(not summarised: {problem})")
    return "\n\n".join(lines) + "\n"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("out", type=Path, nargs="?",
                        help="the OUT folder of tools/gpu_checks.sh (with --first: its WORK)")
    parser.add_argument("--skip-steps", type=int, default=4,
                        help="training steps left out of the medians (warm-up, compile; "
                             "default 4, one read of the losses)")
    parser.add_argument("--first", action="store_true",
                        help="the summary of the first part (OUT is its WORK folder)")
    parser.add_argument("--summary-json", type=Path,
                        help="--first: also write its figures here as JSON")
    parser.add_argument("--machine", action="store_true",
                        help="print what this machine is as JSON, and nothing else")
    args = parser.parse_args(argv)
    if args.machine:
        print(json.dumps(machine_info(), indent=1))
        return 0
    if args.out is None or not args.out.is_dir():
        print(f"gpu_report: no folder {args.out}", file=sys.stderr)
        return 2
    if args.first:
        figures = first_figures(args.out)
        if args.summary_json:
            args.summary_json.write_text(json.dumps(figures, indent=1))
        sys.stdout.write(first_summary(figures))
        return 0
    sys.stdout.write(report(args.out, args.skip_steps))
    return 0


if __name__ == "__main__":
    sys.exit(main())
