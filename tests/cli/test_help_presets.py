"""`warpnerf train --task X --help` shows the values task X runs with, not only the dataclass defaults (#65)."""

from dataclasses import fields

import pytest

from warpnerf.cli import main
from warpnerf.cli.app import build_parser
from warpnerf.cli.flags import task_for_help
from warpnerf.train.config import TrainConfig, load_toml, preset_path

DEFAULTS = {f.name: f.default for f in fields(TrainConfig)}


def _train_helps(help_task=None) -> dict:
    parser = build_parser(help_task=help_task)
    train = next(a for a in parser._actions if a.dest == "command").choices["train"]
    return {a.dest: a.help for a in train._actions}, train.epilog


@pytest.mark.parametrize("task", ["full", "fewshot", "pose"])
def test_task_help_shows_each_preset_value_that_differs(task):
    preset = load_toml(preset_path(task))
    helps, epilog = _train_helps(task)
    changed = {k: v for k, v in preset.items() if v != DEFAULTS[k]}
    assert changed  # every shipped preset changes something
    for key, value in changed.items():
        assert helps[key].endswith(f"(default: {value}, from configs/{task}.toml)"), (key, helps[key])
    for key, value in DEFAULTS.items():  # the rest keep the dataclass default
        if key not in changed and value not in (None, ""):
            assert helps[key].endswith(f"(default: {value})"), (key, helps[key])
    assert f"Defaults shown are task {task}'s: configs/{task}.toml" in epilog


def test_plain_help_keeps_dataclass_defaults_and_points_to_task_help():
    helps, epilog = _train_helps()
    assert helps["iters"] == f"training steps (default: {DEFAULTS['iters']})"
    assert not any("from configs/" in (h or "") for h in helps.values())
    assert "'warpnerf train --task X --help' shows the values task X runs with" in epilog


def test_task_help_end_to_end(capsys, monkeypatch):
    monkeypatch.setenv("COLUMNS", "300")  # no wrapping inside a flag's help
    with pytest.raises(SystemExit) as e:
        main(["train", "--task", "pose", "--help"])
    assert e.value.code == 0
    out = capsys.readouterr().out
    assert "training steps (default: 3000, from configs/pose.toml)" in out
    assert "mask grid levels coarse to fine (default: True, from configs/pose.toml)" in out
    with pytest.raises(SystemExit):
        main(["train", "--help", "--task=fewshot"])
    assert "training steps (default: 1000, from configs/fewshot.toml)" in capsys.readouterr().out


def test_unknown_task_help_falls_back_to_defaults():
    assert task_for_help(["train", "--task", "nope", "--help"]) == "nope"
    helps, epilog = _train_helps("nope")
    assert helps["iters"] == f"training steps (default: {DEFAULTS['iters']})"
    assert "--task X --help" in epilog
    assert task_for_help(["eval", "--task", "pose", "--help"]) is None
