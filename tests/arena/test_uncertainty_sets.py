"""The uncertainty sets without an env: the box, its refusals, draws, nature's map, schedules.

``tests/arena/test_uncertainty.py`` drives whole races; these pin the pure functions of
``arena/uncertainty.py`` at their edges (exact messages, bound values, every-k boundaries,
seeded streams) in milliseconds, so a mutation run kills what it can here first.
"""

from __future__ import annotations

import dataclasses
import re
import warnings
from typing import Any

import numpy as np
import pytest

from arena.sim import CarScales
from arena.uncertainty import (
    DEFAULT_DYNAMICS,
    INDEX,
    LATENCY,
    MAX_LATENCY,
    PARAM_NAMES,
    REWARD_NOISE,
    REWARD_WEIGHTS,
    DynamicsBounds,
    EpisodeRandomisation,
    PerceptionBounds,
    Perturbation,
    PerturbationState,
    RewardBounds,
    UncertaintyConfig,
    UncertaintyError,
    applied,
    default_config,
    nature_values,
    nominal_values,
    normalised,
    reward_noise,
    sample_values,
)

P = len(PARAM_NAMES)
FRICTION = INDEX["friction"]
ONES = ("friction", "mass", "motor", "steer_gain", "contrast", *REWARD_WEIGHTS)
DYNAMICS_FREE = (
    "friction",
    "mass",
    "motor",
    "steer_gain",
    "steer_offset",
    "latency",
    "action_noise",
)


def refused(message: str, **kwargs: Any) -> None:
    """``UncertaintyConfig(**kwargs)`` raises UncertaintyError with exactly ``message``."""
    with pytest.raises(UncertaintyError, match=f"^{re.escape(message)}$"):
        UncertaintyConfig(**kwargs)


# ---- the config's refusals, at their boundaries ----------------------------------------------


def test_every_refusal_names_the_setting_and_the_bad_value() -> None:
    """Each check of ``UncertaintyConfig`` gives its own message with the value it got."""
    refused(
        "uncertainty mode must be one of ('nominal', 'sample', 'fixed', 'adversarial'), "
        "got 'robust'",
        mode="robust",
    )
    refused("resample must be episode, step or every_k: 'lap'", resample="lap")
    refused("every_k must be at least 1, got 0", every_k=0)
    refused("nature_acts must be reset or step: 'lap'", nature_acts="lap")
    refused("nature_rate must be in (0, 1], got 0.0", nature_rate=0.0)
    refused("nature_rate must be in (0, 1], got -0.5", nature_rate=-0.5)
    refused("nature_rate must be in (0, 1], got 1.01", nature_rate=1.01)
    refused("reward noise must be >= 0 and noise_clip > 0", reward=RewardBounds(noise=-0.1))
    refused("reward noise must be >= 0 and noise_clip > 0", reward=RewardBounds(noise_clip=0.0))
    refused(
        "episode start must be grid, random or round_robin: 'pole'",
        episode=EpisodeRandomisation(start="pole"),  # type: ignore[arg-type]
    )
    refused(
        "direction must be forward, random or alternate: 'backwards'",
        episode=EpisodeRandomisation(direction="backwards"),  # type: ignore[arg-type]
    )
    refused(
        "adversarial mode needs at least one interval with lo < hi",
        mode="adversarial",
        dynamics=DynamicsBounds(friction=(0.9, 0.9)),
    )
    refused("edge_share must be in [0, 1], got 1.5", mode="sample", edge_share=1.5)
    refused("edge_share must be in [0, 1], got -0.1", mode="sample", edge_share=-0.1)
    refused("edge_share needs mode 'sample', not 'adversarial'", mode="adversarial",
            dynamics=DynamicsBounds(friction=(0.6, 1.2)), edge_share=0.5)  # fmt: skip
    refused("edge_share needs mode 'sample', not 'fixed'", mode="fixed", edge_share=0.5)


def test_the_accepted_edges_of_each_setting() -> None:
    """The values just inside each refusal are accepted: every_k=1, rate 1, zero noise…"""
    assert UncertaintyConfig(mode="sample", resample="every_k", every_k=1).every_k == 1
    for rate in (1.0, 1e-9, None):
        assert UncertaintyConfig(nature_acts="step", nature_rate=rate).nature_rate == rate
    assert UncertaintyConfig(reward=RewardBounds(noise=0.0, noise_clip=1e-9)).reward.noise == 0.0
    for mode in ("nominal", "sample", "fixed"):
        assert UncertaintyConfig(mode=mode).mode == mode  # type: ignore[arg-type]
    for start in ("grid", "random", "round_robin"):
        for direction in ("forward", "random", "alternate"):
            ep = EpisodeRandomisation(start=start, direction=direction)  # type: ignore[arg-type]
            assert UncertaintyConfig(mode="sample", episode=ep).episode == ep
    adversarial = UncertaintyConfig(mode="adversarial", dynamics=DynamicsBounds(mass=(1.0, 1.1)))
    assert adversarial.free_names == ("mass",)


