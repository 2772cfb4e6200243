"""``odg soak``: odg_node fed a loop of scenes for a long while, at several replay rates.

    odg soak BAG [BAG ...] [--run RATE MINUTES ...] [--params-file F] [-p NAME:=VALUE ...]
    odg soak --synthetic DIR [--scene-seconds S] ...          scenes made there once, reused

Each run starts a fresh odg_node process (use_sim_time) and plays the bags back to back in a
loop with ``odg replay --clock --loop --rate RATE`` for MINUTES of wall time, watching the
node as a planner would (outputs, /diagnostics, its resident memory). Written to --out: the
dated report (``YYYY-MM-DD-soak.md``), its picture (``.png``) and its figures (``.json``);
to --logs: the node's logs and every record (``YYYY-MM-DD-soak-records.json``, kept as each
run ends; ``--from-json`` writes the report again from it). The runs are in a ROS domain of their own
(--domain-id) so that nothing else on the machine is heard.
"""
from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

from .common import UserError, positive_float, positive_int

RUNS = [(1.0, 5.0), (2.0, 5.0), (4.0, 5.0)]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("bags", type=Path, nargs="*", metavar="BAG",
                        help="rosbag2 bags or folders of bags, looped in this order")
    parser.add_argument("--synthetic", type=Path, default=None, metavar="DIR",
                        help="loop synthetic scenes of three kinds (city, open road, dense "
                             "traffic), made in DIR by odg synth + odg bag if not there yet "
                             "(default: none; the BAG arguments are played)")
    parser.add_argument("--scene-seconds", type=positive_float, default=20.0,
                        help="length of each synthetic scene")
    parser.add_argument("--image-size", type=positive_int, nargs=2, default=None,
                        metavar=("H", "W"), help="synthetic camera image size (default: "
                                                 "odg synth's)")
    parser.add_argument("--run", nargs=2, type=positive_float, action="append",
                        metavar=("RATE", "MINUTES"), default=None,
                        help="one run: the replay rate and its wall-clock minutes; repeat "
                             "(default: 1 5, 2 5, 4 5; none with --restarts)")
    parser.add_argument("--params-file", default=None,
                        help="the node's params file (e.g. config/bags/foxglove.yaml; default: "
                             "none, the node's defaults)")
    parser.add_argument("-p", "--param", action="append", default=[], metavar="NAME:=VALUE",
                        help="a node parameter; repeat")
    parser.add_argument("--topics", nargs="+", default=None, metavar="TOPIC",
                        help="topics to play (default: those the node subscribes to)")
    parser.add_argument("--remap", "-m", nargs="+", default=[], metavar="OLD:=NEW",
                        action="extend", help="the replay's topic remapping rules")
    parser.add_argument("--restarts", type=int, default=0, metavar="N",
                        help="after the runs: kill the node with SIGKILL mid-bag and start it "
                             "again, N times, at 1x; reports the time to its first output "
                             "and any stale output")
    parser.add_argument("--warmup-minutes", type=positive_float, default=5.0,
                        help="memory growth is measured after this (at most half a run)")
    parser.add_argument("--out", type=Path, default=Path("soak_report"),
                        help="folder of the dated report, picture and JSON")
    parser.add_argument("--logs", type=Path, default=None,
                        help="folder of the node's logs (default: a new temporary folder)")
    parser.add_argument("--domain-id", type=int, default=None,
                        help="ROS domain of the node and the replay (default: one from this "
                             "process's id, 1..100)")
    parser.add_argument("--quiet", action="store_true", help="no progress bars")
    parser.add_argument("--from-json", type=Path, default=None, metavar="JSON",
                        help="write the report again from an earlier soak's records "
                             "(LOGS/DATE-soak-records.json; nothing is run; default: none, a "
                             "soak is run)")


