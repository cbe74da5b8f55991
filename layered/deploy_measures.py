"""What a deployment measured, per layer and overall: the numbers `layered deploy` prints, draws and writes.

A decision is *missed* when its answer had not come by its deadline (for a layer without delay, the
end of its own base step; with a delay, the start of the step it lands at); a missed decision whose
answer came before its layer decided again took effect late, one whose answer did not was *dropped*.
The *delay seen* of a decision that took effect is the number of base steps from the step it was
decided for to the first step it was in effect: the layer's trained delay (delay x period) when on
time, more when late.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Sequence
from typing import Any

import numpy as np

from layered.deploy import Decision, Episode


def percentiles_ms(seconds: Sequence[float]) -> dict[str, float | None]:
    """The median and 99th percentile of durations, in milliseconds (None for no durations)."""
    if not seconds:
        return {"median": None, "p99": None}
    ms = np.asarray(seconds, np.float64) * 1e3
    return {"median": float(np.median(ms)), "p99": float(np.percentile(ms, 99))}


def layer_measures(decisions: Sequence[Decision], scheduled: int) -> dict[str, Any]:
    """One layer's requests: how many, how fast answered, missed, late, dropped, and the delays seen;
    `scheduled` is the layer's delay in base steps (delay x period), what an answer on time sees."""
    settled = [d for d in decisions if d.missed or d.landed is not None]  # reached the step they were due at
    missed = sum(d.missed for d in settled)
    late = sum(d.missed and d.landed is not None for d in settled)
    seen = Counter(d.landed - d.step for d in settled if d.landed is not None)
    return {
        "requests": len(decisions),
        "answered": sum(d.answered is not None for d in decisions),
        "latency_ms": percentiles_ms([d.latency_s for d in decisions if d.latency_s is not None]),
        "compute_ms": percentiles_ms([d.compute_s for d in decisions if d.compute_s is not None]),
        "to_layer_ms": percentiles_ms([d.to_layer_s for d in decisions if d.to_layer_s is not None]),
        "back_ms": percentiles_ms([d.back_s for d in decisions if d.back_s is not None]),
        "settled": len(settled),
        "missed": missed,
        "miss_rate": missed / len(settled) if settled else 0.0,
        "late": late,
        "dropped": missed - late,
        "asked_unseen": sum(d.unseen for d in decisions),
        "scheduled_delay": scheduled,
        "delay_seen": {str(k): seen[k] for k in sorted(seen)},
        "mean_delay_seen": (sum(k * n for k, n in seen.items()) / sum(seen.values())) if seen else None,
    }


def largest_difference(played: Sequence[np.ndarray], reference: Sequence[np.ndarray]) -> float:
    """The largest |difference| between the executed actions of paired episodes; infinite where an
    episode's length differs from its reference's."""
    largest = 0.0
    for ours, theirs in zip(played, reference, strict=False):
        if ours.shape != theirs.shape:
            return float("inf")
        largest = max(largest, float(np.max(np.abs(ours - theirs), initial=0.0)))
    return largest


def run_measures(episodes: Sequence[Episode], timestep: float) -> dict[str, Any]:
    """Return, steps and pace over deployed episodes: steps per second of wall clock, and how many
    times real time that is (the environment's simulated seconds per wall-clock second)."""
    returns = [e.ret for e in episodes]
    steps = sum(len(e.actions) for e in episodes)
    wall = sum(e.wall_s for e in episodes)
    return {
        "episodes": len(episodes),
        "returns": returns,
        "return_mean": float(np.mean(returns)) if returns else None,
        "return_std": float(np.std(returns)) if returns else None,
        "steps": steps,
        "wall_s": wall,
        "steps_per_s": steps / wall if wall else None,
        "real_time_factor": steps * timestep / wall if wall else None,
    }