@pytest.mark.parametrize(
    ("bounds", "message"),
    [
        (DynamicsBounds(friction=(1.2, 0.6)), "friction bounds must be finite with lo <= hi"),
        (DynamicsBounds(mass=(float("nan"), 1.0)), "mass bounds must be finite with lo <= hi"),
        (DynamicsBounds(motor=(1.0, float("inf"))), "motor bounds must be finite with lo <= hi"),
        (DynamicsBounds(friction=(0.0, 1.0)), "friction in the bounds must be positive"),
        (DynamicsBounds(steer_gain=(-1.0, 1.0)), "steer_gain in the bounds must be positive"),
        (DynamicsBounds(latency=(0, 11)), "latency in the bounds must be whole steps in 0..10"),
        (DynamicsBounds(latency=(-1, 2)), "latency in the bounds must be whole steps in 0..10"),
        (DynamicsBounds(latency=(0, 1.5)), "latency in the bounds must be whole steps in 0..10"),
        (DynamicsBounds(action_noise=(-0.1, 0.1)), "action_noise in the bounds must be >= 0"),
    ],
)
def test_dynamics_bounds_the_simulator_cannot_take(bounds: DynamicsBounds, message: str) -> None:
    """Reversed, non-finite, non-positive scales and out-of-range latencies are refused."""
    refused(message, dynamics=bounds)


@pytest.mark.parametrize(
    ("bounds", "message"),
    [
        (
            PerceptionBounds(lidar_dropout=(0.0, 1.01)),
            "lidar_dropout in the bounds must be in [0, 1]",
        ),
        (PerceptionBounds(shadow=(-0.01, 0.5)), "shadow in the bounds must be in [0, 1]"),
        (PerceptionBounds(contrast=(0.0, 1.0)), "contrast in the bounds must be positive"),
        (PerceptionBounds(lidar_noise=(-0.01, 0.0)), "lidar_noise in the bounds must be >= 0"),
        (PerceptionBounds(image_noise=(-1.0, 0.0)), "image_noise in the bounds must be >= 0"),
        (PerceptionBounds(shift=(-2.0, 2.0)), "shift in the bounds must be >= 0"),
    ],
)
def test_perception_bounds_the_simulator_cannot_take(
    bounds: PerceptionBounds, message: str
) -> None:
    """Probabilities outside [0, 1] and negative noise levels or shifts are refused."""
    refused(message, perception=bounds)


def test_the_widest_legal_bounds_are_accepted() -> None:
    """The closed ends of every range are legal: latency 0..10, fractions 0..1, zero noise."""
    cfg = UncertaintyConfig(
        mode="sample",
        dynamics=DynamicsBounds(latency=(0, MAX_LATENCY), action_noise=(0.0, 0.0)),
        perception=PerceptionBounds(lidar_dropout=(0.0, 1.0), shadow=(0.0, 1.0), shift=(0, 0)),
    )
    assert cfg.highs[LATENCY] == 10.0 and cfg.free_names == ("latency", "lidar_dropout", "shadow")


def test_a_config_perturbation_is_checked_against_its_longest_list() -> None:
    """Per-car lists must agree: the longest one sets the car count the others must match."""
    with pytest.raises(UncertaintyError, match=r"^friction needs one value per car \(3\), got"):
        UncertaintyConfig(
            mode="fixed", perturbation={"friction": [0.7, 0.8], "mass": [1.0, 1.1, 1.2]}
        )
    with pytest.raises(UncertaintyError, match=r"^unknown perturbation parameter 'grip'$"):
        UncertaintyConfig(mode="fixed", perturbation={"grip": 1.0})
    ok = UncertaintyConfig(mode="fixed", perturbation={"friction": 0.7, "mass": [1.0, 1.1, 1.2]})
    assert ok.perturbation == {"friction": 0.7, "mass": [1.0, 1.1, 1.2]}


# ---- the box -----------------------------------------------------------------------------------


def test_the_box_in_param_order_with_the_reward_noise_interval() -> None:
    """lows/highs list every interval in PARAM_NAMES order; reward noise spans ±clip·λ."""
    cfg = UncertaintyConfig(
        mode="sample",
        dynamics=DynamicsBounds(friction=(0.6, 1.2), latency=(1, 3), steer_offset=(-0.05, 0.04)),
        perception=PerceptionBounds(lidar_dropout=(0.0, 0.2), contrast=(0.7, 1.3)),
        reward=RewardBounds(noise=0.5, noise_clip=3.0, collision=(0.5, 2.0), overtake=(0.0, 1.0)),
    )
    lows = dict(zip(PARAM_NAMES, cfg.lows.tolist(), strict=True))
    highs = dict(zip(PARAM_NAMES, cfg.highs.tolist(), strict=True))
    changed_lo = {
        "friction": 0.6,
        "latency": 1.0,
        "steer_offset": -0.05,
        "contrast": 0.7,
        "reward_noise": -1.5,
        "w_collision": 0.5,
        "w_overtake": 0.0,
    }
    changed_hi = {
        "friction": 1.2,
        "latency": 3.0,
        "steer_offset": 0.04,
        "lidar_dropout": 0.2,
        "contrast": 1.3,
        "reward_noise": 1.5,
        "w_collision": 2.0,
    }
    nominal = dict(zip(PARAM_NAMES, nominal_values().tolist(), strict=True))
    assert lows == {**nominal, **changed_lo}
    assert highs == {**nominal, **changed_hi}
    assert cfg.free_names == (
        "friction",
        "steer_offset",
        "latency",
        "lidar_dropout",
        "contrast",
        "reward_noise",
        "w_collision",
        "w_overtake",
    )
    assert cfg.free.tolist() == [INDEX[n] for n in cfg.free_names]
    # Cached and shared: read-only, so no caller can corrupt the box.
    assert cfg.lows is cfg.lows
    for arr in (cfg.lows, cfg.highs, cfg.free):
        with pytest.raises(ValueError, match="read-only"):
            arr[0] = 5
    np.testing.assert_array_equal(cfg.nominal, nominal_values())


