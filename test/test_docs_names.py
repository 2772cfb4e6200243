"""What the docs name exists: every repository path (``odg_ros/online/step.py``,
``config/odg.yaml``), every dotted module or module attribute (``odg_ros.network.budget``,
``odg_ros.online.execution.resolve_budget``), every ``odg`` subcommand and each of its
``--options`` written in code in README.md and docs/ (the living docs, the results pages and
the dated reports). A renamed file, a removed option or a moved function shows here instead
of in a user's shell.

Each check is a function of the text, so the tests also plant a stale name and see it caught."""
from __future__ import annotations

import re
from functools import cache
from pathlib import Path

import pytest

from odg_ros.commands import SUBCOMMANDS, build_parser

ROOT = Path(__file__).resolve().parents[1]
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]
# names a dated report gives of what was there on its day, and what they have become
RENAMED = {"tools/profile_train_step.py": "odg profile train"}

TOP = "odg_ros|tools|test|testing|config|docs|model|launch|msg"
PATH = re.compile(rf"(?<![\w./-])((?:{TOP})/[\w./-]*\w(?:\.\{{[\w,]+\}})?)")
DOTTED = re.compile(r"(?<![\w./-])(odg_ros(?:\.\w+)+)")
CODE = re.compile(r"```.*?```|`[^`\n]+`", re.S)
CALL = re.compile(r"(?<![\w/.-])odg ([a-z]+)\b([^`\n|;\\]*(?:\\\n[^`\n|;\\]*)*)")
PLACEHOLDER = re.compile(r"[*<>]|YYYY")


def expand(path: str) -> list[str]:
    """``a.{txt,json}`` -> ``a.txt``, ``a.json``."""
    brace = re.search(r"\{([\w,]+)\}", path)
    if not brace:
        return [path]
    return [path[:brace.start()] + part + path[brace.end():]
            for part in brace.group(1).split(",")]


def missing_paths(text: str, root: Path = ROOT) -> list[str]:
    found = []
    for match in PATH.finditer(text):
        path = match.group(1).rstrip(".")
        if PLACEHOLDER.search(text[match.start():match.end() + 1]) or path in RENAMED:
            continue
        # a path prefix of results (``--out docs/results/planner``) names its files
        found += [p for p in expand(path) if not (root / p).exists()
                  and not any((root / p).parent.glob((root / p).name + ".*"))]
    return found


def _defines(source: str, name: str) -> bool:
    return re.search(rf"^\s*(?:def|class|async def) {name}\b|^\s*{name}\s*[:=]|"
                     rf"^\s*(?:from\s+\S+\s+)?import\s.*\b{name}\b", source, re.M) is not None


def missing_modules(text: str, root: Path = ROOT) -> list[str]:
    """A dotted name is a module, or a module then one name it defines (then attributes,
    not checked: ``Class.method``)."""
    found = []
    for match in DOTTED.finditer(text):
        parts = match.group(1).split(".")
        module = None
        for k in range(len(parts), 0, -1):
            base = root.joinpath(*parts[:k])
            if base.with_suffix(".py").is_file():
                module = (k, base.with_suffix(".py"))
            elif (base / "__init__.py").is_file():
                module = (k, base / "__init__.py")
            if module:
                break
        k, path = module
        if k < len(parts) and not _defines(path.read_text(), parts[k]):
            found.append(match.group(1))
    return found


@cache
def options_of(command: str) -> frozenset[str]:
    """Every option string of ``odg COMMAND`` and of its own subcommands."""
    parser = build_parser(command)[1]
    options, parsers = set(), [parser]
    while parsers:
        for action in parsers.pop()._actions:
            options |= set(action.option_strings)
            if isinstance(action.choices, dict):
                parsers += list(action.choices.values())
    return frozenset(options)


def unknown_commands(text: str) -> list[str]:
    """``odg X`` with X no subcommand, or ``odg X ... --opt`` with no such option of X, in
    the text's code (fenced blocks and inline code)."""
    found = []
    for code in CODE.finditer(text):
        for call in CALL.finditer(code.group(0)):
            command = call.group(1)
            if command not in SUBCOMMANDS:
                found.append(f"odg {command}")
                continue
            found += [f"odg {command} {option}"
                      for option in re.findall(r"(?<![\w-])--[a-z][a-z0-9-]*", call.group(2))
                      if option not in options_of(command)]
    return found


@pytest.mark.parametrize("doc", DOCS, ids=lambda p: str(p.relative_to(ROOT)))
def test_what_the_docs_name_exists(doc):
    text = doc.read_text()
    assert missing_paths(text) == []
    assert missing_modules(text) == []
    assert unknown_commands(text) == []


def test_a_stale_name_in_the_docs_is_caught():
    planted = ("The step (`odg_ros/benchmark.py`, `odg_ros/online/step.py`, "
               "`docs/results/census/odg_cpu.{txt,csv}`) runs `odg_ros.online.step.OnlineStep`, "
               "`odg_ros.network.budget.scatter_queries`, odg_ros.demo.demo_world.\n\n"
               "```bash\nodg eval --checkpoint model/odg_cpu.pt --query-budget auto \\\n"
               "    --keyframes 8\nodg benchmark --json\n```\n"
               "and `odg bench --sweep --configs a.json`, `tools/<name>.py`, `odg_ros/*.py`.")
    assert missing_paths(planted) == ["odg_ros/benchmark.py", "docs/results/census/odg_cpu.csv"]
    assert missing_modules(planted) == ["odg_ros.network.budget.scatter_queries"]
    assert unknown_commands(planted) == ["odg eval --keyframes", "odg benchmark"]