def run(args) -> int:
    from ..ros.dds import use_localhost_dds

    if args.from_json is not None:
        document = json.loads(args.from_json.read_text())
        context = {k: document[k] for k in ("command", "date", "bags", "logs")}
        # a soak cut short saved its records before it could describe the machine
        machine = document["machine"]
        context["machine"] = machine if "cpu" in machine else \
            _machine(machine.get("load_average_before", [float("nan")] * 3))
        paths = write_report(document["records"], context, args.out,
                             args.warmup_minutes * 60, document.get("restart_record"))
        print("\n".join(f"wrote {p}" for p in paths))
        return 0
    bags = list(args.bags)
    if args.synthetic is not None:
        from ..bench.soak_report import synthetic_scenes
        bags += synthetic_scenes(args.synthetic, args.scene_seconds, args.image_size,
                                 progress=not args.quiet)
    if not bags:
        raise UserError("give bags to loop, or --synthetic DIR")
    for bag in bags:
        if not bag.exists():
            raise FileNotFoundError(f"{bag}: not found")
    if args.params_file is not None and not Path(args.params_file).is_file():
        raise FileNotFoundError(f"params file {args.params_file}: not found")
    os.environ["ROS_DOMAIN_ID"] = str(args.domain_id if args.domain_id is not None
                                      else 1 + os.getpid() % 100)
    use_localhost_dds()
    logs = args.logs or Path(tempfile.mkdtemp(prefix="odg_soak_"))
    logs.mkdir(parents=True, exist_ok=True)
    node_args = ["--ros-args"] + (["--params-file", args.params_file]
                                  if args.params_file else [])
    for item in args.param:
        node_args += ["-p", item]
    started = time.time()
    context = {"command": "odg soak " + " ".join(sys.argv[2:] if sys.argv[1:2] == ["soak"]
                                                 else sys.argv[1:]),
               "date": datetime.date.fromtimestamp(started).isoformat(),
               "bags": [str(b) for b in bags], "logs": str(logs),
               "machine": {"load_average_before": list(os.getloadavg())}}
    records, restarts = [], None
    for rate, minutes in args.run or (RUNS if not args.restarts else []):
        records.append(_one_run(bags, float(rate), float(minutes), node_args, args, logs))
        # kept as they come: a long soak cut short still leaves its runs (--from-json)
        _save(logs, context, records)
    if args.restarts > 0:
        restarts = _restarts(bags, node_args, args, logs)
        _save(logs, context, records, restarts)
    context["machine"] = _machine(context["machine"]["load_average_before"])
    paths = write_report(records, context, args.out, args.warmup_minutes * 60, restarts)
    paths.append(_save(logs, context, records, restarts))
    print("\n".join(f"wrote {p}" for p in paths))
    return 0


def _one_run(bags, rate: float, minutes: float, node_args, args, logs: Path) -> dict:
    from tqdm import tqdm

    from ..ros.soak_run import soak_run

    seconds = minutes * 60
    bar = tqdm(total=round(seconds), desc=f"soak {rate:g}x", unit="s", disable=args.quiet)

    def tick(elapsed):
        bar.update(max(0, round(elapsed) - bar.n))
    try:
        return soak_run(bags, rate, seconds, node_args, topics=args.topics, remap=args.remap,
                        log_path=logs / f"node_{rate:g}x.log", tick=tick,
                        history_max_gap=float(_node_parameter(args, "history_max_gap")),
                        reference_image=_reference_image(args))
    except (RuntimeError, ValueError) as error:
        raise UserError(str(error)) from None
    finally:
        bar.close()


def _restarts(bags, node_args, args, logs: Path) -> dict:
    from ..ros.soak_run import restart_run
    print(f"odg soak: {args.restarts} restarts at 1x", file=sys.stderr, flush=True)
    try:
        return restart_run(bags, node_args, log_path=logs / "node_restarts.log",
                           restarts=args.restarts, reference_image=_reference_image(args),
                           topics=args.topics, remap=args.remap)
    except (RuntimeError, ValueError) as error:
        raise UserError(str(error)) from None


def _node_parameter(args, name: str):
    """A parameter's value as the node gets it: -p, else the params file, else its default."""
    import yaml

    from ..online.parameters import load_schema, params_file_parameters
    values = params_file_parameters(args.params_file) if args.params_file else {}
    for item in args.param:
        key, _, text = item.partition(":=")
        values[key.strip()] = yaml.safe_load(text)
    return values.get(name, load_schema()[name].default)


def _reference_image(args) -> tuple[str, bool]:
    """The node's first camera's image topic (its stamp is the outputs'), and whether it
    is compressed. A relative topic is in the soak's node namespace."""
    from ..ros.soak_run import NAMESPACE
    camera = _node_parameter(args, "camera_names")[0]
    topic = _node_parameter(args, "image_topic").format(camera=camera)
    if not topic.startswith("/"):
        topic = f"{NAMESPACE}/{topic}"
    return topic, _node_parameter(args, "image_transport") == "compressed"


def _machine(load_before) -> dict:
    import torch
    model = next((line.split(":", 1)[1].strip() for line in
                  Path("/proc/cpuinfo").read_text().splitlines()
                  if line.startswith("model name")), platform.processor()) \
        if Path("/proc/cpuinfo").is_file() else platform.processor()
    return {"cpu": model, "cores": os.cpu_count(), "torch": torch.__version__,
            "load_average_before": list(load_before),
            "load_average_after": list(os.getloadavg())}


