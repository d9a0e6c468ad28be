"""The README and docs hold to the code: every Python import and dotted name they show works, and
every `scube-sim` line they show parses. The references of the README and docs as they stood
before the package was arranged by role (tests/fixtures/doc_references_before_house.json) still
work, or fail with a message that names their new place."""

from __future__ import annotations

import importlib
import json
from pathlib import Path

import pytest
import typer.main

from scube_sim.cli import app

from .doc_references import command_words, references

FIXTURE = Path(__file__).parent / "fixtures" / "doc_references_before_house.json"
BEFORE = json.loads(FIXTURE.read_text(encoding="utf-8"))
NOW = references()


def _resolve(dotted: str):
    """The object a dotted name `scube_sim.a.b.C` names: the longest importable module, then
    attributes."""
    parts = dotted.split(".")
    for cut in range(len(parts), 0, -1):
        try:
            obj = importlib.import_module(".".join(parts[:cut]))
        except ModuleNotFoundError as exc:
            if exc.name != ".".join(parts[:cut]) or "moved to" in str(exc):
                raise
            continue
        for attr in parts[cut:]:
            obj = getattr(obj, attr)
        return obj
    raise AssertionError(f"{dotted}: no module of it imports")


def _works_or_names_new_place(run) -> None:
    try:
        run()
    except ImportError as exc:
        msg = str(exc)
        assert "moved to scube_sim." in msg, f"fails without naming the new place: {msg}"
        new = msg.split("moved to ", 1)[1].split()[0].rstrip(",)")
        importlib.import_module(new)  # the place named exists


@pytest.mark.parametrize("stmt", BEFORE["imports"])
def test_earlier_imports_work_or_name_their_new_module(stmt):
    _works_or_names_new_place(lambda: exec(stmt, {}))


@pytest.mark.parametrize("name", BEFORE["names"])
def test_earlier_dotted_names_work_or_name_their_new_module(name):
    _works_or_names_new_place(lambda: _resolve(name))


@pytest.mark.parametrize("stmt", NOW["imports"])
def test_documented_imports_work(stmt):
    exec(stmt, {})


@pytest.mark.parametrize("name", NOW["names"])
def test_documented_dotted_names_exist(name):
    _resolve(name)


def parse_command(line: str):
    """Parse a documented command line with the real CLI, without running it: the subcommand
    path must exist and every option be one of its options; a literal line (no synopsis syntax)
    must parse in full (types, required arguments). Returns the leaf command."""
    words, literal = command_words(line)
    cmd = typer.main.get_command(app)  # typer's own copy of click: groups are told by resolve_command
    ctx = cmd.make_context("scube-sim", list(words), resilient_parsing=True)
    while hasattr(cmd, "resolve_command"):
        rest = [*ctx._protected_args, *ctx.args]
        assert rest, f"{line!r}: names no subcommand of {cmd.name}"
        name, sub, rest = cmd.resolve_command(ctx, rest)
        assert sub is not None, f"{line!r}: {rest[0]!r} is not a subcommand of {ctx.info_name}"
        words = rest
        ctx = sub.make_context(name, list(rest), parent=ctx, resilient_parsing=True)
        cmd = sub
    known = {o for p in cmd.params for o in (*p.opts, *p.secondary_opts)}
    unknown = [w.split("=")[0] for w in words if w.startswith("-") and w.split("=")[0] not in known]
    assert not unknown, f"{line!r}: {cmd.name} has no option {', '.join(unknown)}"
    if literal:
        cmd.make_context(cmd.name, list(words), parent=ctx.parent)  # types and required arguments
    return cmd


@pytest.mark.parametrize("line", sorted(set(BEFORE["commands"]) | set(NOW["commands"])))
def test_documented_commands_parse(line):
    parse_command(line)


def test_the_parser_check_can_fail():
    with pytest.raises(AssertionError, match="no option --no-such"):
        parse_command("scube-sim lidar scene.npz --sensor hdl64e -o x.pcd --no-such 1")
    with pytest.raises(AssertionError, match="not a subcommand"):
        parse_command("scube-sim worlds teleport -o x")
    with pytest.raises(Exception, match="valid integer"):
        parse_command("scube-sim worlds generate --split test --count many -o x")


def test_a_moved_module_names_its_new_place():
    with pytest.raises(ModuleNotFoundError, match="moved to scube_sim.realdata.build"):
        importlib.import_module("scube_sim.reconstruct")
    with pytest.raises(ImportError, match=r"moved to scube_sim.runs.scenario"):
        exec("from scube_sim.sim import Scenario", {})
    with pytest.raises(ModuleNotFoundError, match="No module named 'scube_sim.nothing_here'$"):
        importlib.import_module("scube_sim.nothing_here")