def test_nominal_values_are_one_for_scales_and_weights_zero_for_the_rest() -> None:
    """Multipliers (and contrast, reward weights) are 1 at nominal, offsets and noise 0."""
    nom = dict(zip(PARAM_NAMES, nominal_values().tolist(), strict=True))
    assert nom == {name: 1.0 if name in ONES else 0.0 for name in PARAM_NAMES}
    default = UncertaintyConfig()
    np.testing.assert_array_equal(default.lows, nominal_values())
    np.testing.assert_array_equal(default.highs, nominal_values())
    assert default.free_names == ()


def test_scaled_moves_every_interval_about_nominal() -> None:
    """``scaled(s)``: lo' = nom + s·(lo − nom) on each group; latency rounded; λ scaled."""
    cfg = UncertaintyConfig(
        mode="sample",
        resample="every_k",
        every_k=4,
        dynamics=DynamicsBounds(friction=(0.6, 1.2), steer_offset=(-0.05, 0.05), latency=(0, 3)),
        perception=PerceptionBounds(contrast=(0.7, 1.3), lidar_noise=(0.0, 0.04)),
        reward=RewardBounds(noise=0.2, noise_clip=1.5, progress=(0.5, 1.5)),
    )
    half = cfg.scaled(0.5)
    assert half.dynamics.friction == pytest.approx((0.8, 1.1))
    assert half.dynamics.steer_offset == pytest.approx((-0.025, 0.025))
    assert half.dynamics.latency == (0, 2)  # round(1.5) = 2 (to even)
    assert isinstance(half.dynamics.latency[1], int)
    assert half.dynamics.mass == (1.0, 1.0)
    assert half.perception.contrast == pytest.approx((0.85, 1.15))
    assert half.perception.lidar_noise == pytest.approx((0.0, 0.02))
    assert half.reward.progress == pytest.approx((0.75, 1.25))
    assert half.reward.wall == (1.0, 1.0)
    assert half.reward.noise == pytest.approx(0.1) and half.reward.noise_clip == 1.5
    assert (half.mode, half.resample, half.every_k) == ("sample", "every_k", 4)
    double = cfg.scaled(2.0)
    assert double.dynamics.friction == pytest.approx((0.2, 1.4))
    assert double.dynamics.latency == (0, 6)
    assert double.reward.noise == pytest.approx(0.4)
    third = cfg.scaled(1 / 3)
    assert third.dynamics.latency == (0, 1)
    with pytest.raises(UncertaintyError, match=r"^scale must be >= 0, got -0.1$"):
        cfg.scaled(-0.1)


def test_to_dict_is_the_whole_config_as_plain_data() -> None:
    """Every field, groups as dicts of their fields, the perturbation as a plain dict."""
    cfg = UncertaintyConfig(
        mode="fixed",
        dynamics=DynamicsBounds(friction=(0.6, 1.2)),
        episode=EpisodeRandomisation(start="random", tracks=("oval",)),
        perturbation={"friction": 0.7, "latency": [1, 2]},
    )
    out = cfg.to_dict()
    assert out == {
        "mode": "fixed",
        "resample": "episode",
        "every_k": 10,
        "dynamics": {
            "friction": (0.6, 1.2),
            "mass": (1.0, 1.0),
            "motor": (1.0, 1.0),
            "steer_gain": (1.0, 1.0),
            "steer_offset": (0.0, 0.0),
            "latency": (0, 0),
            "action_noise": (0.0, 0.0),
        },
        "perception": {
            "lidar_noise": (0.0, 0.0),
            "lidar_dropout": (0.0, 0.0),
            "brightness": (0.0, 0.0),
            "contrast": (1.0, 1.0),
            "hue": (0.0, 0.0),
            "image_noise": (0.0, 0.0),
            "shift": (0.0, 0.0),
            "shadow": (0.0, 0.0),
        },
        "reward": {
            "noise": 0.0,
            "noise_clip": 2.0,
            "progress": (1.0, 1.0),
            "off_track": (1.0, 1.0),
            "wall": (1.0, 1.0),
            "collision": (1.0, 1.0),
            "overtake": (1.0, 1.0),
        },
        "episode": {
            "start": "random",
            "start_step": 0.05,
            "direction": "forward",
            "tracks": ("oval",),
        },
        "nature_acts": "reset",
        "nature_rate": None,
        "perturbation": {"friction": 0.7, "latency": [1, 2]},
        "edge_share": 0.0,
    }
    assert type(out["perturbation"]) is dict


def test_default_config_natures_act_every_step_at_ten_percent() -> None:
    """The default robust set; adversarial natures act every step, 10 % per step."""
    adv = default_config("adversarial")
    assert (adv.mode, adv.nature_acts, adv.nature_rate) == ("adversarial", "step", 0.1)
    assert adv.dynamics == DEFAULT_DYNAMICS
    assert adv.free_names == DYNAMICS_FREE
    latched = default_config("adversarial", nature_acts="reset", nature_rate=None)
    assert (latched.nature_acts, latched.nature_rate) == ("reset", None)
    sample = default_config("sample", resample="step")
    assert (sample.mode, sample.resample, sample.nature_acts, sample.nature_rate) == (
        "sample",
        "step",
        "reset",
        None,
    )
    assert sample.dynamics == DEFAULT_DYNAMICS