def _save(out: Path, context: dict, records: list[dict], restarts: dict | None = None):
    out.mkdir(parents=True, exist_ok=True)
    path = out / f"{context['date']}-soak-records.json"
    path.write_text(json.dumps(dict(context, records=records, restart_record=restarts),
                               default=str))
    return path


def write_report(records: list[dict], context: dict, out: Path, warmup_s: float,
                 restart_record: dict | None = None) -> list[Path]:
    """The dated JSON (figures), PNG and Markdown report in ``out``."""
    from ..bench.soak_report import plot_soak, summarize, summarize_restarts, verdicts

    summaries = [summarize(r, warmup_s) for r in records]
    restarts = summarize_restarts(restart_record) if restart_record else None
    checks = verdicts(summaries, restarts=restarts)
    out.mkdir(parents=True, exist_ok=True)
    stem = out / f"{context['date']}-soak"
    picture = plot_soak(records, stem.with_suffix(".png"))
    document = dict(context, targets=checks, runs=summaries, restarts=restarts)
    stem.with_suffix(".json").write_text(json.dumps(document, indent=1, default=str))
    stem.with_suffix(".md").write_text(markdown(summaries, checks, context, picture.name,
                                                restarts))
    for line in summary_lines(summaries, checks):
        print(line)
    return [stem.with_suffix(".md"), picture, stem.with_suffix(".json")]


def _ms(p: dict) -> str:
    return " / ".join("-" if v is None else f"{v:.0f}" for v in p.values())


def _in_stalls(summary: dict) -> str:
    n = summary["statuses"]["error_in_machine_stalls"]
    return f" ({n} during machine stalls)" if n else ""


def summary_lines(summaries: list[dict], checks: list[dict]) -> list[str]:
    lines = []
    for s in summaries:
        r = s["resets"]
        lines.append(
            f"{s['rate']:g}x (achieved {_rate(s)}), {s['wall_s'] / 60:.1f} min: "
            f"{s['outputs']} outputs of {s['sets_completed']} sets, {s['stale_sets_dropped']} "
            f"stale, refused {s['inputs_refused'] or 0}; latency p50/p90/p99 "
            f"{_ms(s['latency_ms_wall'])} ms wall, processing {_ms(s['processing_ms'])} ms; "
            f"history resets {r['at_scene_changes']} at new scenes, "
            f"{r['outputs_further_apart_than_history_max_gap']} after slow outputs, "
            f"{len(r['unexpected'])} unexplained; ERROR {s['statuses']['error']}"
            f"{_in_stalls(s)}; RSS "
            f"{s['rss'].get('first_mb', 0):.0f}"
            f" -> {s['rss'].get('last_mb', 0):.0f} MB")
    lines += [f"  {'met' if c['met'] else 'not met' if c['met'] is False else 'n/a':7s} "
              f"{c['target']}: {c['measured']}" for c in checks]
    return lines


