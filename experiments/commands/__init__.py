"""Subcommands that need the simulator (simulate, run, experiment, montecarlo).

Each module exposes ``command`` (a click command) and imports ``sim``/``mujoco`` lazily inside
the command body, so the core commands still work on a machine without MuJoCo.
"""
