"""What the tools that measure on a CUDA device (tools/gpu_checks.sh runs them) share: the
refusal of ``--device cuda`` where there is none, in one line, and the JSON result written
again after every item measured, so that a run stopped by its time limit keeps what it had."""
from __future__ import annotations

import json
import sys
from pathlib import Path

import torch


def parse_args(parser, argv, tool: str, without_cuda: str,
               json_help: str = "also write the result here"):
    """``parser``'s arguments and a last one, ``--json FILE`` (see write_json), parsed from
    ``argv``; None, after one line on stderr, when ``--device`` is cuda and this machine has
    no CUDA device (``without_cuda`` says what the tool does instead, e.g. "--device cpu: a
    dry run")."""
    parser.add_argument("--json", help=json_help)
    args = parser.parse_args(argv)
    if args.device == "cuda" and not torch.cuda.is_available():
        print(f"{tool}: no CUDA device here ({without_cuda})", file=sys.stderr)
        return None
    return args


def write_json(path, results) -> None:
    """``results`` as indented JSON at ``path`` (``--json``); nothing when no path is given."""
    if path:
        Path(path).write_text(json.dumps(results, indent=1))
