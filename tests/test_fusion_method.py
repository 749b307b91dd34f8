"""fusion.method: ``paper`` reproduces the paper's method; the default is the best measured
combination; keys set beside ``method: paper`` still apply."""

import dataclasses

import pytest

from atlas_onboard.config import PAPER_FUSION, ConfigError, FusionConfig, Weighting, load_world, parse_world
from atlas_onboard.sim import scenarios


def _fusion(section):
    return parse_world({"fusion": section, "entities": {"drone": {}}}, None).fusion


def test_method_paper_is_the_papers_method_whatever_the_defaults():
    f = _fusion({"method": "paper"})
    assert f == PAPER_FUSION
    assert f.path == "bfs" and f.weighting is Weighting.SIGMA_MIN and f.filter == "none"
    assert f.age_sigma_m_per_s == 0.0 and f.age_sigma_deg_per_s == 0.0 and f.outlier_gate_sigma == 0.0
    assert f.ema_alpha == 1.0 and not f.relative_poses


def test_a_key_beside_method_paper_still_applies_and_no_section_is_the_default():
    f = _fusion({"method": "paper", "filter": "ekf", "ema_alpha": 0.5})
    assert f == dataclasses.replace(PAPER_FUSION, filter="ekf", ema_alpha=0.5)
    assert _fusion(None) == _fusion({}) == _fusion({"method": "default"}) == FusionConfig()


def test_the_default_differs_from_the_paper():
    """The defaults are not the paper's method (a user who reads no table gets the best row)."""
    differ = [
        k
        for k in ("path", "weighting", "age_sigma_m_per_s", "filter")
        if getattr(FusionConfig(), k) != getattr(PAPER_FUSION, k)
    ]
    assert differ, "the default fusion settings are the paper's method"


def test_an_unknown_method_names_the_field():
    with pytest.raises(ConfigError, match=r"fusion\.method.*default, paper.*'best'"):
        _fusion({"method": "best"})


@pytest.mark.parametrize("name", ["paper-test1", "paper-test2"])
def test_the_paper_replicas_run_the_papers_method(name):
    assert load_world(scenarios.get(name).world_path()).fusion == PAPER_FUSION
