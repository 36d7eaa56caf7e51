"""The typed config is the one source of the train CLI: every field a flag, typed, with help and choices."""

import argparse
from dataclasses import fields

import pytest

from warpnerf.cli.app import build_parser
from warpnerf.cli.flags import config_overrides, flag_name
from warpnerf.train import config as C


def train_parser() -> argparse.ArgumentParser:
    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    return sub.choices["train"]


def train_actions() -> dict:
    return {opt: a for a in train_parser()._actions for opt in a.option_strings}


def parse(*argv):
    return build_parser().parse_args(["train", *argv])


def test_every_field_has_a_flag_with_help():
    actions = train_actions()
    for f in fields(C.TrainConfig):
        action = actions.get(flag_name(f.name))
        assert action is not None, f"TrainConfig.{f.name} has no flag {flag_name(f.name)}"
        assert action.dest == f.name
        assert C.field_help()[f.name].strip(), f"TrainConfig.{f.name} has no help comment"
        assert C.field_help()[f.name] in action.help.replace("%%", "%")


def test_flag_types_follow_annotations():
    actions = train_actions()
    for f in fields(C.TrainConfig):
        typ, optional = C.field_type(f.name)
        action = actions[flag_name(f.name)]
        if typ is bool:
            assert isinstance(action, argparse.BooleanOptionalAction) and "--no-" + flag_name(f.name)[2:] in actions
        else:
            assert action.type is typ, f.name
        # optional fields hold None by default; the others a value of their annotated type
        assert (f.default is None) == optional, f.name
        if f.default is not None:
            assert isinstance(f.default, typ), f.name


def test_field_type_unwraps_optional():
    assert C.field_type("threads") == (int, True)
    assert C.field_type("pose_noise") == (float, True)
    assert C.field_type("data_root") == (str, True)
    assert C.field_type("g2fr") == (bool, False)
    assert C.field_type("lr") == (float, False)


def test_flags_not_given_are_none_so_presets_keep_their_values():
    args = parse()
    values = config_overrides(args)
    assert set(values) == {f.name for f in fields(C.TrainConfig)} - {"task"}
    assert all(v is None for v in values.values())
    assert args.task is None  # build_config: the --config file's task, else full
    cfg = C.build_config("fewshot", None, config_overrides(parse("--task", "fewshot")))
    assert cfg.iters == 1000 and cfg.g2fr is True and cfg.n_views == 10  # configs/fewshot.toml


def test_flags_round_trip_into_the_config(tmp_path):
    args = parse("--task", "pose", "--iters", "7", "--lr", "3e-3", "--no-g2fr", "--g2fr-mask", "binary",
                 "--model", "mtrf", "--pose-noise", "0.05", "--threads", "1", "--data-root", str(tmp_path),
                 "--hidden", "32", "--levels", "8", "--pose-lr", "2e-3", "--no-random-background", "--log2-table-size",
                 "12")
    cfg = C.build_config(args.task, None, config_overrides(args))
    assert (cfg.task, cfg.iters, cfg.lr, cfg.g2fr, cfg.g2fr_mask, cfg.model) == ("pose", 7, 3e-3, False, "binary", "mtrf")
    assert (cfg.pose_noise, cfg.threads, cfg.data_root, cfg.hidden, cfg.levels) == (0.05, 1, str(tmp_path), 32, 8)
    assert (cfg.pose_lr, cfg.random_background, cfg.log2_table_size) == (2e-3, False, 12)
    assert isinstance(cfg.lr, float) and isinstance(cfg.iters, int)
    # --g2fr turns on what the full preset leaves off; the flag beats the preset and a config file
    cfg_file = tmp_path / "c.toml"
    cfg_file.write_text("g2fr = false\niters = 9\n")
    cfg = C.build_config("full", str(cfg_file), config_overrides(parse("--g2fr", "--config", str(cfg_file))))
    assert cfg.g2fr is True and cfg.iters == 9


