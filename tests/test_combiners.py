"""Combiners against values computed by hand."""

import numpy as np
import pytest

from layered.combiners import COMBINERS, Gate, ResidualClip, Route

LOW, HIGH = np.array([-2.0, -2.0]), np.array([2.0, 2.0])


def test_registry_holds_both_paper_combiners():
    assert {"residual-clip", "gate"} <= set(COMBINERS.names())
    with pytest.raises(KeyError, match="known: gate, residual-clip"):
        COMBINERS.get("sum")


def test_residual_always_adds():
    assert ResidualClip().route(np.array([5.0, -5.0])) == Route.ADD
    assert ResidualClip().route(np.zeros((3, 2))).tolist() == [Route.ADD] * 3


@pytest.mark.parametrize(("gate", "route"), [(0.01, Route.COMMIT), (0.0, Route.DEFER), (-0.7, Route.DEFER)])
def test_gate_commits_only_when_its_last_output_is_positive(gate, route):
    assert Gate().route(np.array([1.5, -0.3, gate])) == route


def test_routes_and_admissions_over_a_batch_are_those_of_each_row():
    gates = np.array([[1.5, 0.01], [1.5, 0.0], [-1.0, -0.7]])
    assert Gate().route(gates).tolist() == [Route.COMMIT, Route.DEFER, Route.DEFER]
    combiner = ResidualClip(threshold=np.array([0.6, 0.6]))
    above = np.array([[1.0, -1.0], [1.0, -1.0], [1.8, 1.8]])
    contributions = np.array([[0.5, -0.1], [0.7, -0.1], [3.0, 3.0]])
    assert combiner.admit(above, contributions, LOW, HIGH).tolist() == [[0.0, 0.0], [0.7, -0.1], [0.0, 0.0]]


def test_combiners_describe_themselves():
    assert (ResidualClip.gate_dims, ResidualClip.residual_below, ResidualClip.thresholded) == (0, True, True)
    assert (Gate.gate_dims, Gate.residual_below, Gate.thresholded) == (1, False, False)
    assert ResidualClip.encoding is None and Gate.encoding is not None
    assert Gate.encoding.value(True) == 1.0 and Gate.encoding.value(False) == -1.0
    assert bool(Gate.encoding.commits(0.01)) and not bool(Gate.encoding.commits(0.0))


def test_a_combiner_written_to_json_reads_back_the_same():
    from layered.combiners import combiner_from_json

    combiner = ResidualClip(threshold=np.array([0.6, 0.25], np.float32), per_dimension=True)
    data = combiner.to_json()
    assert data == {"kind": "residual-clip", "per_dimension": True, "threshold": [0.6000000238418579, 0.25]}
    back = combiner_from_json(data)
    assert type(back) is ResidualClip and back.per_dimension and back.threshold.tolist() == combiner.threshold.tolist()


def test_residual_without_threshold_admits_everything():
    c = np.array([0.01, -0.02])
    assert np.array_equal(ResidualClip().admit(np.array([1.0, 1.0]), c, LOW, HIGH), c)


def test_threshold_all_dimensions():
    combiner = ResidualClip(threshold=np.array([0.6, 0.6]))
    above = np.array([1.0, -1.0])
    # effects |clip(1.5)-1| = 0.5 and |clip(-1.1)+1| = 0.1: both below 0.6 -> dropped
    assert np.array_equal(combiner.admit(above, np.array([0.5, -0.1]), LOW, HIGH), [0.0, 0.0])
    # one effect of 0.7 >= 0.6 keeps the whole contribution
    assert np.array_equal(combiner.admit(above, np.array([0.7, -0.1]), LOW, HIGH), [0.7, -0.1])


def test_threshold_measures_the_effect_after_clipping():
    combiner = ResidualClip(threshold=np.array([0.6, 0.6]))
    # above is 1.8: adding 3.0 clips to 2.0, an effect of only 0.2 -> dropped
    assert np.array_equal(combiner.admit(np.array([1.8, 1.8]), np.array([3.0, 3.0]), LOW, HIGH), [0.0, 0.0])


def test_threshold_per_dimension():
    combiner = ResidualClip(threshold=np.array([0.6, 0.6]), per_dimension=True)
    out = combiner.admit(np.array([0.0, 0.0]), np.array([0.7, -0.1]), LOW, HIGH)
    assert np.array_equal(out, [0.7, 0.0])


def test_a_thresholded_contribution_keeps_its_dtype():
    """The action stays float32 through a threshold (the float64 threshold and zeros do not leak into it)."""
    combiner = ResidualClip(threshold=np.array([0.6, 0.6]))
    out = combiner.admit(np.zeros(2, np.float32), np.array([0.7, -0.1], np.float32), LOW, HIGH)
    assert out.dtype == np.float32 and np.array_equal(out, np.array([0.7, -0.1], np.float32))


def test_an_effect_exactly_at_the_threshold_is_kept():
    """The paper drops corrections *smaller* than the threshold: one of exactly the threshold stays."""
    combiner = ResidualClip(threshold=np.array([0.5, 0.5]))
    assert np.array_equal(combiner.admit(np.array([0.0, 0.0]), np.array([0.5, 0.0]), LOW, HIGH), [0.5, 0.0])
    per_dimension = ResidualClip(threshold=np.array([0.5, 0.5]), per_dimension=True)
    assert np.array_equal(per_dimension.admit(np.array([0.0, 0.0]), np.array([0.5, 0.25]), LOW, HIGH), [0.5, 0.0])


@pytest.mark.parametrize("name", COMBINERS.names())
def test_a_combiner_without_threshold_round_trips_through_json(name):
    from layered.combiners import combiner_from_json

    combiner = COMBINERS.get(name)()
    data = combiner.to_json()
    assert data["threshold"] is None
    back = combiner_from_json(data)
    assert type(back) is type(combiner) and back.threshold is None


def test_a_threshold_round_trips_through_json_as_float32():
    from layered.combiners import combiner_from_json

    assert combiner_from_json(ResidualClip(np.array([0.5])).to_json()).threshold.dtype == np.float32
