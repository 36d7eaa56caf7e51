"""The ``warpnerf`` command line; :func:`main` is the console script (``warpnerf = "warpnerf.cli:main"``).

Importing it stays cheap (no torch, no Warp): the subcommands import what they run when they run.
"""

from warpnerf.cli.app import main

__all__ = ["main"]