# ---- perturbations -----------------------------------------------------------------------------


def test_from_mapping_sets_cars_and_leaves_the_rest_nominal() -> None:
    """One value for every car or one per car; the unnamed parameters stay nominal."""
    p = Perturbation.from_mapping({"friction": [0.7, 1.1, 0.9], "latency": 2, "hue": 0.25}, 3)
    assert p.column("friction").tolist() == [0.7, 1.1, 0.9]
    assert p.column("latency").tolist() == [2.0, 2.0, 2.0]
    car = p.car(1)
    assert car == {**Perturbation.nominal(1).car(0), "friction": 1.1, "latency": 2, "hue": 0.25}
    assert type(car["latency"]) is int and type(car["friction"]) is float
    np.testing.assert_array_equal(Perturbation.nominal(2).values, np.tile(nominal_values(), (2, 1)))
    assert Perturbation.from_mapping({}, 2).values.shape == (2, P)


@pytest.mark.parametrize(
    ("mapping", "message"),
    [
        ([("friction", 1.0)], "a perturbation is a mapping of parameter names to values"),
        ({"grip": 1.0}, "unknown perturbation parameter 'grip'"),
        ({"friction": [1.0]}, "friction needs one value per car (2), got (1,)"),
        ({"mass": [1.0, 1.0, 1.0]}, "mass needs one value per car (2), got (3,)"),
        ({"mass": [[1.0, 1.0], [1.0, 1.0]]}, "mass must be a finite number or one per car"),
        ({"motor": float("nan")}, "motor must be a finite number or one per car"),
        ({"motor": [1.0, float("inf")]}, "motor must be a finite number or one per car"),
        # JSON-shaped junk in reset(options={"perturbation": ...}) from someone who read
        # from_mapping: a word, null, an object, a list with a word in it.
        ({"friction": "fast"}, "friction must be a finite number or one per car"),
        ({"mass": None}, "mass must be a finite number or one per car"),
        ({"motor": {}}, "motor must be a finite number or one per car"),
        ({"latency": [1, "two"]}, "latency must be a finite number or one per car"),
        ({"friction": [1.0, 0.0]}, "friction in the perturbation must be positive"),
        ({"latency": 1.5}, f"latency in the perturbation must be whole steps in 0..{MAX_LATENCY}"),
        ({"latency": 11}, f"latency in the perturbation must be whole steps in 0..{MAX_LATENCY}"),
        ({"shadow": 1.5}, "shadow in the perturbation must be in [0, 1]"),
        ({"shift": -1.0}, "shift in the perturbation must be >= 0"),
    ],
)
def test_from_mapping_refuses_what_the_simulator_cannot_take(mapping: Any, message: str) -> None:
    """Each bad perturbation (a reset option from a user) gets its own exact message."""
    with pytest.raises(UncertaintyError, match=f"^{re.escape(message)}$"):
        Perturbation.from_mapping(mapping, 2)


def test_scales_and_weights_are_the_right_columns() -> None:
    """The simulator's multipliers (copies) and the five reward weights in RACING_TERMS order."""
    p = Perturbation.from_mapping(
        {
            "friction": [0.7, 0.8],
            "mass": [1.1, 1.2],
            "motor": [0.9, 0.95],
            "steer_gain": [1.05, 0.85],
            "steer_offset": [0.01, -0.02],
            "w_progress": 1.5,
            "w_off_track": 0.5,
            "w_wall": 2.0,
            "w_collision": 0.25,
            "w_overtake": 3.0,
        },
        2,
    )
    sc = p.scales()
    assert isinstance(sc, CarScales)
    assert sc.friction.tolist() == [0.7, 0.8] and sc.mass.tolist() == [1.1, 1.2]
    assert sc.motor.tolist() == [0.9, 0.95] and sc.steer_gain.tolist() == [1.05, 0.85]
    assert sc.steer_offset.tolist() == [0.01, -0.02]
    sc.friction[0] = 9.0  # the scales are the simulator's own copies
    assert p.column("friction")[0] == 0.7
    assert p.weights().tolist() == [[1.5, 0.5, 2.0, 0.25, 3.0]] * 2


# ---- draws -------------------------------------------------------------------------------------

BOX = UncertaintyConfig(
    mode="sample",
    dynamics=DynamicsBounds(friction=(0.6, 1.2), latency=(1, 3), steer_offset=(-0.05, 0.05)),
    perception=PerceptionBounds(lidar_dropout=(0.0, 0.2)),
    reward=RewardBounds(noise=0.1, noise_clip=2.0, collision=(0.5, 2.0)),
)


def test_draws_fill_the_box_and_nothing_else() -> None:
    """Uniform inside every interval, latency whole steps lo..hi inclusive, fixed ones exact."""
    values = sample_values(BOX, np.random.default_rng(0), (500, 2))
    assert values.shape == (500, 2, P)
    flat = values.reshape(-1, P)
    assert np.all(flat >= BOX.lows) and np.all(flat <= BOX.highs)
    fixed = [k for k in range(P) if k not in BOX.free]
    np.testing.assert_array_equal(
        flat[:, fixed], np.broadcast_to(BOX.lows[fixed], (1000, len(fixed)))
    )
    assert sorted(set(flat[:, LATENCY].tolist())) == [1.0, 2.0, 3.0]
    # Each continuous interval is covered (uniform: mean at the middle, near both ends).
    for name in ("friction", "steer_offset", "lidar_dropout", "w_collision"):
        k, lo, hi = INDEX[name], BOX.lows[INDEX[name]], BOX.highs[INDEX[name]]
        col = flat[:, k]
        assert col.min() < lo + 0.01 * (hi - lo) and col.max() > hi - 0.01 * (hi - lo), name
        assert abs(col.mean() - (lo + hi) / 2) < 0.05 * (hi - lo), name
    # Cars and parameters are independent draws.
    assert not np.array_equal(values[:, 0, FRICTION], values[:, 1, FRICTION])
    assert abs(np.corrcoef(flat[:, FRICTION], flat[:, INDEX["w_collision"]])[0, 1]) < 0.1


