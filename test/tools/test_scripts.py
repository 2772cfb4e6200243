"""Every maintainer script answers ``--help`` (run as ``python -m tools.NAME --help`` would,
in this process: cheap), every name it imports from the package exists (also the imports
inside functions, which --help never runs), and the shell scripts parse. A script that does
work at import, ignores ``--help`` or imports a module that moved fails here instead of in a
maintainer's hands."""
import ast
import contextlib
import importlib
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


def package_imports(path: Path) -> list[tuple[str, str]]:
    """(module, name) of every ``from odg_ros... import name`` in a file, at any depth."""
    return [(node.module, alias.name) for node in ast.walk(ast.parse(path.read_text()))
            if isinstance(node, ast.ImportFrom) and node.level == 0 and node.module
            and node.module.split(".")[0] == "odg_ros" for alias in node.names]


@pytest.mark.parametrize("name", SCRIPTS + HELPERS)
def test_every_name_a_tool_imports_from_the_package_exists(name):
    missing = []
    for module, attribute in package_imports(TOOLS / f"{name}.py"):
        try:
            found = importlib.import_module(module)
        except ModuleNotFoundError:
            missing.append(f"{module} (no such module)")
            continue
        if not hasattr(found, attribute):
            try:
                importlib.import_module(f"{module}.{attribute}")
            except ModuleNotFoundError:
                missing.append(f"{module}.{attribute}")
    assert not missing, missing


@pytest.mark.parametrize("name", HELPERS)
def test_every_helper_module_imports(name):
    __import__(f"tools.{name}")


@pytest.mark.parametrize("script", sorted(path.name for path in TOOLS.glob("*.sh")))
def test_every_shell_script_parses(script):
    assert subprocess.run(["bash", "-n", str(TOOLS / script)]).returncode == 0


def test_the_node_overhead_tool_runs_without_ros():
    """It swaps the predictor's device step for a recording of one real step: that reaches
    into the predictor, so a change of its step's signature must show here."""
    result = subprocess.run([sys.executable, "-m", "tools.measure_node_overhead", "--preset",
                             "odg_cpu", "--sets", "2", "--no-ros"],
                            capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-2000:]
    assert "total, all outputs" in result.stdout, result.stdout[-2000:]
