"""Every stage config composes with every profile; bad selections fail naming the key."""

import pytest
from hydra.errors import ConfigCompositionException, MissingConfigException
from omegaconf import OmegaConf

from tests.conftest import CONF, compose_cfg

STAGES = sorted(p.stem for p in CONF.glob("*.yaml") if p.stem != "base")
PROFILES = sorted(p.stem for p in (CONF / "profile").glob("*.yaml"))


@pytest.mark.parametrize("stage", STAGES)
@pytest.mark.parametrize("profile", PROFILES)
def test_every_stage_composes_with_every_profile(stage, profile):
    cfg = compose_cfg(stage, [f"profile={profile}"])
    resolved = OmegaConf.to_container(cfg, resolve=True, throw_on_missing=True)
    assert resolved["stage"] == stage and resolved["profile_name"] == profile


def test_unknown_profile_names_the_group():
    with pytest.raises(MissingConfigException, match="profile/bogus"):
        compose_cfg("synthesize", ["profile=bogus"])


def test_unknown_key_names_the_key():
    with pytest.raises(ConfigCompositionException, match="synth.bogus"):
        compose_cfg("synthesize", ["synth.bogus=1"])


def test_bad_synth_values_name_the_key():
    from pipeline.data.synth.generate import SynthConfig, assign_splits
    from pipeline.data.synth.mitsuba_backend import choose_variant

    with pytest.raises(ValueError, match="synth.scenes=2"):
        assign_splits(2, {"train": 0.7, "val": 0.15, "test": 0.15}, 0)
    with pytest.raises(ValueError, match="synth.variant='cuda'"):
        choose_variant("cuda")
    with pytest.raises(ValueError, match="unknown key"):
        SynthConfig.from_dict({"scenes": 3, "nope": 1})