def test_the_corner_weighted_sampler_puts_the_given_share_on_the_ends() -> None:
    """``edge_share``: each value is an interval end with that probability (low and high as
    likely), the rest uniform inside; latency ends are whole steps; the reward noise stays
    the truncated Gaussian; 0 is the uniform sampler's stream exactly; 1 is the box's corners."""
    n = 20_000
    uniform = sample_values(BOX, np.random.default_rng(5), (n,))
    off = sample_values(dataclasses.replace(BOX, edge_share=0.0), np.random.default_rng(5), (n,))
    np.testing.assert_array_equal(uniform, off)
    half = sample_values(dataclasses.replace(BOX, edge_share=0.5), np.random.default_rng(5), (n,))
    assert np.all(half >= BOX.lows) and np.all(half <= BOX.highs)
    for name in ("friction", "steer_offset", "lidar_dropout", "w_collision"):
        k = INDEX[name]
        at_lo = np.mean(half[:, k] == BOX.lows[k])
        at_hi = np.mean(half[:, k] == BOX.highs[k])
        assert abs(at_lo - 0.25) < 0.02 and abs(at_hi - 0.25) < 0.02, name
        assert np.mean(uniform[:, k] == BOX.lows[k]) < 0.001, name  # uniform: no atoms
    # Latency 1..3: an end w.p. 1/2, else uniform over the three steps.
    lat = half[:, LATENCY]
    assert set(lat.tolist()) == {1.0, 2.0, 3.0}
    assert abs(np.mean(lat == 3.0) - (0.25 + 0.5 / 3)) < 0.02
    assert abs(np.mean(lat == 2.0) - 0.5 / 3) < 0.02
    # Several bad values at once (lowest grip, longest latency) are drawn far more often.
    corner = (half[:, FRICTION] == BOX.lows[FRICTION]) & (lat == 3.0)
    assert abs(corner.mean() - 0.25 * (0.25 + 0.5 / 3)) < 0.02
    noise = half[:, REWARD_NOISE]
    clip = BOX.reward.noise * BOX.reward.noise_clip
    assert np.all(np.abs(noise) < clip) and abs(noise.mean()) < 0.005  # no atoms at ±c·λ
    corners = sample_values(dataclasses.replace(BOX, edge_share=1.0), np.random.default_rng(1), 500)
    for k in (k for k in BOX.free if k != REWARD_NOISE):
        assert set(corners[:, k].tolist()) <= {BOX.lows[k], BOX.highs[k]}, PARAM_NAMES[k]
    assert dataclasses.replace(BOX, edge_share=0.5).scaled(0.5).edge_share == 0.5


def test_same_seed_same_draws_and_an_int_shape_is_one_race() -> None:
    """A seeded generator gives the same draws again; ``n_cars`` equals ``(n_cars,)``."""
    a = sample_values(BOX, np.random.default_rng(7), 4)
    b = sample_values(BOX, np.random.default_rng(7), (4,))
    c = sample_values(BOX, np.random.default_rng(8), 4)
    assert a.shape == (4, P)
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)
    np.testing.assert_array_equal(
        reward_noise(BOX, np.random.default_rng(3), 5),
        reward_noise(BOX, np.random.default_rng(3), (5,)),
    )


def test_reward_noise_is_a_centred_gaussian_truncated_at_clip_lambda() -> None:
    """N(0, λ) cut at ±c·λ by rejection: inside the cut, centred, λ-scaled; zeros when λ=0."""
    zero = reward_noise(UncertaintyConfig(), np.random.default_rng(0), (3, 2))
    assert zero.shape == (3, 2) and not zero.any()
    unit = reward_noise(
        UncertaintyConfig(reward=RewardBounds(noise=1.0)), np.random.default_rng(0), 1000
    )
    assert np.all(np.abs(unit) <= 2.0) and unit.std() == pytest.approx(0.8796, rel=0.1)
    lam = 0.4
    # A tight cut (0.5 λ) makes most draws rejections: every kept one is still N(0, λ).
    tight = UncertaintyConfig(reward=RewardBounds(noise=lam, noise_clip=0.5))
    out = reward_noise(tight, np.random.default_rng(1), 40_000)
    assert out.shape == (40_000,) and np.all(np.abs(out) <= 0.5 * lam)
    assert abs(out.mean()) < 0.004
    assert out.max() > 0.49 * lam and out.min() < -0.49 * lam
    # N(0, λ) restricted to ±0.5 λ: std 0.2871 λ (a centred unit normal cut at ±0.5).
    assert out.std() == pytest.approx(0.2871 * lam, rel=0.02)
    # The default cut (2 λ): std 0.8796 λ.
    wide = reward_noise(
        UncertaintyConfig(reward=RewardBounds(noise=lam)), np.random.default_rng(2), 40_000
    )
    assert np.all(np.abs(wide) <= 2 * lam) and wide.max() > 1.9 * lam
    assert wide.std() == pytest.approx(0.8796 * lam, rel=0.02)