def test_choices_come_from_the_code_registries():
    from warpnerf.model import g2fr
    from warpnerf.train import tasks

    actions = train_actions()
    assert list(actions["--task"].choices) == list(tasks.TASKS)
    assert list(actions["--model"].choices) == list(C.MODELS)
    assert list(actions["--g2fr-mask"].choices) == list(g2fr.MASK_MODES)
    with pytest.raises(SystemExit):
        parse("--g2fr-mask", "smooth")
    with pytest.raises(SystemExit):
        parse("--iters", "ten")
    with pytest.raises(C.ConfigError, match="g2fr_mask"):
        C.build_config("full", overrides={"g2fr_mask": "smooth"})


def test_toml_values_are_checked_against_the_annotations(tmp_path):
    good = tmp_path / "good.toml"
    good.write_text("lr = 1\nthreads = 2\npose_noise = 0\ndata_root = 'x'\ng2fr = true\n")
    values = C.load_toml(str(good))
    assert values == {"lr": 1.0, "threads": 2, "pose_noise": 0.0, "data_root": "x", "g2fr": True}
    assert isinstance(values["lr"], float) and isinstance(values["pose_noise"], float)
    for bad in ("iters = 1.5", "iters = true", "lr = 'fast'", "threads = 2.0", "g2fr = 1", "pose_noise = false"):
        path = tmp_path / "bad.toml"
        path.write_text(bad + "\n")
        with pytest.raises(C.ConfigError, match=bad.split(" ")[0]):
            C.load_toml(str(path))


def test_g2fr_beta_has_one_default():
    from warpnerf.model.g2fr import G2FR_BETA, G2fRSchedule
    from warpnerf.studies import spectrum

    assert C.TrainConfig().g2fr_beta == G2FR_BETA
    assert G2fRSchedule(4, 10).beta == G2FR_BETA
    assert spectrum.FitConfig().beta == G2FR_BETA
    for task in ("full", "fewshot", "pose"):  # presets do not restate it
        assert "g2fr_beta" not in C.load_toml(C.preset_path(task))


@pytest.mark.parametrize("bad", [0.0, 1.5, float("nan")])
def test_occ_uniform_fraction_is_checked(bad):
    with pytest.raises(C.ConfigError, match="^occ_uniform_fraction must be in"):
        C.validate(C.build_config("full", overrides={"occ_uniform_fraction": bad}))


@pytest.mark.parametrize("key", ["background_low", "background_low_late", "background_late_from"])
@pytest.mark.parametrize("bad", [-0.1, 1.5, float("nan")])
def test_background_bounds_are_checked(key, bad):
    """A random background's channels are drawn from U[low, 1]: each bound must be a colour value, and the
    switch to the late bound a fraction of the steps."""
    with pytest.raises(C.ConfigError, match=f"^{key} must be in"):
        C.validate(C.build_config("full", overrides={key: bad}))
    C.validate(C.build_config("full", overrides={key: 1.0}))
    C.validate(C.build_config("full", overrides={key: 0.0}))


@pytest.mark.parametrize("bad", [-0.01, float("nan"), float("inf")])
def test_distortion_weight_is_checked(bad):
    """A negative weight would reward spreading each ray's weight; NaN or inf would poison the loss."""
    with pytest.raises(C.ConfigError, match="^distortion_weight must be a finite number >= 0"):
        C.validate(C.build_config("full", overrides={"distortion_weight": bad}))
    C.validate(C.build_config("full", overrides={"distortion_weight": 0.01}))


