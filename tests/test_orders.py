"""Training orders give the phases the paper describes, for any depth."""

from layered.orders import ORDERS, Phase
from layered.schema import PhaseConfig

NAMES = ["slow", "mid", "fast"]


def test_slow_to_fast_trains_each_layer_on_top_of_the_frozen_slower_ones():
    assert ORDERS.get("slow-to-fast")(NAMES, []) == [
        Phase(("slow",), ("slow",)), Phase(("mid",), ("slow", "mid")), Phase(("fast",), ("slow", "mid", "fast")),
    ]


def test_fast_to_slow_starts_with_the_fastest_alone():
    assert ORDERS.get("fast-to-slow")(NAMES, []) == [
        Phase(("fast",), ("fast",)), Phase(("mid",), ("mid", "fast")), Phase(("slow",), ("slow", "mid", "fast")),
    ]


def test_one_layer_is_one_phase_either_way():
    assert ORDERS.get("slow-to-fast")(["a"], []) == ORDERS.get("fast-to-slow")(["a"], []) == [Phase(("a",), ("a",))]


def test_explicit_phases_default_to_learners_plus_everything_trained_before():
    phases = [PhaseConfig(learn=["fast"]), PhaseConfig(learn=["slow", "mid"], steps=10),
              PhaseConfig(learn=["mid"], active=["mid"])]
    assert ORDERS.get("explicit")(NAMES, phases) == [
        Phase(("fast",), ("fast",)),
        Phase(("slow", "mid"), ("slow", "mid", "fast"), steps=10),
        Phase(("mid",), ("mid",)),
    ]


def test_joint_trains_every_layer_at_once():
    assert ORDERS.get("joint")(NAMES, []) == [Phase(("slow", "mid", "fast"), ("slow", "mid", "fast"))]