# ---- nature's map ------------------------------------------------------------------------------

NATURE = UncertaintyConfig(
    mode="adversarial",
    dynamics=DynamicsBounds(friction=(0.6, 1.2), latency=(0, 4)),
    reward=RewardBounds(noise=0.25, noise_clip=2.0),
)


def test_nature_map_edges_midpoint_and_clipping_exactly() -> None:
    """-1 is lo, +1 is hi, 0 the middle; beyond ±1 and NaN clip to the edges and middle."""
    start = np.tile(nominal_values(), (4, 1))
    act = np.array([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0], [0.0, 0.5, -0.5], [-3.0, np.nan, 2.0]])
    out = nature_values(NATURE, act, start)
    cols = [FRICTION, LATENCY, REWARD_NOISE]
    np.testing.assert_allclose(
        out[:, cols],
        [[0.6, 0.0, -0.5], [1.2, 4.0, 0.5], [0.9, 3.0, -0.25], [0.6, 2.0, 0.5]],
        rtol=0,
        atol=1e-15,
    )
    others = [k for k in range(P) if k not in cols]
    np.testing.assert_array_equal(out[:, others], start[:, others])
    np.testing.assert_array_equal(start, np.tile(nominal_values(), (4, 1)))  # input untouched
    # Latency stays continuous until applied; the inverse map recovers the clipped action.
    assert out[2, LATENCY] == 3.0 and nature_values(NATURE, np.array([0.1, 0.1, 0.1]), start[0])[
        LATENCY
    ] == pytest.approx(2.2)
    np.testing.assert_allclose(
        normalised(NATURE, out), np.clip(np.nan_to_num(act), -1, 1), rtol=0, atol=1e-12
    )


def test_nature_rate_limits_each_move_both_ways() -> None:
    """With a rate r each call moves at most r·(hi − lo) towards the target, up or down."""
    at_lo = nature_values(NATURE, -np.ones(3), nominal_values())
    at_hi = nature_values(NATURE, np.ones(3), nominal_values())
    up = nature_values(NATURE, np.ones(3), at_lo, rate=0.25)
    down = nature_values(NATURE, -np.ones(3), at_hi, rate=0.25)
    np.testing.assert_allclose(up[[FRICTION, LATENCY, REWARD_NOISE]], [0.75, 1.0, -0.25])
    np.testing.assert_allclose(down[[FRICTION, LATENCY, REWARD_NOISE]], [1.05, 3.0, 0.25])
    # A target within one step is reached exactly (the free map's value, to the last bit);
    # rate 1 is a free move.
    act = np.array([-0.9, -0.5, 0.3])
    near = nature_values(NATURE, act, at_lo, rate=0.25)
    far = nature_values(NATURE, act, at_lo, rate=1.0)
    assert near[FRICTION] == far[FRICTION] == 0.6 + 0.5 * (1 - 0.9) * (1.2 - 0.6)
    np.testing.assert_array_equal(nature_values(NATURE, np.ones(3), at_lo, rate=1.0), at_hi)
    # Back to an edge from anywhere inside the box within reach: exactly the edge.
    rng = np.random.default_rng(0)
    starts = nature_values(
        NATURE, rng.uniform(-1, -0.6, (200, 3)), np.tile(nominal_values(), (200, 1))
    )
    for start in starts:
        back = nature_values(NATURE, -np.ones(3), start, rate=0.25)
        assert back[FRICTION] == 0.6 and back[LATENCY] == 0.0 and back[REWARD_NOISE] == -0.5


def test_infinite_actions_clip_to_the_edges_without_overflow() -> None:
    """±inf (a diverged policy) maps to the edges like ±1, with no floating-point warning
    (the latency interval, 4 wide, would overflow an unclipped 1.8e308)."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        low = nature_values(NATURE, np.array([-np.inf, -np.inf, -np.inf]), nominal_values())
        high = nature_values(NATURE, np.array([np.inf, np.inf, np.inf]), nominal_values())
    assert low[[FRICTION, LATENCY, REWARD_NOISE]].tolist() == [0.6, 0.0, -0.5]
    assert high[[FRICTION, LATENCY, REWARD_NOISE]].tolist() == [1.2, 4.0, 0.5]


def test_a_rate_limited_move_from_outside_the_box_lands_on_its_edge() -> None:
    """A start outside the box (nominal friction 1 below a (1.1, 1.3) box, or above a
    (0.5, 0.9) one) lands on the box's edge, however small the rate."""
    below = UncertaintyConfig(mode="adversarial", dynamics=DynamicsBounds(friction=(1.1, 1.3)))
    assert nature_values(below, np.array([1.0]), nominal_values(), rate=0.1)[FRICTION] == 1.1
    assert nature_values(below, np.array([-1.0]), nominal_values(), rate=0.1)[FRICTION] == 1.1
    above = UncertaintyConfig(mode="adversarial", dynamics=DynamicsBounds(friction=(0.5, 0.9)))
    assert nature_values(above, np.array([-1.0]), nominal_values(), rate=0.1)[FRICTION] == 0.9
    assert nature_values(above, np.array([1.0]), nominal_values(), rate=0.1)[FRICTION] == 0.9


