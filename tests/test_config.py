"""Config: defaults, per-env defaults, presets, typed key=value overrides and clear errors."""

import re

import pytest
from omegaconf import OmegaConf

from pets.config import ConfigError, all_keys, load_config, make_config, parse_overrides

REQUIRED = [
    "trials",
    "seed",
    "device",
    "planner.population",
    "planner.particles",
    "planner.horizon",
    "planner.iterations",
    "model.ensemble_size",
    "model.hidden_size",
    "model.num_layers",
]


def test_required_keys_exist():
    assert set(REQUIRED) <= set(all_keys())


def test_per_env_defaults_follow_pets_references():
    cheetah = make_config("halfcheetah")
    assert (cheetah.planner.horizon, cheetah.planner.population, cheetah.planner.particles) == (30, 400, 20)
    assert cheetah.planner.iterations == 5 and cheetah.planner.elites == pytest.approx(0.16)
    reacher = make_config("reacher")
    assert (reacher.planner.horizon, reacher.planner.population) == (15, 350)
    assert make_config("invertedpendulum").planner.horizon == 45


def test_overrides_are_typed_and_never_octal():
    cfg = make_config("hopper", overrides=parse_overrides(["trials=00143", "planner.alpha=1e-3", "seed=7"]))
    assert cfg.trials == 143 and isinstance(cfg.trials, int)
    assert cfg.planner.alpha == pytest.approx(1e-3)
    assert cfg.seed == 7


def test_fast_preset_plans_the_pendulums_with_mppi():
    ip = make_config("invertedpendulum", preset="fast")
    assert (ip.planner.name, ip.planner.horizon, ip.model.batch_size) == ("mppi", 20, 32)
    assert make_config("hopper", preset="fast").planner.name == "cem"
    assert make_config("invertedpendulum", preset="fast", overrides={"planner.name": "cem"}).planner.name == "cem"


def test_override_beats_preset_beats_env_default():
    fast = make_config("halfcheetah", preset="fast")
    assert fast.planner.population == 100
    cfg = make_config("halfcheetah", preset="fast", overrides={"planner.population": "64"})
    assert cfg.planner.population == 64


@pytest.mark.parametrize(
    "item, fragment",
    [
        ("planner.popsize=3", "unknown config key"),
        ("trials=1.5", "bad value for trials"),
        ("trials=abc", "bad value for trials"),
        ("trials=0", "trials must be >= 1"),
        ("planner.propagation=ts2", "must be one of ts1, tsinf, expectation"),
        ("planner.alpha=nan", "planner.alpha"),
        ("model.num_elites=9", "num_elites"),
        ("planner.replan_every=99", "replan_every"),
        ("planner.elites=0", "planner.elites must be a ratio"),
        ("planner.elites=1000", "planner.population=480], got 1000"),
        ("planner.elites=2.5", "planner.elites must be"),
        ("model.curve_every=-1", "model.curve_every must be >= 0"),
        ("planner.risk_aversion=-1", "planner.risk_aversion must be a finite number >= 0, got -1.0"),
        ("planner.risk_aversion=inf", "planner.risk_aversion must be a finite number >= 0, got inf"),
    ],
)
def test_bad_values_raise_config_error(item, fragment):
    with pytest.raises(ConfigError, match=fragment.replace(".", r"\.").replace("(", r"\(")):
        make_config("invertedpendulum", overrides=parse_overrides([item]))


def test_unknown_key_error_lists_accepted_keys():
    with pytest.raises(ConfigError) as info:
        make_config("reacher", overrides={"nope": "1"})
    assert "planner.population" in str(info.value)


def test_malformed_override():
    with pytest.raises(ConfigError, match="key=value"):
        parse_overrides(["population"])


