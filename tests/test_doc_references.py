"""The README and docs hold to the code: every Python import and dotted name they show works, and
every `scube-sim` line they show parses."""

from __future__ import annotations

import importlib

import pytest
import typer.main

from scube_sim.cli import app

from .doc_references import command_words, references

NOW = references()


def _resolve(dotted: str):
    """The object a dotted name `scube_sim.a.b.C` names: the longest importable module, then
    attributes."""
    parts = dotted.split(".")
    for cut in range(len(parts), 0, -1):
        try:
            obj = importlib.import_module(".".join(parts[:cut]))
        except ModuleNotFoundError as exc:
            if exc.name != ".".join(parts[:cut]):
                raise
            continue
        for attr in parts[cut:]:
            obj = getattr(obj, attr)
        return obj
    raise AssertionError(f"{dotted}: no module of it imports")


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


@pytest.mark.parametrize("line", sorted(set(NOW["commands"])))
def test_documented_commands_parse(line):
    parse_command(line)


def test_the_parser_check_can_fail():
    with pytest.raises(AssertionError, match="no option --no-such"):
        parse_command("scube-sim lidar scene.npz --sensor hdl64e -o x.pcd --no-such 1")
    with pytest.raises(AssertionError, match="not a subcommand"):
        parse_command("scube-sim worlds teleport -o x")
    with pytest.raises(Exception, match="valid integer"):
        parse_command("scube-sim worlds generate --split test --count many -o x")
