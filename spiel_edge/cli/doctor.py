"""``spiel-edge doctor``: check the device, permissions, ModemManager, config, model and numba."""

from __future__ import annotations

import json

import click

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
    checks = run_checks(profile_name, calibration, config_dir, skip_numba=skip_numba, port=port)
    ok = all(c.ok for c in checks)
    if as_json:
        click.echo(json.dumps({"ok": ok, "checks": [c.as_dict() for c in checks]}, indent=2))
    else:
        for c in checks:
            click.echo(f"[{' ok ' if c.ok else 'FAIL'}] {c.name}: {c.detail}")
            if not c.ok and c.fix:
                click.echo(f"       fix: {c.fix}")
        click.echo("all good" if ok else f"{sum(not c.ok for c in checks)} problem(s)")
    return 0 if ok else 1
