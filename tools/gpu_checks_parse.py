"""Check the command lines that ``CHECK=parse bash tools/gpu_checks.sh PART`` recorded, without
running them: a typo in the GPU script then fails on the CPU, not in a GPU session.

    python -m tools.gpu_checks_parse COMMANDS.jsonl

Each line is a JSON list: ``["odg", NAME, ARGS...]`` is parsed by ``odg NAME``'s own parser,
``["tools/X.py", ARGS...]`` by the script's (its ``main`` stops right after parsing), and
``["pytest", ARGS...]`` is collected (every file must exist and at least one test be selected).
Files that an earlier step of the script writes (under ``out/``) need not exist yet; every
other file must. Prints one line per failing command and exits 1 if any failed.

A bounded part (``first``) also records its time limits: ``["bound", PART, CHECK, SECONDS,
OVERHEAD]`` per check (``SECONDS`` may be ``rest:MIN``: the time left, at least MIN) and
``["limit", PART, LIMIT, MAX_FILES, FILES]``. The upper bound of the part's wall time is the
sum of the checks' limits and overheads, or LIMIT where a check takes the rest (the script
then stops it at LIMIT); it must be at most LIMIT with every ``rest`` check given its MIN,
and the part may leave at most MAX_FILES files in its output folder.
"""
from __future__ import annotations

import argparse
import contextlib
import io
import json
import importlib
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
MADE_BY_THE_SCRIPT = ("out/",)


class Parsed(Exception):
    """Raised right after a parser accepted the command line: nothing runs."""


def _lenient_file_types(parser: argparse.ArgumentParser) -> None:
    """Path options accept the files and folders a previous step would have written."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub in action.choices.values():
                _lenient_file_types(sub)
        check = action.type
        if callable(check) and check not in (int, float, str) and \
                not getattr(check, "lenient", False):
            action.type = _lenient(check)


def _lenient(check):
    def lenient(text):
        try:
            return check(text)
        except argparse.ArgumentTypeError:
            if text.startswith(MADE_BY_THE_SCRIPT):
                return text
            raise
    lenient.lenient = True
    return lenient


def _parse_only():
    """Within it, ``parse_args`` parses and then raises ``Parsed``."""
    original = argparse.ArgumentParser.parse_args

    def parse_then_stop(self, args=None, namespace=None):
        _lenient_file_types(self)
        original(self, args, namespace)
        raise Parsed

    argparse.ArgumentParser.parse_args = parse_then_stop
    return original


def check_odg(argv: list[str]) -> str | None:
    from odg_ros.commands import SUBCOMMANDS, build_parser
    if not argv or argv[0] not in SUBCOMMANDS:
        return f"no odg command {argv[:1]}"
    _, parser = build_parser(argv[0])
    return _parse(lambda: parser.parse_args(argv[1:]))


def check_tool(argv: list[str]) -> str | None:
    """``tools.NAME ARGS``: the maintainer script's own parser takes ARGS."""
    try:
        module = importlib.import_module(argv[0])
    except ImportError as error:
        return f"no such script {argv[0]} ({error})"
    if not hasattr(module, "main"):
        return f"{argv[0]} has no main(argv)"
    return _parse(lambda: module.main(argv[1:]))


def _parse(call) -> str | None:
    stderr = io.StringIO()
    try:
        with contextlib.redirect_stderr(stderr), contextlib.redirect_stdout(io.StringIO()):
            call()
    except Parsed:
        return None
    except SystemExit:
        return stderr.getvalue().strip().splitlines()[-1] if stderr.getvalue() else "exit"
    return "the command ran without parsing its arguments"


def check_pytest(argv: list[str]) -> str | None:
    import pytest

    class Selected:
        count = 0

        def pytest_collection_finish(self, session):
            Selected.count = len(session.items)

    files = [a for a in argv if a.endswith(".py")]
    missing = [f for f in files if not (ROOT / f).is_file()]
    if missing:
        return f"no such test file {missing}"
    kept = []
    skip_value = {"--timeout", "-p"}
    args = list(argv)
    i = 0
    while i < len(args):   # options that write or need plugins are left out; -k is kept
        a = args[i]
        if a.startswith("--junitxml"):
            i += 1
            continue
        if a in skip_value:
            i += 2
            continue
        kept.append(a)
        i += 1
    with contextlib.redirect_stdout(io.StringIO()):
        code = pytest.main(["--collect-only", "-q", "-p", "no:cacheprovider", *kept],
                           plugins=[Selected()])
    if code != 0 or Selected.count == 0:
        return f"pytest selects {Selected.count} tests (exit {int(code)})"
    return None


def check_bounds(lines: list[list[str]]) -> tuple[list[str], list[str]]:
    """(one line per bounded part, the problems) from the "bound" and "limit" records."""
    bounds, reports, problems = {}, [], []
    for line in lines:
        if line[0] == "bound":
            _, part, name, seconds, overhead = line
            bounds.setdefault(part, []).append((name, seconds, int(overhead)))
    for line in lines:
        if line[0] != "limit":
            continue
        _, part, limit, max_files, files = line
        limit, max_files, files = int(limit), int(max_files), int(files)
        checks = bounds.get(part, [])
        fixed = sum(int(s) + o for _, s, o in checks if not s.startswith("rest:"))
        rest = [(n, int(s[5:]) + o) for n, s, o in checks if s.startswith("rest:")]
        least = fixed + sum(s for _, s in rest)
        bound = limit if rest else fixed
        reports.append(f"part {part}: {len(checks)} time limits, wall time at most {bound} s "
                       f"(limits {fixed} s" + (f" + the rest, at least {least - fixed} s"
                                               if rest else "")
                       + f"; limit {limit} s), {files} files (at most {max_files})")
        if least > limit:
            problems.append(f"part {part}: its checks need {least} s, more than its {limit} s")
        if files > max_files:
            problems.append(f"part {part}: {files} files in its output, more than {max_files}")
    if bounds and not reports:
        problems.append("time limits recorded without a part limit")
    return reports, problems


def main(argv=None) -> int:
    args = sys.argv[1:] if argv is None else argv
    if len(args) != 1:
        print("usage: python -m tools.gpu_checks_parse COMMANDS.jsonl", file=sys.stderr)
        return 2
    lines = [json.loads(line) for line in Path(args[0]).read_text().splitlines() if line]
    reports, problems = check_bounds(lines)
    lines = [line for line in lines if line[0] not in ("bound", "limit")]
    original = _parse_only()
    failures = 0
    try:
        for command in lines:
            kind = command[0]
            if kind == "odg":
                error = check_odg(command[1:])
            elif kind == "pytest":
                argparse.ArgumentParser.parse_args = original   # pytest parses for real
                try:
                    error = check_pytest(command[1:])
                finally:
                    _parse_only()
            else:
                error = check_tool(command)
            if error:
                failures += 1
                print(f"{' '.join(command)}\n  -> {error}")
    finally:
        argparse.ArgumentParser.parse_args = original
    print(f"{len(lines)} command lines, {failures} refused")
    for line in reports + problems:
        print(line)
    return 1 if failures or problems else 0


if __name__ == "__main__":
    sys.exit(main())
