"""Training orders give the phases the paper describes, for any depth."""

from pathlib import Path

import pytest

from layered.orders import ORDERS, Phase, stack_weights
from layered.recipe import load_recipe
from layered.runs import untrained_gates
from layered.schema import PhaseConfig

NAMES = ["slow", "mid", "fast"]
ROOT = Path(__file__).resolve().parent.parent


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


PENDULUM = Path(__file__).parent.parent / "recipes" / "pendulum"


@pytest.mark.parametrize("name, select, weights, expected", [
    # TLA-C: the fast layer learns last, over the slow layer that its phase was handed
    ("tla-c.toml", "best", "final", {"slow": "best", "fast": "final"}),
    ("tla-c.toml", "final", "best", {"slow": "final", "fast": "best"}),
    ("tla-c.toml", "best", None, {"slow": "best", "fast": "best"}),
    # TLA-O: the slow gate layer learns last, over the fast layer
    ("tla-o.toml", "best", "final", {"slow": "final", "fast": "best"}),
    # one phase: every layer learns in the last
    ("tla-joint.toml", "best", "final", {"slow": "final", "fast": "final"}),
])
def test_the_stack_of_a_run_is_its_last_phases_weights_over_what_earlier_phases_handed_on(name, select, weights,
                                                                                          expected):
    recipe = load_recipe(PENDULUM / name, [f"train.select={select}"])
    assert stack_weights(recipe, weights) == expected


@pytest.mark.parametrize("recipe, overrides, warned", [
    ("pendulum/tla-o.toml", [], False),  # fast-to-slow: the gate learns over the trained fast layer
    ("pendulum/tla-joint.toml", [], False),  # both learn at once
    ("research/pendulum-gate-over-residual-3.toml", [], False),  # the gate learns last, over the others
    ("pendulum/tla-o.toml", ["train.order=slow-to-fast"], True),  # the gate learns alone, then routes the fast layer
    ("pendulum/tla-o.toml", ["train.order=explicit", 'train.phases=[{learn=["slow"], active=["slow"]}, '
                             '{learn=["fast"]}, {learn=["slow"]}]'], False),  # ... and again over it
    ("pendulum/tla-c.toml", [], False),  # no gate
])
def test_a_gate_that_never_learns_over_a_layer_below_it_is_named(recipe, overrides, warned):
    warnings = untrained_gates(load_recipe(ROOT / "recipes" / recipe, overrides))
    assert warnings == (["layer 'slow' gates the layers below it ('gate') from phase 1 on, but learns in no phase "
                         "where one of them is present: its gate output, unused while it learns alone, routes them "
                         "by its initial weights (train it over a layer below: order \"fast-to-slow\", \"joint\" or "
                         "explicit phases)"] if warned else [])
