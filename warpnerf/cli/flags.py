"""``warpnerf train`` flags generated from :class:`warpnerf.train.config.TrainConfig`.

Every field becomes ``--field-name``: its type from the annotation (``Optional[X]`` takes an X),
its help from the field's trailing comment, its choices from :data:`warpnerf.train.config.CHOICES`, and
bool fields become ``--x/--no-x``. Every flag defaults to ``None``, meaning "not given", so the task
preset and ``--config FILE`` keep their values (see :func:`warpnerf.train.config.build_config`). A new
config field therefore gets its flag, help and type check without touching the CLI.
"""

from __future__ import annotations

import argparse
from dataclasses import MISSING, fields

from warpnerf.train.config import CHOICES, RENAMED, TrainConfig, field_help, field_type


def flag_name(name: str) -> str:
    """Command-line flag of a config field.

    >>> flag_name("g2fr_beta")
    '--g2fr-beta'
    """
    return "--" + name.replace("_", "-")


def _help(f, comment: str) -> str:
    """The field's comment plus its default; unset and empty defaults are explained by the comment."""
    if f.default is not MISSING and f.default not in (None, ""):
        comment = f"{comment} (default: {f.default})"
    return comment.replace("%", "%%")  # argparse %-formats help strings


def add_config_flags(parser: argparse.ArgumentParser, skip: tuple = ()) -> None:
    """Add one flag per TrainConfig field (except ``skip``) to ``parser``; all default to None."""
    helps = field_help()
    for f in fields(TrainConfig):
        if f.name in skip:
            continue
        typ, _ = field_type(f.name)
        text = _help(f, helps[f.name])
        if typ is bool:
            parser.add_argument(flag_name(f.name), action=argparse.BooleanOptionalAction, default=None, help=text)
            continue
        choices = CHOICES.get(f.name)
        metavar = None if choices is not None else typ.__name__.upper()
        # a renamed setting keeps its old flag as a second spelling (train.config.RENAMED), so scripts still run
        old = [flag_name(k) for k, v in RENAMED.items() if v == f.name]
        parser.add_argument(flag_name(f.name), *old, dest=f.name, type=typ, default=None, choices=choices,
                            metavar=metavar, help=text)


def config_overrides(args: argparse.Namespace) -> dict:
    """The config values given on the command line (None for flags not given), keyed by field name.

    ``task`` is left out: :func:`warpnerf.train.config.build_config` takes it as its own argument.
    """
    return {f.name: getattr(args, f.name) for f in fields(TrainConfig) if f.name != "task" and hasattr(args, f.name)}
