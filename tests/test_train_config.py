"""Presets and the default regularizer weight γ (docs/training.md, γ schedule)."""

import pytest

from risp_data.errors import RispError
from risp_train.config import (DEFAULT_REG, GAMMA_DEFAULTS, GAMMA_START_DEFAULTS, default_preset, make_config,
                               resolved_gamma, resolved_gamma_start)


def test_default_gamma_is_per_environment_and_the_same_in_both_presets():
    """γ is dimensionless (calibrated regularizer): no preset factor; the default regularizer is RISP's."""
    for env in GAMMA_DEFAULTS:
        paper = make_config("s", "o", preset="paper", reg="exact")
        cpu = make_config("s", "o", preset="cpu", reg=DEFAULT_REG)
        assert DEFAULT_REG != "none"
        assert resolved_gamma(paper, env) == resolved_gamma(cpu, env) == GAMMA_DEFAULTS[env] > 0


def test_default_preset_follows_the_hardware(monkeypatch):
    import torch

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert default_preset() == "cpu"
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    assert default_preset() == "paper"


def test_explicit_gamma_wins_and_none_regularizer_has_no_weight():
    assert resolved_gamma(make_config("s", "o", preset="cpu", reg="exact", gamma=3.0), "cube") == 3.0
    assert resolved_gamma(make_config("s", "o", preset="paper", reg="none"), "cube") == 0.0
    with pytest.raises(RispError, match="unknown environment 'nosuch'; choose one of"):  # was a KeyError traceback
        resolved_gamma(make_config("s", "o", preset="cpu", reg="stochastic"), "nosuch")


@pytest.mark.parametrize("kw, words", [(dict(preset="huge"), "unknown --preset 'huge'"), (dict(reg="l2"), "unknown --reg 'l2'"),
                                       (dict(gamma=-1.0), "--gamma must be >= 0"), (dict(lr=0.0), "--lr must be"),
                                       (dict(gamma_start=1.0), "--gamma-start must be in [0, 1), got 1.0"),
                                       (dict(gamma_start=-0.1), "--gamma-start must be in [0, 1), got -0.1"),
                                       (dict(gamma_ramp=1.5), "--gamma-ramp must be in [0, 1]"),
                                       (dict(stem="resnet"), "unknown stem 'resnet'"),
                                       (dict(seed=-1), "--seed must be in [0, 2**63)"),
                                       (dict(seed=2 ** 64), "--seed must be in [0, 2**63)")])  # was torch's traceback
def test_bad_configuration_is_a_clear_error(kw, words):
    """Each bad setting is refused by a line that names it (not some other rule's error)."""
    with pytest.raises(RispError) as info:
        make_config("s", "o", **kw)
    assert words in str(info.value), str(info.value)


def test_the_ramp_start_is_per_environment_unless_given():
    cfg = make_config("s", "o", preset="cpu", reg="stochastic")
    assert cfg.gamma_start is None  # "the default", resolved per environment
    for env in GAMMA_DEFAULTS:
        assert resolved_gamma_start(cfg, env) == GAMMA_START_DEFAULTS.get(env, 0.0)
    assert resolved_gamma_start(make_config("s", "o", preset="cpu", gamma_start=0.2), "cube") == 0.2
    assert resolved_gamma_start(make_config("s", "o", preset="cpu", gamma_start=0.0), "cube") == 0.0


def test_every_stem_of_the_model_is_accepted():
    from risp_train.model import STEM_FACTOR

    for stem in ("auto", *STEM_FACTOR):
        assert make_config("s", "o", stem=stem).stem == stem



@pytest.mark.parametrize("extra", [["--gamma", "0.5"], ["--gamma-start", "0.9"], ["--gamma-ramp", "0.3"]])
def test_gamma_with_no_regularizer_is_refused(tmp_path, extra):
    """`risp-train fit --reg none --gamma 0.5` used to train without a regularizer and say nothing of the weight."""
    from click.testing import CliRunner

    from risp_train.cli import cli

    r = CliRunner().invoke(cli, ["fit", str(tmp_path / "shards"), "--reg", "none", "--out", str(tmp_path / "run"), *extra])
    assert r.exit_code == 1 and "--reg none trains without one" in r.output, r.output
    assert not (tmp_path / "run").exists()


def test_cli_choices_are_the_modules_own_and_listed_in_help():
    """risp-train's --reg / --preset / --env choices (literals so that --help does not import torch) are the names
    the trainer accepts, and --help lists them."""
    from click.testing import CliRunner

    from risp_data.envs import ENV_NAMES
    from risp_train.cli import cli
    from risp_train.config import PRESETS
    from risp_train.defaults import PRESET_CHOICES, REG_CHOICES
    from risp_train.regularizers import REGULARIZERS

    assert REG_CHOICES == REGULARIZERS and set(PRESET_CHOICES) == set(PRESETS)
    for command, listed in (("fit", ("none|surrogate|exact|stochastic", "paper|cpu")),
                            ("ablation", ("|".join(ENV_NAMES), "paper|cpu"))):
        r = CliRunner().invoke(cli, [command, "--help"])
        assert r.exit_code == 0
        text = " ".join(r.output.split())
        assert all(words in text for words in listed), (command, text)