def test_a_key_given_twice_with_different_values_is_refused_not_the_last_taken():
    with pytest.raises(
        ConfigError, match=r"planner.horizon is given twice \(planner.horizon=20 and planner.horizon=30\)"
    ):
        parse_overrides(["planner.horizon=20", "seed=1", "planner.horizon = 30"])
    assert parse_overrides(["seed=1", "seed=1"]) == {"seed": "1"}  # no value wins over another


def test_a_key_given_twice_in_two_spellings_of_one_value_is_that_value() -> None:
    """The repeat is compared as the key's type parses it, not as text: 5 and 05 of an int, 1e3 and 1000 of a
    float, true and True, null and None are one value (the first text is kept); values that differ once parsed, a
    value the key's type refuses, and a key the schema does not know (a planner section before its imports) are
    refused."""
    assert parse_overrides(["planner.horizon=5", "seed=1", "planner.horizon=05"]) == {
        "planner.horizon": "5",
        "seed": "1",
    }
    assert parse_overrides(["stop_reward=1e3", "stop_reward=1000"]) == {"stop_reward": "1e3"}
    assert parse_overrides(["tensorboard=true", "tensorboard=True", "episode_length=null", "episode_length=None"]) == {
        "tensorboard": "true",
        "episode_length": "null",
    }
    assert (
        make_config("reacher", overrides=parse_overrides(["planner.horizon=5", "planner.horizon=05"])).planner.horizon
        == 5
    )
    for a, b in [("planner.horizon=5", "planner.horizon=6"), ("planner.horizon=1e3", "planner.horizon=1000"),
                 ("stop_reward=1e3", "stop_reward=1001"), ("env=05", "env=5"),
                 ("planner.random_shooting.spread=0.5", "planner.random_shooting.spread=.5")]:  # fmt: skip
        with pytest.raises(ConfigError, match=re.escape(f"is given twice ({a} and {b}); give it once")):
            parse_overrides([a, b])


def test_saved_config_round_trips(tmp_path):
    cfg = make_config("ant", head="gem", overrides={"episode_length": "200"})
    path = tmp_path / "config.yaml"
    path.write_text(OmegaConf.to_yaml(cfg))
    back = load_config(str(path))
    assert OmegaConf.to_container(back) == OmegaConf.to_container(cfg)


def test_fast_preset_plans_invertedpendulum_with_the_terminal_value_and_small_mppi_noise() -> None:
    """Issue 16's measured amendment (docs/planning.md): fast InvertedPendulum only, and overrides still win."""
    fast = make_config("invertedpendulum", "gem", "fast")
    assert (fast.planner.name, fast.planner.horizon, fast.planner.mppi.sigma, fast.value.enabled) == (
        "mppi",
        20,
        0.2,
        True,
    )
    research = make_config("invertedpendulum", "gem", "research")
    assert (research.planner.name, research.planner.mppi.sigma, research.value.enabled) == ("cem", 0.5, False)
    idp = make_config("inverteddoublependulum", "gem", "fast")
    assert (idp.planner.mppi.sigma, idp.value.enabled) == (0.5, False)
    off = make_config("invertedpendulum", "gem", "fast", {"value.enabled": "false", "planner.mppi.sigma": "0.5"})
    assert (off.planner.mppi.sigma, off.value.enabled) == (0.5, False)


def test_risk_aversion_reaches_the_agents_evaluator_and_defaults_to_the_mean() -> None:
    """``planner.risk_aversion`` is off by default (PETS' mean over particles) and the built agent's evaluator gets
    the configured value."""
    import torch

    import envs
    from pets import builder
    from pets.models import make_model

    spec, cpu = envs.get("hopper"), torch.device("cpu")
    for overrides, k in (({}, 0.0), ({"planner.risk_aversion": "1.5"}, 1.5)):
        cfg = make_config("hopper", "delta", "locomotion", overrides)
        agent = builder.make_agent(cfg, spec, make_model(cfg, spec, cpu), cpu, torch.Generator())
        assert cfg.planner.risk_aversion == k and agent.evaluator.risk_aversion == k
