"""Every numeric option of every command, found by introspection (so options added later are
covered too), given values outside its type or range: a usage error naming the option,
status 2, no traceback."""

from __future__ import annotations

import importlib

import click
import pytest

from spiel_edge.cli import COMMANDS

ALWAYS_BAD = ["nan", "inf", "-inf", "1e999", "abc", "", "1e5000000"]


def _numeric_options():
    for name in sorted(COMMANDS):
        command = importlib.import_module(f"spiel_edge.cli.{name}").command
        subs = (
            [([name, sub], c) for sub, c in command.commands.items()]
            if isinstance(command, click.Group)
            else [([name], command)]
        )
        for path, cmd in subs:
            for param in cmd.params:
                if isinstance(param, click.Option) and isinstance(
                    param.type, (click.types.FloatParamType, click.types.IntParamType)
                ):
                    yield path, param


def _bad_values(param) -> list[str]:
    kind = param.type
    values = list(ALWAYS_BAD)
    if isinstance(kind, click.types.IntParamType):
        values += ["1.5", "99999999999999999999"]
    low, high = getattr(kind, "min", None), getattr(kind, "max", None)
    if low is not None:
        values.append(str(low - 1))
    if high is not None:
        values.append(str(high + 1 if isinstance(high, int) else high * 1.5 + 1))
    return values


CASES = [
    pytest.param(path, param.opts[0], value, id=f"{' '.join(path)} {param.opts[0]}={value!r}")
    for path, param in _numeric_options()
    for value in _bad_values(param)
]


@pytest.mark.parametrize(("path", "option", "value"), CASES)
def test_out_of_range_numbers_are_usage_errors(cli, path, option, value):
    ran = cli(*path, f"{option}={value}")
    assert ran.status == 2, ran
    assert option in ran.err, ran


def test_every_command_has_been_found():
    assert len(CASES) >= 100
    assert {p[0] for p, _ in _numeric_options()} >= {"run", "replay", "evaluate", "calibrate"} - {
        "replay"
    }


STRING_CASES = [
    ("run", "--udp", "nohostport"),
    ("run", "--udp", "host:99999"),
    ("run", "--udp", "host:-1"),
    ("run", "--udp", ":"),
    ("run", "--udp", "h:" + "9" * 100_000),
    ("run", "--foxglove", "abc"),
    ("run", "--foxglove", "70000"),
    ("run", "--port", "foo://x"),
    ("run", "--port", "x" * 100_000),
    ("run", "--profile", "no-such-profile"),
    ("run", "--profile", "y" * 100_000),
    ("run", "--association", "magic"),
    ("config commit", "--crc", "zz"),
    ("config commit", "--crc", "f" * 100_000),
    ("simulate", "URL", "http://x"),
    ("replay", "--format", "csv"),
]


@pytest.mark.parametrize(("path", "option", "value"), STRING_CASES, ids=lambda v: str(v)[:30])
def test_bad_strings_are_errors_not_tracebacks(cli, tmp_path, path, option, value):
    args = path.split()
    if option == "URL":
        args += ["--pty", value]
    else:
        args += [option, value]
    if args[0] == "run":
        args += ["--port", f"serial://{tmp_path}/none"] if option != "--port" else []
        args += ["-o", tmp_path / "o.ndjson", "--frames", "1"]
    if args[0] == "config":
        args += ["--port", f"serial://{tmp_path}/none"]
    if args[0] == "replay":
        args.insert(1, str(tmp_path))
    ran = cli(*args)
    assert ran.status == 2, ran
