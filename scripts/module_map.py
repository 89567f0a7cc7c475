"""Write the module map of docs/architecture.md: one row per folder of code, with its modules.

The folders: every package under senfunet_core and senfunet_ros (found, so a new subpackage gets
its row), every test folder, bench and scripts. A package's row says what its `__init__`
docstring says (first sentence) unless DESCRIPTIONS below has it; other folders need an entry
there. The table sits between the two marker comments in the document; the rest of the document
is left alone.

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
DESCRIPTIONS = {  # folder -> description, where the package docstring does not give it
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


def folders() -> list[str]:
    """Packages (depth first, in name order), then test folders, then the others described."""
    def packages(root: Path) -> list[str]:
        found = [root.relative_to(REPO).as_posix()]
        for child in sorted(p for p in root.iterdir() if (p / "__init__.py").is_file()):
            found += packages(child)
        return found

    out = packages(REPO / "senfunet_core") + packages(REPO / "senfunet_ros")
    out += sorted({p.parent.relative_to(REPO).as_posix() for p in (REPO / "test").rglob("test_*.py")})
    return out + [f for f in DESCRIPTIONS if f not in out]


def describe(folder: str) -> str:
    if folder in DESCRIPTIONS:
        return DESCRIPTIONS[folder]
    init = REPO / folder / "__init__.py"
    doc = ast.get_docstring(ast.parse(init.read_text())) if init.is_file() else None
    if not doc:
        raise SystemExit(f"{folder}: no package docstring; give it one or a description in {__file__}")
    return first_sentence(doc)


def table() -> str:
    rows = ["| folder | what it holds | modules |", "| --- | --- | --- |"]
    for folder in folders():
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