def markdown(summaries: list[dict], checks: list[dict], context: dict, picture: str,
             restarts: dict | None = None) -> str:
    m = context["machine"]
    rows = ["| | " + " | ".join(f"{s['rate']:g}x" for s in summaries) + " |",
            "|---|" + "---|" * len(summaries)]

    def row(name, cell):
        rows.append(f"| {name} | " + " | ".join(cell(s) for s in summaries) + " |")
    row("replay rate achieved", _rate)
    row("wall time", lambda s: f"{s['wall_s'] / 60:.1f} min")
    row("node start-up (model load)", lambda s: f"{s['node_startup_s']:.0f} s")
    row("scenes with outputs", lambda s: str(s["scenes_with_outputs"]))
    row("outputs / completed sets", lambda s: f"{s['outputs']} / {s['sets_completed']}")
    row("outputs per completed set", lambda s: "-" if s["outputs_per_completed_set"] is None
        else f"{s['outputs_per_completed_set']:.3f}")
    row("stale sets dropped", lambda s: str(s["stale_sets_dropped"]))
    row("inputs refused", lambda s: str(s["inputs_refused"] or 0))
    row("latency p50 / p90 / p99, wall ms", lambda s: _ms(s["latency_ms_wall"]))
    row("node's pipeline latency p50 / p90 / p99, as wall ms",
        lambda s: _ms(s["node_latency_ms_as_wall"]))
    row("processing p50 / p90 / p99, ms", lambda s: _ms(s["processing_ms"]))
    row("history resets at new scenes", lambda s: str(s["resets"]["at_scene_changes"]))
    row("history resets after outputs further apart than history_max_gap",
        lambda s: str(s["resets"]["outputs_further_apart_than_history_max_gap"]))
    row("history resets unexplained", lambda s: str(len(s["resets"]["unexpected"])))
    row("new scenes without a reset", lambda s: str(s["resets"]["new_scenes_without_reset"]))
    row("longest output gap within a scene", lambda s: "-" if
        s["longest_output_gap"]["seconds"] is None else
        f"{s['longest_output_gap']['seconds']:.1f} s")
    row("diagnostics OK / WARN / ERROR", lambda s: f"{s['statuses']['ok']} / "
        f"{s['statuses']['warn']} / {s['statuses']['error']}{_in_stalls(s)}")
    row("machine stalls (the soak's own sampling stopped)", lambda s: ", ".join(
        f"{st['seconds']:.0f} s at {st['at_s'] / 60:.1f} min"
        for st in s["machine_stalls"]) or "none")
    row("RSS first / peak / last, MB", lambda s: f"{s['rss'].get('first_mb', 0):.0f} / "
        f"{s['rss'].get('peak_mb', 0):.0f} / {s['rss'].get('last_mb', 0):.0f}")
    row("RSS growth after warm-up", lambda s: "-" if "growth_after_warmup_mb" not in s["rss"]
        else f"{s['rss']['growth_after_warmup_mb']:+.1f} MB "
             f"({s['rss']['slope_mb_per_hour']:+.1f} MB/h)")
    targets = ["| target | measured | |", "|---|---|---|"] + [
        f"| {c['target']} | {c['measured']} | "
        f"{'met' if c['met'] else 'NOT met' if c['met'] is False else 'not measured'} |"
        for c in checks]
    warnings = sorted({w for s in summaries for w in s["statuses"]["warnings"]})
    return "\n".join([
        f"# Soak: odg_node, {context['date']}", "",
        f"`{context['command']}`", "",
        f"{m['cpu']}, {m['cores']} cores, torch {m['torch']}, CPU. Load average (1/5/15 min) "
        f"{_load(m['load_average_before'])} before, {_load(m['load_average_after'])} after "
        "(a shared machine: other work ran alongside).", "",
        "Scenes, looped in this order: " + ", ".join(f"`{Path(b).name}`"
                                                     for b in context["bags"]) + ".", "",
        *targets, "", *(rows + [""] if summaries else []),
        *(_restart_rows(restarts) if restarts else []),
        *([f"![memory and latency]({picture})", ""] if summaries else []),
        "Latency, wall: the output's reference camera image reaching the soak's watcher -> "
        "the output reaching it. The node's pipeline latency: its ~/debug/pipeline_latency_ms "
        "(its clock, the bag time, at publishing minus the stamp) over the replay rate "
        "achieved, for outputs published in their own scene; it reads low where the node's "
        "intake lags (its /clock lags with it). Processing: the node's set complete "
        "-> published (~/debug/processing_time_ms, steady clock). A history reset is "
        "explained by a new scene's first output, or by an output further than "
        "history_max_gap (bag time) after the previous one of its scene: a node that slow "
        "cannot keep a history.",
        *([""] + ["WARN statuses seen: " + "; ".join(f"`{w}`" for w in warnings) + "."]
          if warnings else []), ""])


def _restart_rows(restarts: dict) -> list[str]:
    rows = ["Restarts (SIGKILL mid-bag at 1x, then a new process):", "",
            "| restart | first report after | first output after | outputs | stale "
            "(not checked) | ERROR reports |", "|---|---|---|---|---|---|"]
    for n, c in enumerate(restarts["restarts"], 1):
        rows.append(f"| {n} | {c['up_after_s']:.1f} s | {c['first_output_after_s']:.1f} s | "
                    f"{c['outputs']} | {c['stale_outputs']} ({c['outputs_not_checked']}) | "
                    f"{c['errors']} |")
    return rows + ["", "Times from the new process's start (Python, the model loaded, "
                   "its first complete set and its step). Stale: an output made of a camera "
                   "image that reached the machine before the new process started. A new "
                   "process holds no history: every frame it uses came after its start.", ""]


def _rate(s: dict) -> str:
    return "not measured" if s["effective_rate"] is None else f"{s['effective_rate']:.2f}x"


def _load(values) -> str:
    return "/".join(f"{v:.1f}" for v in values)