def test_forward_facing_scenes_get_their_preset(tmp_path, monkeypatch):
    """task=full on a forward-facing scene (LLFF layout: a dataset scene or the built-in 'yard') merges
    configs/full_forward_facing.toml over full.toml; other scenes and tasks keep their presets, and
    --config files and flags still win over it."""
    monkeypatch.delenv("WARPNERF_DATA", raising=False)
    ff = C.load_toml(C.preset_path("full" + C.FORWARD_FACING_SUFFIX))
    assert ff["distortion_weight"] > 0 and ff["march_steps"] == 256
    full = C.load_toml(C.preset_path("full"))

    def picked(cfg, preset):
        return {k: getattr(cfg, k) for k in preset}

    assert picked(C.build_config("full", overrides={"scene": "yard"}), ff) == ff
    assert picked(C.build_config("full", overrides={"scene": "chair"}), ff) == {
        k: full.get(k, getattr(C.TrainConfig, k)) for k in ff}
    assert C.build_config("fewshot", overrides={"scene": "yard"}).distortion_weight == 0.0
    assert C.build_config("full", overrides={"scene": "yard", "march_steps": 384}).march_steps == 384
    cfg_file = tmp_path / "mine.toml"
    cfg_file.write_text("occ_threshold = 0.02\n")
    assert C.build_config("full", str(cfg_file), {"scene": "yard"}).occ_threshold == 0.02
    # dataset scenes: by layout, found under the data root as loading would find them
    root = tmp_path / "data"
    (root / "nerf_llff_data" / "leaves").mkdir(parents=True)
    (root / "nerf_llff_data" / "leaves" / "poses_bounds.npy").write_bytes(b"")
    (root / "nerf_synthetic" / "yard").mkdir(parents=True)
    (root / "nerf_synthetic" / "yard" / "transforms_train.json").write_text("{}")
    assert C.build_config("full", overrides={"scene": "leaves", "data_root": str(root)}).march_steps == 256
    # a dataset scene named like the built-in one shadows it: a Blender scene is not forward-facing
    assert C.build_config("full", overrides={"scene": "yard", "data_root": str(root)}).march_steps == full["march_steps"]
    monkeypatch.setenv("WARPNERF_DATA", str(root))
    assert C.build_config("full", overrides={"scene": "leaves"}).distortion_weight == ff["distortion_weight"]
    # an unusable data root is loading's error to report, not the config's
    assert C.build_config("full", overrides={"scene": "yard", "data_root": str(tmp_path / "none")}).march_steps == 256


def test_renamed_keys_of_an_old_run_folder_still_load(tmp_path):
    """eval_every (it counted views, its siblings count steps) is eval_view_stride; save_every and
    checkpoint_every, two periods for one file, are checkpoint_every. An old config.toml still loads."""
    from warpnerf.train.config import ConfigError, build_config, load_toml

    p = tmp_path / "config.toml"
    p.write_text('task = "full"\neval_every = 4\nsave_every = 500\ncheckpoint_every = 100\n')
    assert load_toml(str(p)) == {"task": "full", "eval_view_stride": 4, "checkpoint_every": 100}
    p.write_text("save_every = 500\ncheckpoint_every = 0\n")
    assert load_toml(str(p)) == {"checkpoint_every": 500}
    p.write_text("save_every = 0\ncheckpoint_every = 0\n")
    assert load_toml(str(p)) == {"checkpoint_every": 0}
    assert build_config("full", overrides={"save_every": 250, "eval_every": 2}).checkpoint_every == 250
    p.write_text('save_every = "often"\n')
    with pytest.raises(ConfigError, match="checkpoint_every"):
        load_toml(str(p))


def test_renamed_settings_keep_their_old_flags():
    args = build_parser().parse_args(["train", "--save-every", "10", "--eval-every", "2"])
    overrides = config_overrides(args)
    assert overrides["checkpoint_every"] == 10 and overrides["eval_view_stride"] == 2
    assert "save_every" not in overrides and "eval_every" not in overrides


def test_forward_facing_pose_preset(monkeypatch):
    """task=pose on a forward-facing scene merges configs/pose_forward_facing.toml over pose.toml (the fern
    pilot's settings, docs/studies/2026-12-07-pose-fern-barf-protocol.md); object scenes keep pose.toml and a
    flag still wins."""
    monkeypatch.delenv("WARPNERF_DATA", raising=False)
    ff = C.load_toml(C.preset_path("pose" + C.FORWARD_FACING_SUFFIX))
    pose = C.load_toml(C.preset_path("pose"))
    assert ff["march_steps"] != pose["march_steps"] and ff["pose_lr_final"] != pose["pose_lr_final"]
    yard = C.build_config("pose", overrides={"scene": "yard"})
    assert {k: getattr(yard, k) for k in ff} == ff
    assert yard.g2fr and yard.iters == pose["iters"]  # the rest is pose.toml's
    chair = C.build_config("pose", overrides={"scene": "chair"})
    assert {k: getattr(chair, k) for k in ff} == {k: pose.get(k, getattr(C.TrainConfig, k)) for k in ff}
    assert C.build_config("pose", overrides={"scene": "yard", "march_steps": 384}).march_steps == 384
