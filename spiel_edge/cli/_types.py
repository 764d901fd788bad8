"""Rules every numeric option follows, whoever adds it: applied to each command as it loads
(:func:`harden_command`), so a new ``type=float`` or ``click.IntRange`` option needs nothing.

* floats must be finite (``nan``, ``inf`` and overflowing text such as ``1e999`` are usage
  errors, exit status 2), ranges kept as declared;
* integers must fit in 32 bits (``MAX_INT``) unless the option declares its own maximum: no
  value reaches a wire field or an array size it would overflow.
"""

from __future__ import annotations

import math

import click

MAX_INT = 2**31 - 1
_CLASSES: dict[type, type] = {}


def _convert_float(self, value, param, ctx):
    number = super(type(self), self).convert(value, param, ctx)
    if isinstance(number, float) and not math.isfinite(number):
        self.fail(f"{value!r} is not a finite number.", param, ctx)
    return number


def _convert_int(self, value, param, ctx):
    number = super(type(self), self).convert(value, param, ctx)
    declared_max = getattr(self, "max", None)
    if isinstance(number, int) and declared_max is None and abs(number) > MAX_INT:
        self.fail(f"{value!r} is too large (at most {MAX_INT}).", param, ctx)
    return number


def _hardened(kind: click.ParamType) -> click.ParamType:
    cls = type(kind)
    if getattr(cls, "_hardened", False):
        return kind
    if isinstance(kind, click.types.FloatParamType):
        convert = _convert_float
    elif isinstance(kind, click.types.IntParamType):
        convert = _convert_int
    else:
        return kind
    sub = _CLASSES.get(cls)
    if sub is None:
        sub = type(cls.__name__, (cls,), {"_hardened": True, "convert": convert})
        _CLASSES[cls] = sub
    hardened = object.__new__(sub)
    hardened.__dict__.update(kind.__dict__)
    return hardened


def harden_command(command: click.Command) -> click.Command:
    """Apply the rules to every option and argument of ``command`` (and its subcommands)."""
    if getattr(command, "_hardened", False):
        return command
    for param in command.params:
        param.type = _hardened(param.type)
    if isinstance(command, click.Group):
        for sub in command.commands.values():
            harden_command(sub)
    command._hardened = True  # type: ignore[attr-defined]
    return command
