"""``spiel-edge doctor``: check the device, permissions, ModemManager, config, model and numba."""

from __future__ import annotations

import json
import shlex

import click

from spiel_edge.errors import SpielError
from spiel_edge.safety.shown import escape
from spiel_edge.service.doctor import CONFIG_DIR, run_checks


@click.command("doctor")
@click.option(
    "--profile",
    "profile_name",
    default=None,
    help="Profile to check (default: the one in the config dir's spiel-edge.env, else the built-in).",
)
@click.option(
    "--calibration",
    type=click.Path(dir_okay=False),
    default=None,
    help="Calibration file to check.",
)
@click.option(
    "--config",
    "config_dir",
    default=CONFIG_DIR,
    show_default=True,
    type=click.Path(file_okay=False),
    help="Service config folder.",
)
@click.option(
    "--skip-numba", is_flag=True, help="Skip the numba checks (they run the pipeline once)."
)
@click.option(
    "--port",
    default=None,
    help="Also talk to the board at this port (HELLO, CONFIG_STATUS): protocol version, "
    "max_payload, stored config.",
)
@click.option("--json", "as_json", is_flag=True, help="One JSON document instead of text.")
def command(profile_name, calibration, config_dir, skip_numba, port, as_json) -> int:
    """Check what the service needs; print a fix for each problem. Exit status 1 on any problem."""
    try:
        checks = run_checks(
            profile_name,
            calibration,
            config_dir,
            skip_numba=skip_numba,
            port=port,
            rejects=service_rejects,
        )
    except MemoryError:  # a check that cannot finish is a problem found, not a crash (status 1)
        click.echo("[FAIL] doctor: out of memory while checking; free some memory and run it again")
        return 1
    ok = all(c.ok for c in checks)
    if as_json:
        click.echo(json.dumps({"ok": ok, "checks": [c.as_dict() for c in checks]}, indent=2))
    else:
        for c in checks:  # details carry paths, environment values and exception texts
            click.echo(f"[{' ok ' if c.ok else 'FAIL'}] {c.name}: {escape(c.detail)}")
            if not c.ok and c.fix:
                click.echo(f"       fix: {escape(c.fix)}")
        click.echo("all good" if ok else f"{sum(not c.ok for c in checks)} problem(s)")
    return 0 if ok else 1


def service_rejects(env: dict[str, str]) -> str | None:
    """Why `spiel-edge run` would refuse SPIEL_RUN_OPTIONS or SPIEL_PORT (parsed by run's own
    option parser, ranges included), or None."""
    from spiel_edge.cli import cli
    from spiel_edge.link import LINK_SCHEMES, scheme_of

    port = env.get("SPIEL_PORT", "")
    if port and scheme_of(port) not in LINK_SCHEMES:
        return f"SPIEL_PORT {port!r}: unknown URL scheme {scheme_of(port)!r}"
    try:
        args = shlex.split(env.get("SPIEL_RUN_OPTIONS", ""))
    except ValueError as exc:
        return f"SPIEL_RUN_OPTIONS: {exc}"
    run = cli.get_command(click.Context(cli), "run")
    try:
        ctx = run.make_context("run", list(args), resilient_parsing=False)
    except click.ClickException as exc:
        return f"SPIEL_RUN_OPTIONS: {exc.format_message()}"
    except click.exceptions.Exit:
        return "SPIEL_RUN_OPTIONS: --help or --version ends the service at once"
    from spiel_edge.outputs.udp import parse_host_port

    try:
        for target in ctx.params.get("udp") or ():
            parse_host_port(target, what="--udp")
        if ctx.params.get("foxglove"):
            parse_host_port(ctx.params["foxglove"], default_host="127.0.0.1", what="--foxglove")
        if ctx.params.get("slot"):  # the robot file and its board, as run checks them
            from spiel_edge.robot.slot_session import slot_keeper_of

            slot_keeper_of(ctx.params["slot"])
    except SpielError as exc:
        return f"SPIEL_RUN_OPTIONS: {exc}"
    return None
