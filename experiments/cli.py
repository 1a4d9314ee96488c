"""Entry point of the ``gyroharness`` console script: core commands + simulator commands."""

from __future__ import annotations

import sys
from typing import Sequence

from gyrocore.cli import build_group, run_cli


def main(argv: Sequence[str] | None = None) -> None:
    sys.exit(run_cli(build_group(["experiments.commands"]), argv))


if __name__ == "__main__":
    main()
