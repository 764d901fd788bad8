"""Every option of every command says what it does (``--help`` is the first manual)."""

from __future__ import annotations

import click

from spiel_edge.cli import COMMANDS, cli


def _commands():
    ctx = click.Context(cli)
    for name in COMMANDS:
        command = cli.get_command(ctx, name)
        yield name, command
        if isinstance(command, click.Group):
            for sub in command.list_commands(ctx):
                yield f"{name} {sub}", command.get_command(ctx, sub)


def test_every_option_has_help():
    missing = [
        f"{name} {'/'.join(p.opts)}"
        for name, command in _commands()
        for p in command.params
        if isinstance(p, click.Option) and not (p.help or "").strip()
    ]
    assert not missing, f"options without help: {missing}"


def test_every_command_has_help():
    assert all((c.help or "").strip() for _, c in _commands())
