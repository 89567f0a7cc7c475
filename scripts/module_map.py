"""Write the module map of docs/architecture.md: one row per folder of code, with its modules.

A package's row says what its `__init__` docstring says (first sentence); the other folders'
descriptions are below. The table sits between the two marker comments in the document; the
rest of the document is left alone.

    .venv/bin/python scripts/module_map.py           # rewrite the table
    .venv/bin/python scripts/module_map.py --check   # exit 1 when the table is stale (the tests run this)
"""
from __future__ import annotations

import argparse
import ast
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
DOC = REPO / "docs" / "architecture.md"
BEGIN = "<!-- module-map: written by scripts/module_map.py, do not edit by hand -->"
END = "<!-- /module-map -->"
FOLDERS = {  # folder -> description when it is not a package with a docstring
    "senfunet_core": None,
    "senfunet_core/learning": None,
    "senfunet_ros": None,
    "senfunet_ros/commands": "One module per `senfunet` sub-command.",
    "test/core": "Tests of the engine modules; no ROS needed (`-m \"not ros\"` runs these).",
    "test/core/learning": "Tests of the offline tooling.",
    "test/ros": "Tests of the ROS layer: real rclpy nodes on a private ROS_DOMAIN_ID, real bag files.",
    "bench": "Benchmarks that write the figures of docs/performance.md.",
    "scripts": "Set-up, checks and generators (like this table).",
}


def first_sentence(text: str) -> str:
    paragraph = " ".join(text.strip().split("\n\n")[0].split())
    end = paragraph.find(". ")
    return paragraph if end < 0 else paragraph[:end + 1]


def describe(folder: str) -> str:
    given = FOLDERS[folder]
    if given is not None:
        return given
    init = REPO / folder / "__init__.py"
    doc = ast.get_docstring(ast.parse(init.read_text())) if init.is_file() else None
    if not doc:
        raise SystemExit(f"{folder}: no package docstring; give it one or a description in {__file__}")
    return first_sentence(doc)


def table() -> str:
    rows = ["| folder | what it holds | modules |", "| --- | --- | --- |"]
    for folder in FOLDERS:
        files = sorted(p for p in (REPO / folder).iterdir() if p.is_file() and p.suffix in (".py", ".sh")
                       and p.name not in ("__init__.py", "conftest.py"))
        modules = ", ".join(f"`{p.stem if p.suffix == '.py' else p.name}`" for p in files)
        rows.append(f"| `{folder}/` | {describe(folder)} | {modules} |")
    return "\n".join(rows)


def written(document: str) -> str:
    """The document with the table between the markers (appended with a heading when absent)."""
    block = f"{BEGIN}\n{table()}\n{END}"
    if BEGIN in document and END in document:
        head, rest = document.split(BEGIN, 1)
        return head + block + rest.split(END, 1)[1]
    return document.rstrip("\n") + "\n\n## Module map\n" + block + "\n"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--check", action="store_true", help="only check that the table is current")
    args = parser.parse_args()
    document = DOC.read_text()
    new = written(document)
    if args.check:
        if new != document:
            print(f"{DOC.relative_to(REPO)}: the module map is stale; run .venv/bin/python scripts/module_map.py",
                  file=sys.stderr)
            return 1
        return 0
    DOC.write_text(new)
    return 0


if __name__ == "__main__":
    sys.exit(main())
