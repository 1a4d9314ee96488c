"""Core subcommands of ``gyroharness``: one module per command, each exposing ``command``.

Modules here are discovered automatically by :mod:`gyrocore.cli`; they must not import
``sim`` or ``mujoco``.
"""
