"""Every maintainer script answers ``--help`` (run as ``python -m tools.NAME --help`` would,
in this process: cheap), and the shell scripts parse. A script that does work at import or
ignores ``--help`` fails here instead of in a maintainer's hands."""
import contextlib
import io
import runpy
import subprocess
import sys
from pathlib import Path

import pytest

TOOLS = Path(__file__).resolve().parents[2] / "tools"
SCRIPTS = sorted(path.stem for path in TOOLS.glob("*.py")
                 if 'if __name__ == "__main__":' in path.read_text())
HELPERS = sorted(path.stem for path in TOOLS.glob("*.py")
                 if path.stem not in SCRIPTS and path.stem != "__init__")


def test_the_scripts_are_found():
    assert {"eval_budget", "profile_budget", "plot_budget", "node_parameters"} <= set(SCRIPTS)
    assert HELPERS == ["gpu_tool", "revision"]


@pytest.mark.parametrize("name", SCRIPTS)
def test_every_script_answers_help(name, monkeypatch):
    monkeypatch.setattr(sys, "argv", [str(TOOLS / f"{name}.py"), "--help"])
    out = io.StringIO()
    with pytest.raises(SystemExit) as exit_, contextlib.redirect_stdout(out):
        runpy.run_module(f"tools.{name}", run_name="__main__", alter_sys=False)
    assert exit_.value.code in (0, None) and "usage" in out.getvalue()


@pytest.mark.parametrize("name", HELPERS)
def test_every_helper_module_imports(name):
    __import__(f"tools.{name}")


@pytest.mark.parametrize("script", sorted(path.name for path in TOOLS.glob("*.sh")))
def test_every_shell_script_parses(script):
    assert subprocess.run(["bash", "-n", str(TOOLS / script)]).returncode == 0