def test_float32_actions_map_in_float64() -> None:
    """SB3 hands nature float32 actions and may hold float32 values: the map is computed,
    and returned, in float64 (the same numbers as from float64 inputs)."""
    act32 = np.array([0.1, -0.3, 0.7], np.float32)
    cur32 = nominal_values().astype(np.float32)
    out = nature_values(NATURE, act32, cur32, rate=0.5)
    assert out.dtype == np.float64
    np.testing.assert_array_equal(
        out, nature_values(NATURE, act32.astype(np.float64), nominal_values(), rate=0.5)
    )
    x = float(act32[0])
    assert out[FRICTION] == 0.6 + 0.5 * (x + 1.0) * (1.2 - 0.6)


def test_applied_rounds_latency_only_and_copies() -> None:
    """Latency to whole control steps (half to even), every other value as it was."""
    raw = np.tile(nominal_values(), (3, 1))
    raw[:, LATENCY] = [0.4, 1.5, 2.6]
    raw[:, FRICTION] = [0.61, 0.72, 0.83]
    out = applied(raw)
    assert out.dtype == np.float64 and applied(raw.astype(np.float32)).dtype == np.float64
    assert out[:, LATENCY].tolist() == [0.0, 2.0, 3.0]
    assert out[:, FRICTION].tolist() == [0.61, 0.72, 0.83]
    assert raw[:, LATENCY].tolist() == [0.4, 1.5, 2.6]


def test_normalised_is_clipped_to_the_unit_box() -> None:
    """Values outside the box map to ±1, not beyond (what the nature observation holds)."""
    values = np.tile(nominal_values(), (3, 1))
    values[:, FRICTION] = [0.3, 0.75, 2.0]
    values[:, LATENCY] = [0.0, 1.0, 4.0]
    out = normalised(NATURE, values)
    np.testing.assert_allclose(out[:, :2], [[-1.0, -1.0], [-0.5, -0.5], [1.0, 1.0]])


# ---- when values change: PerturbationState -----------------------------------------------------


def test_state_starts_at_nominal_pulled_into_the_box() -> None:
    """Before any episode (and in nominal/adversarial modes) values are nominal clipped in."""
    cfg = UncertaintyConfig(
        mode="adversarial", dynamics=DynamicsBounds(friction=(1.1, 1.3), mass=(0.5, 0.9))
    )
    state = PerturbationState(cfg, (2, 3))
    assert state.raw.shape == state.values.shape == (2, 3, P)
    assert np.all(state.values[..., FRICTION] == 1.1) and np.all(
        state.values[..., INDEX["mass"]] == 0.9
    )
    state.raw[..., FRICTION] = 1.2
    state.raw[..., INDEX["mass"]] = 0.6
    state.start(np.random.default_rng(0))
    assert np.all(state.values[..., FRICTION] == 1.1)  # nominal 1 below the box
    assert np.all(state.values[..., INDEX["mass"]] == 0.9)  # and above it
    # A nominal state never moves.
    nominal = PerturbationState(UncertaintyConfig(), (1, 2))
    nominal.start(np.random.default_rng(0))
    assert nominal.advance(np.random.default_rng(0), 5, np.zeros((1, 2, 0))) is False
    np.testing.assert_array_equal(nominal.values, np.tile(nominal_values(), (1, 2, 1)))


def test_state_start_draws_only_for_the_masked_races() -> None:
    """``start(envs=mask)`` redraws the races in the mask (one alone too), the rest keep."""
    rng = np.random.default_rng(0)
    state = PerturbationState(BOX, (3, 2))
    state.start(rng)
    before = state.values.copy()
    state.start(rng, envs=np.array([False, True, False]))
    np.testing.assert_array_equal(state.values[[0, 2]], before[[0, 2]])
    assert not np.array_equal(state.values[1, :, FRICTION], before[1, :, FRICTION])
    assert np.all(state.values[1] >= BOX.lows) and np.all(state.values[1] <= BOX.highs)
    same = state.values.copy()
    state.start(rng, envs=np.zeros(3, dtype=bool))
    np.testing.assert_array_equal(state.values, same)
    # A 0/1 list is a mask too (not race indices).
    state.start(rng, envs=[0, 0, 1])  # type: ignore[arg-type]
    np.testing.assert_array_equal(state.values[:2], same[:2])
    assert not np.array_equal(state.values[2, :, FRICTION], same[2, :, FRICTION])


def test_state_fixed_takes_the_given_then_the_configs_perturbation() -> None:
    """``fixed``: a mapping or a Perturbation given at reset, else the config's, else nominal."""
    rng = np.random.default_rng(0)
    cfg = UncertaintyConfig(mode="fixed", perturbation={"friction": 0.7, "latency": [1, 2]})
    state = PerturbationState(cfg, (2, 2))
    state.start(rng)
    assert state.values[..., FRICTION].tolist() == [[0.7, 0.7], [0.7, 0.7]]
    assert state.values[..., LATENCY].tolist() == [[1, 2], [1, 2]]
    given = Perturbation.from_mapping({"mass": [1.1, 0.9]}, 2)
    state.start(rng, envs=np.array([True, False]), given=given)
    np.testing.assert_array_equal(state.values[0], given.values)
    assert state.values[1, :, LATENCY].tolist() == [1, 2]
    bare = PerturbationState(UncertaintyConfig(mode="fixed"), (1, 2))
    bare.start(rng)
    np.testing.assert_array_equal(bare.values[0], Perturbation.nominal(2).values)
    with pytest.raises(UncertaintyError, match=r"^reset option 'perturbation' needs uncertainty"):
        PerturbationState(BOX, (1, 2)).start(rng, given={"friction": 0.7})


