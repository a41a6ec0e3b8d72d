"""The command line's help shows what it says: every command's `--help` keeps its help
texts whole, defaults and TOML table names in square brackets included (rich markup used to
swallow them: `[default: all]`, `[engines.*]`)."""

from __future__ import annotations

import os
import subprocess
import sys

import click
import pytest
import typer

from natcoord.cli import app

ROOT = typer.main.get_command(app)


def _commands(group: click.Group, prefix=()):
    for name, cmd in sorted(group.commands.items()):
        yield (*prefix, name), cmd
        if isinstance(cmd, click.Group):
            yield from _commands(cmd, (*prefix, name))


COMMANDS = list(_commands(ROOT))


def _words(text: str) -> str:
    return " ".join(text.split())


def _help(*command: str) -> str:
    p = subprocess.run([sys.executable, "-m", "natcoord.cli", *command, "--help"],
                       capture_output=True, text=True, timeout=120,
                       env={**os.environ, "COLUMNS": "200"})
    assert p.returncode == 0, p.stderr
    return _words(p.stdout)


@pytest.mark.parametrize("path, cmd", COMMANDS, ids=[" ".join(p) for p, _ in COMMANDS])
def test_every_help_text_is_shown_whole(path, cmd):
    shown = _help(*path)
    texts = [p.help for p in cmd.params if getattr(p, "help", None)]
    if cmd.help:
        texts.append(cmd.help.split("\n\n")[0])
    for text in texts:
        assert _words(text) in shown, (text, shown[:2000])


def test_the_bracketed_words_are_there():
    assert "Comma-separated engines [default: all]" in _help("run")
    assert "[engines.*]" in _help("propose")
