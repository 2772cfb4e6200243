"""A module of odg_ros as it was at a git revision, imported beside this code's own: the
"before" side of the side-by-side benchmarks (bench_render, bench_raycast)."""
import importlib.util
import json
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def module_at(rev: str, path: str):
    """``path`` (e.g. "odg_ros/render/splat.py") at ``rev``, as module "<its name>_before"."""
    source = subprocess.run(["git", "-C", str(ROOT), "show", f"{rev}:{path}"],
                            check=True, capture_output=True, text=True).stdout
    name = path.removesuffix(".py").replace("/", ".") + "_before"
    file = Path(tempfile.mkdtemp()) / f"{name.rsplit('.', 1)[-1]}.py"
    file.write_text(source)
    # a name inside the package, so that its relative imports resolve
    spec = importlib.util.spec_from_file_location(name, file)
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module           # its dataclasses look their module up
    spec.loader.exec_module(module)
    return module


def report(result: dict, failure: str | None) -> int:
    """Print ``result`` as JSON; a comparison with the revision that failed says so on
    stderr and exits 1."""
    print(json.dumps(result, indent=2))
    if failure:
        print(failure, file=sys.stderr)
        return 1
    return 0
