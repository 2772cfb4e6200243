"""Write (or check) what is generated from the node's parameter schema.

    python -m tools.node_parameters --write    # after editing config/odg_node.schema.yaml
    python -m tools.node_parameters --check    # exit 1 when config/odg.yaml or README is stale

Writes config/odg.yaml (every parameter at its default), docs/parameters.md (the full table)
and the README's summary of the parameters (between the parameters markers).
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from odg_ros.online.parameters import (load_schema, markdown_table, params_file_text,
                                      summary_table)

ROOT = Path(__file__).resolve().parent.parent
BEGIN, END = "<!-- parameters:begin -->", "<!-- parameters:end -->"


def generated(root: Path = ROOT) -> dict[Path, str]:
    """path -> the text it should have."""
    schema = load_schema(root / "config/odg_node.schema.yaml")
    readme = (root / "README.md").read_text()
    if readme.count(BEGIN) != 1 or readme.count(END) != 1:
        raise SystemExit(f"README.md needs one {BEGIN} ... {END} block")
    head, rest = readme.split(BEGIN)
    _, tail = rest.split(END)
    reference = ("# odg_node parameters\n\nWritten from `config/odg_node.schema.yaml` by "
                 "`python -m tools.node_parameters --write`; `odg_node --help` prints the same. "
                 "Every parameter is read at start-up.\n\n" + markdown_table(schema) + "\n")
    return {root / "config/odg.yaml": params_file_text(schema),
            root / "docs/parameters.md": reference,
            root / "README.md": f"{head}{BEGIN}\n{summary_table(schema)}\n{END}{tail}"}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    mode = parser.add_mutually_exclusive_group(required=True)
    mode.add_argument("--write", action="store_true", help="rewrite the generated files")
    mode.add_argument("--check", action="store_true", help="exit 1 if one is stale")
    args = parser.parse_args(argv)
    stale = [path for path, text in generated().items()
             if not path.exists() or path.read_text() != text]
    if args.check:
        for path in stale:
            print(f"{path.relative_to(ROOT)} is stale: run python -m tools.node_parameters "
                  "--write", file=sys.stderr)
        return 1 if stale else 0
    for path, text in generated().items():
        path.write_text(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
