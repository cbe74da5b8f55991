"""Whether two sets of seeds differ: the tests `layered report` puts beside its means and standard deviations.

Two setups of one environment are compared as independent samples of seeds with Welch's t-test, which
does not assume equal variances (as Colas et al., 2018, "How many random seeds?", recommend for RL); the
phases of a stack trained in phases, each against the phase before it, and two setups whose runs share their
trained layers seed by seed (a probe started from another setup's runs' weights), with a paired t-test on the
seeds' differences (the same seed's stack before and after, or the same layers under two settings). Each
comparison gives the difference of the means with its 95% confidence interval and a two-sided p-value, and how
often the first comes out above the second: over every pair of a seed of each (the probability of improvement
of Agarwal et al., 2021), or over the seeds; ties count half. Since a report makes many such tests at once, each
p-value also comes adjusted for all of them by Holm's step-down method, which holds the chance of any false
"p < 0.05" in the report to 5%. A method run in several environments is compared with another across them by
its probability of improvement averaged over the environments, with a stratified-bootstrap interval.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from layered.summary import Run, Setup

LEVEL = 0.95  # of the confidence intervals

MEASURES: tuple[tuple[str, str, str], ...] = (
    ("fresh_best_return_mean", "return, best weights", "{:+.1f}"),
    ("fresh_final_return_mean", "return, final weights", "{:+.1f}"),
    ("return_mean", "return, final evaluation", "{:+.1f}"),
    ("auc", "AUC", "{:+.3f}"),
    ("run_auc", "AUC, whole run", "{:+.3f}"),
    ("fresh_final_repetition", "action repetition, final weights", "{:+.1%}"),
)
"""What setups are compared on (a `results.json` key, its name, the format of a difference), where every run
of both has it; phases are compared on the first two, the fresh-episode returns each phase records. `run_auc`
(the AUC over all of a run's phases and those behind the stack it continued, `layered.summary`) only where one of
the two trained in phases (`phased`): elsewhere it is the AUC."""


@dataclass(frozen=True)
class Comparison:
    """The first sample of seeds against the second."""

    difference: float  # the first's mean less the second's
    low: float  # the difference's confidence interval at LEVEL
    high: float
    p: float  # two-sided p-value of no difference
    above: float  # share of the pairs of a seed of each (paired: of the seeds) in which the first is above
    sizes: tuple[int, int]  # seeds in each


def welch(first: Sequence[float], second: Sequence[float]) -> Comparison | None:
    """Two independent samples (a setup's seeds against another's) by Welch's t-test; None where either has
    fewer than two values (no spread to test against)."""
    a, b = np.asarray(first, np.float64), np.asarray(second, np.float64)
    if len(a) < 2 or len(b) < 2:
        return None
    va, vb = a.var(ddof=1) / len(a), b.var(ddof=1) / len(b)  # each mean's variance
    df = (va + vb) ** 2 / (va**2 / (len(a) - 1) + vb**2 / (len(b) - 1)) if va + vb > 0 else math.inf
    return _t_test(float(a.mean() - b.mean()), math.sqrt(va + vb), df, float(improvement(a, b)),
                   (len(a), len(b)))


def improvement(first: np.ndarray, second: np.ndarray) -> np.ndarray:
    """The share of the pairs of a value of each (along their last axes) in which the first is above, ties half:
    the probability of improvement of Agarwal et al. (2021); one per index of their leading axes."""
    a, b = first[..., :, None], second[..., None, :]
    return np.mean((a > b) + 0.5 * (a == b), axis=(-2, -1))


def paired(first: Sequence[float], second: Sequence[float]) -> Comparison | None:
    """Two samples of the same seeds (`first[k]` and `second[k]` of seed k) by a paired t-test on their
    differences; None for fewer than two seeds."""
    a, b = np.asarray(first, np.float64), np.asarray(second, np.float64)
    if len(a) != len(b):
        raise ValueError(f"paired samples of {len(a)} and {len(b)} values")
    d = a - b
    if len(d) < 2:
        return None
    above = float(np.mean((d > 0) + 0.5 * (d == 0)))
    return _t_test(float(d.mean()), float(d.std(ddof=1)) / math.sqrt(len(d)), len(d) - 1, above, (len(a), len(b)))


def _t_test(difference: float, se: float, df: float, above: float, sizes: tuple[int, int]) -> Comparison:
    """The difference's interval and p-value from its standard error on Student's t with `df` degrees."""
    from scipy import stats  # (imported when a report compares: it is large)

    if se == 0:  # no spread in either sample: the difference is exactly what it is
        return Comparison(difference, difference, difference, 1.0 if difference == 0 else 0.0, above, sizes)
    margin = float(stats.t.ppf(0.5 + LEVEL / 2, df)) * se
    p = float(2 * stats.t.sf(abs(difference) / se, df))
    return Comparison(difference, difference - margin, difference + margin, p, above, sizes)


@dataclass(frozen=True)
class Row:
    """One comparison of a report: what is compared with what, on which measure."""

    env: str
    first: str
    second: str
    measure: str
    fmt: str
    paired: bool
    comparison: Comparison
    p_holm: float = math.nan  # the p-value adjusted for all the report's comparisons (`adjusted`)


def holm(ps: Sequence[float]) -> list[float]:
    """Holm's step-down adjustment of m p-values, in their order: the i-th smallest becomes the largest of
    (m - j + 1) p_(j) over j <= i, at most 1, so that "adjusted p < 0.05" errs in any of the m with
    probability at most 0.05, however the tests depend on one another."""
    out, running = [0.0] * len(ps), 0.0
    for rank, i in enumerate(sorted(range(len(ps)), key=lambda k: ps[k])):
        running = max(running, min(1.0, (len(ps) - rank) * ps[i]))
        out[i] = running
    return out


def adjusted(rows: Sequence[Row]) -> list[Row]:
    """The rows with their p-values adjusted by `holm` for all of them: the family a report tests at once."""
    return [replace(r, p_holm=p) for r, p in zip(rows, holm([r.comparison.p for r in rows]), strict=True)]


def number(value: Any) -> float:
    """A measure's value in a run's results, NaN where the run has none."""
    return float(value) if isinstance(value, int | float) and not isinstance(value, bool) else float("nan")


def _values(runs: Sequence[Run], key: str, phase: int | None = None) -> list[float] | None:
    """Each run's value of `key` (in its last phase's results, or phase `phase`'s); None unless every run has one."""
    found = [number((run.final if phase is None else run.phases[phase]).get(key)) for run in runs]
    return None if any(v != v for v in found) else found


def setup_pairs(setups: Sequence[Setup]) -> Iterator[tuple[Setup, Setup]]:
    """Each finished setup with each listed before it in the same environment and setting (the real-time one or
    not; the paper's baselines come first): what is compared with what, later first."""
    done = [s for s in setups if all(r.finished for r in s.runs)]
    for i, later in enumerate(done):
        yield from ((later, s) for s in done[:i] if (s.env, s.realtime) == (later.env, later.realtime))


def between_setups(setups: Sequence[Setup]) -> list[Row]:
    """Each of `setup_pairs`, on every measure of `MEASURES` that all their runs have: seed by seed where the two
    setups are `paired_seeds`, else as independent samples."""
    rows = []
    for later, earlier in setup_pairs(setups):
        pair = paired_seeds(later, earlier)
        whole = phased((*later.runs, *earlier.runs))
        for key, name, fmt in (m for m in MEASURES if whole or m[0] != "run_auc"):
            a, b = _values(later.runs, key), _values(earlier.runs, key)
            if a is not None and b is not None and (result := (paired if pair else welch)(a, b)) is not None:
                rows.append(Row(later.env, later.method, earlier.method, name, fmt, pair, result))
    return rows


def phased(runs: Sequence[Run]) -> bool:
    """Whether any of the runs trained in phases, or continued a stack that another run's phases trained: where the
    whole run's AUC (`run_auc`) differs from the AUC, and so is reported beside it."""
    return any(len(run.phases) > 1 or run.continues is not None for run in runs)


def paired_seeds(first: Setup, second: Setup) -> bool:
    """Whether two setups ran the same seeds and each seed's two runs hold trained layers in common (one started
    from the other's weights, or both from one run's, as a fast phase tried over the slow layers of another
    setup's runs): then a seed's two returns share its layers' luck, and only their difference measures the setups."""
    if [r.seed for r in first.runs] != [r.seed for r in second.runs]:  # (each sorted by seed)
        return False
    return all(x.shares_layers_with(y) for x, y in zip(first.runs, second.runs, strict=True))


def between_phases(setups: Sequence[Setup]) -> list[Row]:
    """In each finished setup trained in phases, each phase against the one before it, seed by seed, on the
    returns of its best and its final weights on fresh episodes (for TLA: the stack against its slow layer alone);
    and a setup whose runs continued the stacks of another's (`continued`), its first phase against the phase
    they continued from, where `between_setups` does not compare the two already."""
    rows = []
    done = [s for s in setups if all(r.finished for r in s.runs)]
    for s in done:
        phases = s.runs[0].phases
        pairs: list[tuple[int, Sequence[Run], int, str]] = [
            (p, s.runs, p - 1, f"phase {p - 1} ({_learns(phases[p - 1])})")
            for p in range(1, min(len(r.phases) for r in s.runs))]
        if (earlier := continued(s, done)) is not None:
            source, runs, q = earlier
            if len(phases) > 1 or q < min(len(r.phases) for r in source.runs) - 1:
                pairs.insert(0, (0, runs, q, f"{source.method} phase {q} ({_learns(runs[0].phases[q])})"))
        for p, others, q, second in pairs:
            for key, name, fmt in MEASURES[:2]:
                a, b = _values(s.runs, key, p), _values(others, key, q)
                if a is not None and b is not None and (result := paired(a, b)) is not None:
                    rows.append(Row(s.env, f"{s.method} phase {p} ({_learns(phases[p])})", second, name, fmt, True,
                                    result))
    return rows


def continued(setup: Setup, setups: Sequence[Setup]) -> tuple[Setup, list[Run], int] | None:
    """The setup of `setups` whose runs `setup`'s runs continued (each started from the layers of its own run of it,
    all at the end of one phase: `Run.continues`), in the same environment and setting; those runs, in the order of
    `setup`'s; and that phase. None where there is no such setup."""
    owners = {run.path.resolve(): (other, run) for other in setups if other is not setup for run in other.runs}
    found = [owners[run.continues[0]] for run in setup.runs if run.continues and run.continues[0] in owners]
    phases = {run.continues[1] for run in setup.runs if run.continues}
    if not found or len(found) < len(setup.runs) or len(phases) > 1:
        return None
    (source, _), runs, phase = found[0], [run for _, run in found], phases.pop()
    one_each = all(other is source for other, _ in found) and len({id(run) for run in runs}) == len(runs)
    if not one_each or (source.env, source.realtime) != (setup.env, setup.realtime) \
            or any(len(run.phases) <= phase for run in runs):
        return None
    return source, runs, phase


@dataclass(frozen=True)
class Across:
    """A method against another over several environments."""

    first: str
    second: str
    envs: tuple[str, ...]
    measure: str
    above: float  # the mean over the environments of the chance that a seed of the first is above one of the second
    low: float  # its interval at LEVEL, from a stratified bootstrap
    high: float


RESAMPLES = 2000
"""Bootstrap resamples of an `Across` interval."""


def across_envs(setups: Sequence[Setup], resamples: int = RESAMPLES) -> list[Across]:
    """Each method (a recipe's name) against each listed before it, over every environment of one setting where
    both have finished setups, where there are two or more such: `mean_improvement` over those environments, on
    every measure of `MEASURES` that all their runs have."""
    pairs: dict[tuple[bool, str, str], list[tuple[Setup, Setup]]] = {}
    for later, earlier in setup_pairs(setups):
        flipped = (later.realtime, earlier.method, later.method)
        if flipped in pairs:  # listed the other way round in an earlier environment
            pairs[flipped].append((earlier, later))
        else:
            pairs.setdefault((later.realtime, later.method, earlier.method), []).append((later, earlier))
    rows = []
    for (_, first, second), shared in ((k, v) for k, v in pairs.items() if len(v) > 1):
        for key, name, _ in MEASURES:
            values = [(_values(a.runs, key), _values(b.runs, key)) for a, b in shared]
            if all(a is not None and b is not None for a, b in values):
                interval = mean_improvement([(np.asarray(a), np.asarray(b)) for a, b in values], resamples)
                rows.append(Across(first, second, tuple(a.env for a, _ in shared), name, *interval))
    return rows


def mean_improvement(samples: Sequence[tuple[np.ndarray, np.ndarray]], resamples: int) -> tuple[float, float, float]:
    """The probability of improvement of each environment's (first seeds, second seeds) averaged over them, and its
    interval at LEVEL from a stratified bootstrap: each environment's seeds of each drawn again with replacement,
    `resamples` times (seeded, so the same runs give the same interval)."""
    rng = np.random.default_rng(0)
    point, boot = 0.0, np.zeros(resamples)
    for a, b in samples:
        point += float(improvement(a, b)) / len(samples)
        boot += improvement(a[rng.integers(0, len(a), (resamples, len(a)))],
                            b[rng.integers(0, len(b), (resamples, len(b)))]) / len(samples)
    low, high = np.percentile(boot, [50 - LEVEL * 50, 50 + LEVEL * 50])
    return point, float(low), float(high)


def across_table(rows: Sequence[Across]) -> str:
    """The comparisons over environments as a Markdown table."""
    lines = ["| first | second | environments | measure | P(first above) [95% CI] |", "|---|---|---|---|---|"]
    lines += [f"| {r.first} | {r.second} | {', '.join(r.envs)} | {r.measure} | "
              f"{r.above:.2f} [{r.low:.2f}, {r.high:.2f}] |" for r in rows]
    return "\n".join(lines)


ACROSS_COLUMNS = ("first", "second", "envs", "measure", "first_above", "low", "high")
"""The columns of a report's `across-envs.csv`; `envs` separated by spaces."""


def across_csv_row(r: Across) -> list[Any]:
    """A comparison over environments as a row of `ACROSS_COLUMNS`."""
    return [r.first, r.second, " ".join(r.envs), r.measure, r.above, r.low, r.high]


def _learns(phase: dict[str, Any]) -> str:
    return "+".join(phase.get("learn", [])) or "?"


def comparisons_table(rows: Sequence[Row]) -> str:
    """The comparisons as a Markdown table."""
    lines = ["| environment | first | second | seeds | measure | first - second [95% CI] | p | p, Holm | first above |",
             "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        c = r.comparison
        n, m = c.sizes
        seeds = f"{n}, paired" if r.paired else f"{n} and {m}"
        above = f"{c.above * n:g} of {n} seeds" if r.paired else f"{c.above:.2f} of seed pairs"
        lines.append(f"| {r.env} | {r.first} | {r.second} | {seeds} | {r.measure} | {r.fmt.format(c.difference)} "
                     f"[{r.fmt.format(c.low)}, {r.fmt.format(c.high)}] | {c.p:.3g} | {r.p_holm:.3g} | {above} |")
    return "\n".join(lines)


COLUMNS = ("env", "first", "second", "measure", "paired", "first_seeds", "second_seeds", "difference", "low",
           "high", "p", "p_holm", "first_above")
"""The columns of a report's `comparisons.csv`."""


def csv_row(r: Row) -> list[Any]:
    """A comparison as a row of `COLUMNS`."""
    c = r.comparison
    return [r.env, r.first, r.second, r.measure, r.paired, *c.sizes, c.difference, c.low, c.high, c.p, r.p_holm,
            c.above]
