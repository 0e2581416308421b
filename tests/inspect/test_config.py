"""InspectConfig validation and the verdict names."""

import pytest

from smdinspect.errors import InputError
from smdinspect.inspect import InspectConfig, Verdict
from smdinspect.synth._board_scene import DEFECTS


def test_verdicts_are_the_simulator_classes_plus_unreliable():
    assert {v.value for v in Verdict} == set(DEFECTS) | {"unreliable"}
    assert not Verdict.OK.is_defect and not Verdict.UNRELIABLE.is_defect
    assert all(Verdict(c).is_defect for c in DEFECTS if c != "ok")


@pytest.mark.parametrize("kwargs, match", [
    ({"min_reliable_fraction": 1.5}, "min_reliable_fraction must be <= 1"),
    ({"height_percentile": 20}, "height_percentile must be >= 50"),
    ({"bridge_height_mm": 0}, "bridge_height_mm must be > 0"),
    ({"body_margin_mm": float("nan")}, "body_margin_mm must be a finite number"),
    ({"fillet_model": "cubic"}, "fillet_model must be one of meniscus, percentile"),
    ({"icp": "yes"}, "icp must be true or false"),
    ({"seed": 1.5}, "seed must be an integer"),
])
def test_bad_settings_are_named(kwargs, match):
    with pytest.raises(InputError, match=match):
        InspectConfig(**kwargs)


def test_from_dict_round_trip_and_unknown_keys():
    cfg = InspectConfig(min_reliable_fraction=0.3, fillet_model="percentile")
    again = InspectConfig.from_dict(cfg.to_dict())
    assert again == cfg and again.fillet_model.value == "percentile"
    with pytest.raises(InputError, match="unknown inspect setting.*colour"):
        InspectConfig.from_dict({"colour": 1})
