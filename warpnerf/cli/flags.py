"""``warpnerf train`` flags generated from :class:`warpnerf.train.config.TrainConfig`.

Every field becomes ``--field-name``: its type from the annotation (``Optional[X]`` takes an X),
its help from the field's trailing comment, its choices from :data:`warpnerf.train.config.CHOICES`, and
bool fields become ``--x/--no-x``. Every flag defaults to ``None``, meaning "not given", so the task
preset and ``--config FILE`` keep their values (see :func:`warpnerf.train.config.build_config`). A new
config field therefore gets its flag, help and type check without touching the CLI.

The help shows each field's dataclass default, or with ``preset`` (``warpnerf train --task X --help``,
:func:`task_for_help`) the value task X's preset gives it where that differs, naming the preset file.
"""

from __future__ import annotations

import argparse
import os
from dataclasses import MISSING, fields
from typing import Optional

from warpnerf.train.config import CHOICES, RENAMED, ConfigError, TrainConfig, field_help, field_type, load_toml, preset_path


def flag_name(name: str) -> str:
    """Command-line flag of a config field.

    >>> flag_name("g2fr_beta")
    '--g2fr-beta'
    """
    return "--" + name.replace("_", "-")


def _help(f, comment: str, preset: Optional[tuple[str, dict]] = None) -> str:
    """The field's comment plus its default; unset and empty defaults are explained by the comment.
    ``preset`` = (file name, values): a value the preset sets other than the default is shown instead,
    with the file that sets it."""
    if preset is not None and f.name in preset[1] and preset[1][f.name] != f.default:
        comment = f"{comment} (default: {preset[1][f.name]}, from {preset[0]})"
    elif f.default is not MISSING and f.default not in (None, ""):
        comment = f"{comment} (default: {f.default})"
    return comment.replace("%", "%%")  # argparse %-formats help strings


def task_for_help(argv: list[str]) -> Optional[str]:
    """The task of ``warpnerf train ... --task X ... --help``, else None (no help asked, another command, no --task).

    >>> task_for_help(["train", "--task", "pose", "--help"])
    'pose'
    >>> task_for_help(["--debug", "train", "-h", "--task=fewshot"])
    'fewshot'
    >>> task_for_help(["train", "--task", "pose"]) is None
    True
    """
    words = [a for a in argv if not a.startswith("-")]
    if not words or words[0] != "train" or not any(a in ("-h", "--help") for a in argv):
        return None
    for i, a in enumerate(argv):
        if a == "--task" and i + 1 < len(argv):
            return argv[i + 1]
        if a.startswith("--task="):
            return a.split("=", 1)[1]
    return None


def preset_values(task: str) -> Optional[tuple[str, dict]]:
    """(``configs/<task>.toml``, its values) for the help of ``--task task``; None when no such preset loads."""
    path = preset_path(task)
    if not os.path.exists(path):
        return None
    try:
        return f"configs/{task}.toml", load_toml(path)
    except ConfigError:  # a broken preset is reported when a run loads it, not by --help
        return None


def add_config_flags(parser: argparse.ArgumentParser, skip: tuple = (), preset: Optional[tuple[str, dict]] = None) -> None:
    """Add one flag per TrainConfig field (except ``skip``) to ``parser``; all default to None. ``preset``
    (:func:`preset_values`): the help shows the preset's values where they differ from the defaults."""
    helps = field_help()
    for f in fields(TrainConfig):
        if f.name in skip:
            continue
        typ, _ = field_type(f.name)
        text = _help(f, helps[f.name], preset)
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
