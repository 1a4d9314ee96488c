"""``gyroharness noise``: the same command as ``gyroharness allan`` (the name fits what it does)."""

from __future__ import annotations

import click

from .allan import command as _allan

command = click.Command(
    "noise",
    callback=_allan.callback,
    params=list(_allan.params),
    help=(_allan.help or "") + " Same command as 'allan'.",
)
