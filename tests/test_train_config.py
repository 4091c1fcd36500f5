"""Presets and the default regularizer weight γ (docs/training.md, γ schedule)."""

import pytest

from risp_data.errors import RispError
from risp_train.config import GAMMA_DEFAULTS, make_config, resolved_gamma


def test_paper_preset_uses_the_papers_gamma_and_cpu_preset_scales_it():
    paper = make_config("s", "o", preset="paper", reg="exact")
    cpu = make_config("s", "o", preset="cpu", reg="stochastic")
    assert resolved_gamma(paper, "cube") == GAMMA_DEFAULTS["cube"] == 20.0
    assert resolved_gamma(cpu, "cube") == pytest.approx(0.05)
    assert resolved_gamma(cpu, "hand") == pytest.approx(100.0 / 400.0)


def test_explicit_gamma_wins_and_none_regularizer_has_no_weight():
    assert resolved_gamma(make_config("s", "o", preset="cpu", reg="exact", gamma=3.0), "cube") == 3.0
    assert resolved_gamma(make_config("s", "o", preset="paper", reg="none"), "cube") == 0.0


@pytest.mark.parametrize("kw", [dict(preset="huge"), dict(reg="l2"), dict(gamma=-1.0), dict(lr=0.0)])
def test_bad_configuration_is_a_clear_error(kw):
    with pytest.raises(RispError):
        make_config("s", "o", **kw)