@pytest.mark.parametrize(
    ("resample", "redraws"),
    [
        ("episode", []),
        ("step", [1, 2, 3, 4, 5, 6, 7, 8]),
        ("every_k", [3, 6]),
        ("every_k=1", [1, 2, 3, 4, 5, 6, 7, 8]),
    ],
)
def test_state_resample_boundaries(resample: str, redraws: list[int]) -> None:
    """Steps counted before each step: ``step`` redraws from t=1, ``every_k`` at t=k, 2k…;
    the reward noise is new on every step in every schedule."""
    resample, _, k = resample.partition("=")
    cfg = UncertaintyConfig(
        mode="sample",
        resample=resample,  # type: ignore[arg-type]
        every_k=int(k or 3),
        dynamics=DynamicsBounds(friction=(0.6, 1.2)),
        reward=RewardBounds(noise=0.1),
    )
    rng = np.random.default_rng(4)
    state = PerturbationState(cfg, (1, 2))
    state.start(rng)
    changed, noises = [], [state.values[0, 0, REWARD_NOISE]]
    for t in range(9):
        before = state.values[0, :, FRICTION].copy()
        moved = state.advance(rng, t)
        assert moved == (t in redraws)
        if not np.array_equal(before, state.values[0, :, FRICTION]):
            changed.append(t)
        noises.append(state.values[0, 0, REWARD_NOISE])
    assert changed == redraws
    assert len(set(noises)) == len(noises)


def test_state_resamples_each_race_on_its_own_step_count() -> None:
    """In a batch, only the races whose step count hits the schedule redraw."""
    cfg = UncertaintyConfig(
        "sample",
        "every_k",
        4,
        dynamics=DynamicsBounds(friction=(0.6, 1.2)),
        reward=RewardBounds(noise=0.1),
    )
    rng = np.random.default_rng(5)
    state = PerturbationState(cfg, (4, 1))
    state.start(rng)
    before = state.values.copy()
    assert state.advance(rng, np.array([0, 4, 5, 8])) is True
    assert (state.values[:, 0, FRICTION] != before[:, 0, FRICTION]).tolist() == [
        False,
        True,
        False,
        True,
    ]
    assert np.all(state.values[:, 0, REWARD_NOISE] != before[:, 0, REWARD_NOISE])
    assert state.advance(rng, np.array([1, 5, 6, 9])) is False
    # Drawn once per episode: every race's reward noise is still new on every step.
    once = UncertaintyConfig("sample", dynamics=cfg.dynamics, reward=cfg.reward)
    batch = PerturbationState(once, (3, 2))
    batch.start(rng)
    for t in range(3):
        before = batch.values.copy()
        assert batch.advance(rng, t) is False
        np.testing.assert_array_equal(batch.values[..., FRICTION], before[..., FRICTION])
        assert np.all(batch.values[..., REWARD_NOISE] != before[..., REWARD_NOISE])


def test_state_nature_acts_at_the_first_step_and_then_as_configured() -> None:
    """``reset``: only the t=0 action counts; ``step``: every step, rate-limited after t=0."""
    rng = np.random.default_rng(0)
    k = len(NATURE.free)
    low, high = -np.ones((1, 2, k)), np.ones((1, 2, k))
    latched = PerturbationState(NATURE, (1, 2))
    latched.start(rng)
    assert latched.advance(rng, 0, None) is False  # no nature acted: nominal kept
    assert latched.values[0, :, FRICTION].tolist() == [1.0, 1.0]
    assert latched.advance(rng, 0, low) is True
    assert latched.values[0, :, FRICTION].tolist() == [0.6, 0.6]
    assert latched.advance(rng, 1, high) is False
    assert latched.values[0, :, FRICTION].tolist() == [0.6, 0.6]

    cfg = UncertaintyConfig(
        mode="adversarial",
        dynamics=NATURE.dynamics,
        reward=NATURE.reward,
        nature_acts="step",
        nature_rate=0.25,
    )
    moving = PerturbationState(cfg, (1, 2))
    moving.start(rng)
    assert moving.advance(rng, 0, low, np.array([[True, False]])) is True
    assert moving.values[0, :, FRICTION].tolist() == [0.6, 1.0]  # car 1's nature did not act
    assert moving.advance(rng, 1, high) is True
    np.testing.assert_allclose(moving.values[0, :, FRICTION], [0.75, 1.15])
    np.testing.assert_allclose(moving.raw[0, :, LATENCY], [1.0, 1.0])
    assert moving.values[0, 0, LATENCY] == 1.0
    assert moving.advance(rng, 2, high, np.zeros((1, 2), dtype=bool)) is False
    free = UncertaintyConfig(
        mode="adversarial", dynamics=NATURE.dynamics, nature_acts="step", nature_rate=None
    )
    unlimited = PerturbationState(free, (1, 1))
    unlimited.start(rng)
    unlimited.advance(rng, 0, -np.ones((1, 1, 2)))
    unlimited.advance(rng, 1, np.ones((1, 1, 2)))
    assert unlimited.values[0, 0, FRICTION] == 1.2 and unlimited.values[0, 0, LATENCY] == 4.0
    with pytest.raises(
        UncertaintyError, match=r"^nature actions must have shape \(1, 2, 3\), got \(1, 2, 2\)$"
    ):
        moving.advance(rng, 3, np.zeros((1, 2, 2)))
