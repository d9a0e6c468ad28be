"""What the user-facing Markdown shows of the package: its Python imports and dotted names, and its
`scube-sim` command lines. tests/test_doc_references.py holds every one of them to the code.

Run as a script to print the references of README.md and docs/*.md as JSON:
    python -m tests.doc_references
"""

from __future__ import annotations

import json
import re
import shlex
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

_IMPORT = re.compile(r"^\s*(?:>>> )?(from (scube_sim[\w.]*) import (.+)|import (scube_sim[\w.]*)(?: as \w+)?)\s*$")
_DOTTED = re.compile(r"`(scube_sim(?:\.\w+)+)`|\b(scube_sim(?:\.\w+)+)\b")
_FENCE = re.compile(r"^\s*```")


def markdown_files(root: Path = ROOT) -> list[Path]:
    """README.md and every docs/*.md, in a fixed order."""
    return [root / "README.md"] + sorted((root / "docs").glob("*.md"))


def _blocks(text: str):
    """(in a fenced code block?, line) for every line of a Markdown text."""
    inside = False
    for line in text.splitlines():
        if _FENCE.match(line):
            inside = not inside
            continue
        yield inside, line


def imports_of(text: str) -> list[str]:
    """Import statements of our package shown in code blocks, one statement per entry (a name
    list in parentheses or with a trailing comma is not used in the docs)."""
    out = []
    for inside, line in _blocks(text):
        m = _IMPORT.match(line) if inside else None
        if m:
            stmt = m.group(1).split("#")[0].strip()
            out.append(stmt)
    return out


def dotted_names_of(text: str) -> list[str]:
    """Dotted names `scube_sim.a.b` in prose and code, without a trailing call or punctuation."""
    out = []
    for _, line in _blocks(text):
        for m in _DOTTED.finditer(line):
            out.append((m.group(1) or m.group(2)).rstrip("."))
    return out


def commands_of(text: str) -> list[str]:
    """`scube-sim ...` lines of code blocks (backslash continuations joined, comments cut)."""
    out, pending = [], ""
    for inside, line in _blocks(text):
        if not inside:
            pending = ""
            continue
        line = pending + line
        if line.rstrip().endswith("\\"):
            pending = line.rstrip()[:-1] + " "
            continue
        pending = ""
        stripped = line.strip()
        if stripped.startswith("$ "):
            stripped = stripped[2:]
        if stripped.startswith("scube-sim "):
            out.append(re.sub(r"\s+#.*$", "", stripped).strip())
    return out


def references(root: Path = ROOT) -> dict:
    """{"imports": [...], "names": [...], "commands": [...]}: each entry once, in file order."""
    found = {"imports": [], "names": [], "commands": []}
    for path in markdown_files(root):
        text = path.read_text(encoding="utf-8")
        for key, values in (("imports", imports_of(text)), ("names", dotted_names_of(text)),
                            ("commands", commands_of(text))):
            for v in values:
                if v not in found[key]:
                    found[key].append(v)
    return found


_PLACEHOLDER = re.compile(r"^[A-Z][A-Z0-9_]*(?:[./][\w.]*)?$")


def command_words(line: str) -> tuple[list[str], bool]:
    """The words of a documented command line after `scube-sim`, and whether it is literal (no
    synopsis syntax: `[optional]`, `a|b`, UPPER_CASE placeholders). A synopsis keeps each bracket's
    first alternative and each `a|b`'s first word, so its command and option names can be checked."""
    body = line.split(None, 1)[1] if " " in line else ""
    literal = not re.search(r"[\[\]|]", body)
    body = re.sub(r"\[([^\[\]]*)\]", lambda m: m.group(1).split(" | ")[0], body)
    body = re.sub(r"\s\|\s\S+", "", body)  # `X | Y ...`: X
    words = [w.split("|")[0] for w in shlex.split(body)]
    if any(_PLACEHOLDER.match(w) for w in words):
        literal = False
    return words, literal


if __name__ == "__main__":
    print(json.dumps(references(), indent=1))
