"""Car presets: names resolve, unknown names fail clearly, DeepRacer has its published figures."""

from __future__ import annotations

import math

import pytest

from arena.cars import CAR_PRESETS, CarError, car_name, car_params
from arena.sim import CarParams
from tracks.errors import SlipstreamError


def test_f1tenth_is_todays_default_car() -> None:
    assert car_params("f1tenth") == CarParams()
    assert car_params(" F1TENTH ") == CarParams()


def test_deepracer_matches_published_figures() -> None:
    # Figures from the DeepRacer URDF (aws-deepracer/aws-deepracer deepracer_description) and the
    # AWS DeepRacer Developer Guide's action space (steering ±30°, speed up to 4 m/s).
    car = car_params("deepracer")
    assert car.wheelbase == pytest.approx(0.164, abs=1e-3)
    assert car.track_width == pytest.approx(0.162, abs=1e-3)
    assert math.degrees(car.max_steer) == pytest.approx(30.0)
    assert 3.5 < car.top_speed <= 4.0
    assert car.length < CarParams().length and car.width < CarParams().width
    # full-lock radius of the centre line: tighter than DeepRacer tracks' tightest bends (~0.6 m)
    assert car.wheelbase / math.tan(car.max_steer) < 0.35


def test_carparams_passes_through() -> None:
    custom = CarParams(mass=4.0)
    assert car_params(custom) is custom
    assert car_name(custom) is None
    assert car_name(CAR_PRESETS["deepracer"]) == "deepracer"


@pytest.mark.parametrize("bad", ["f1ten", "", "deep racer"])
def test_unknown_name_is_a_clear_error(bad: str) -> None:
    with pytest.raises(CarError, match="unknown car") as info:
        car_params(bad)
    assert "f1tenth" in str(info.value) and "deepracer" in str(info.value)
    assert isinstance(info.value, SlipstreamError)


def test_wrong_type_is_a_clear_error() -> None:
    with pytest.raises(CarError, match="preset name or CarParams"):
        car_params(3)  # type: ignore[arg-type]
