"""The tests of seeds against seeds (`layered.compare`), checked against values worked out by hand, and the report's
comparisons of setups and phases."""

import csv
import json
import math
from dataclasses import replace
from pathlib import Path

import pytest

from layered.compare import across_envs, holm, paired, welch
from layered.report import write_report
from layered.summary import Run, find_runs, group

# Student's t with 2 degrees of freedom has a closed form: two-sided p = 1 - |t| / sqrt(2 + t^2), and its
# 0.975 quantile is 0.95 / sqrt(2 * 0.975 * 0.025)
T2_975 = 0.95 / math.sqrt(2 * 0.975 * 0.025)  # 4.3027


def p_two_sided_df2(t):
    return 1 - abs(t) / math.sqrt(2 + t * t)


def test_welch_by_hand():
    # means 2 and 1, sample variances 2 and 2: the difference's standard error sqrt(2/2 + 2/2), and Welch's
    # degrees of freedom (1 + 1)^2 / (1^2 / 1 + 1^2 / 1) = 2
    c = welch([1.0, 3.0], [0.0, 2.0])
    se = math.sqrt(2.0)
    assert c.difference == pytest.approx(1.0)
    assert c.p == pytest.approx(p_two_sided_df2(1.0 / se))  # 0.5528
    assert (c.low, c.high) == pytest.approx((1.0 - T2_975 * se, 1.0 + T2_975 * se))  # -5.085, 7.085
    assert c.above == 0.75  # 1 > 0, 3 > 0, 3 > 2; not 1 > 2
    assert c.sizes == (2, 2)


def test_welch_weighs_each_sample_by_its_own_spread():
    # variances 1 and 4 over 3 seeds each: standard error sqrt(1/3 + 4/3), degrees (5/3)^2 / ((1/3)^2/2 + (4/3)^2/2)
    c = welch([1.0, 2.0, 3.0], [2.0, 4.0, 6.0])
    se, df = math.sqrt(5 / 3), (5 / 3) ** 2 / ((1 / 3) ** 2 / 2 + (4 / 3) ** 2 / 2)
    assert df == pytest.approx(50 / 17)
    from scipy import stats

    assert c.p == pytest.approx(2 * stats.t.sf(2.0 / se, 50 / 17))
    assert c.difference == -2.0 and c.above == pytest.approx(1.5 / 9)  # 3 > 2, and 2 ties 2: of nine pairs


def test_ties_count_half():
    assert welch([1.0, 2.0], [1.0, 1.0]).above == 0.75  # (1, 1) twice half, (2, 1) twice whole
    assert paired([1.0, 2.0, 3.0], [1.0, 1.0, 4.0]).above == pytest.approx(0.5)  # tie, above, below


def test_paired_by_hand():
    # differences 2, 3, 0: mean 5/3, sample standard deviation sqrt(7/3), 2 degrees of freedom
    c = paired([3.0, 5.0, 4.0], [1.0, 2.0, 4.0])
    se = math.sqrt(7 / 3) / math.sqrt(3)
    assert c.difference == pytest.approx(5 / 3)
    assert c.p == pytest.approx(p_two_sided_df2((5 / 3) / se))  # 0.1994
    assert (c.low, c.high) == pytest.approx((5 / 3 - T2_975 * se, 5 / 3 + T2_975 * se))
    assert c.above == pytest.approx(2.5 / 3)


def test_no_spread_and_too_few_seeds():
    assert welch([1.0], [2.0, 3.0]) is None and paired([1.0], [2.0]) is None
    same = welch([5.0, 5.0], [5.0, 5.0])
    assert (same.difference, same.low, same.high, same.p) == (0.0, 0.0, 0.0, 1.0)
    apart = welch([1000.0, 1000.0], [900.0, 900.0])
    assert (apart.difference, apart.low, apart.high, apart.p, apart.above) == (100.0, 100.0, 100.0, 0.0, 1.0)
    with pytest.raises(ValueError, match="paired samples of 2 and 3"):
        paired([1.0, 2.0], [1.0, 2.0, 3.0])


def test_holm_by_hand():
    # m = 4; sorted 0.01, 0.03, 0.04, 0.2 times 4, 3, 2, 1: 0.04, 0.09, 0.08, 0.2; each at least the one
    # before it (0.08 -> 0.09), given back in the order the p-values came
    assert holm([0.01, 0.04, 0.03, 0.2]) == pytest.approx([0.04, 0.09, 0.09, 0.2])
    assert holm([0.5, 0.6]) == [1.0, 1.0]  # 0.5 * 2 = 1.0, then at least that; never above 1
    assert holm([0.02, 0.02]) == pytest.approx([0.04, 0.04])  # ties: 2 * 0.02, then 1 * 0.02 raised to it
    assert holm([0.3]) == [0.3] and holm([]) == []


def _run(label, seed, phases, finished=True, realtime=True):
    final = {k: v for k, v in phases[-1].items() if k != "learn"}
    return Run(Path(f"/r/{label}-{seed}"), "Hopper-v5", label, seed, realtime, final, ((0, 1.0),),
               phases=tuple(phases), stands="" if finished else "phase 1, step 100")


def test_the_report_compares_setups_and_each_phase_with_the_one_before(tmp_path):
    def td3(seed, best):
        return _run("hopper/td3-realtime", seed, [{"phase": 0, "learn": ["fast"], "fresh_best_return_mean": best}])

    def tla(seed, slow, best):
        return _run("hopper/tla-realtime", seed, [{"phase": 0, "learn": ["slow"], "fresh_best_return_mean": slow},
                                                  {"phase": 1, "learn": ["fast"], "fresh_best_return_mean": best}])

    runs = [td3(0, 0.0), td3(1, 2.0), td3(2, 1.0), tla(0, 1.0, 3.0), tla(1, 2.0, 5.0), tla(2, 4.0, 4.0)]
    text = write_report(group(runs), tmp_path)
    rows = list(csv.DictReader((tmp_path / "comparisons.csv").open()))
    assert [(r["first"], r["second"], r["paired"]) for r in rows] == [
        ("tla-realtime", "td3-realtime", "False"), ("tla-realtime phase 1 (fast)", "phase 0 (slow)", "True")]
    between, phases = rows
    # TLA 3, 5, 4 against TD3 0, 2, 1: means 4 and 1, variances 1 and 1, so se = sqrt(2/3) and df = 4
    from scipy import stats

    assert float(between["difference"]) == pytest.approx(3.0)
    assert float(between["p"]) == pytest.approx(2 * stats.t.sf(3.0 / math.sqrt(2 / 3), 4))
    assert float(between["first_above"]) == 1.0 and between["measure"] == "return, best weights"
    # phase 1 against phase 0 seed by seed: 3 - 1, 5 - 2, 4 - 4, as in test_paired_by_hand
    assert float(phases["difference"]) == pytest.approx(5 / 3)
    p_phases = p_two_sided_df2((5 / 3) / (math.sqrt(7 / 3) / math.sqrt(3)))  # 0.1994
    assert float(phases["p"]) == pytest.approx(p_phases)
    # two comparisons in the report: the smaller p (between, 0.0213) doubled, the larger kept (at least that)
    assert float(between["p_holm"]) == pytest.approx(2 * float(between["p"]))
    assert float(phases["p_holm"]) == pytest.approx(p_phases)
    assert "| Hopper-v5 | tla-realtime | td3-realtime | 3 and 3 | return, best weights | +3.0 [" in text
    assert "| 1.00 of seed pairs |" in text
    assert "| tla-realtime phase 1 (fast) | phase 0 (slow) | 3, paired | return, best weights | +1.7 [" in text
    assert "| 2.5 of 3 seeds |" in text


def test_setups_are_compared_on_action_repetition(tmp_path):
    def run(label, seed, repetition):
        return _run(label, seed, [{"phase": 0, "learn": ["fast"], "fresh_final_repetition": repetition}])

    # repetition 0.6, 0.7, 0.8 against 0.1, 0.2, 0.3: a difference of 0.5 with variances 0.01 and 0.01, se =
    # sqrt(0.02 / 3) and df = 4, every seed of the first above every seed of the second
    runs = [run("p/tla-c", k, 0.6 + 0.1 * k) for k in range(3)] + [run("p/td3", k, 0.1 + 0.1 * k) for k in range(3)]
    text = write_report(group(runs), tmp_path)
    row, = list(csv.DictReader((tmp_path / "comparisons.csv").open()))
    from scipy import stats

    assert row["measure"] == "action repetition, final weights" and float(row["difference"]) == pytest.approx(0.5)
    assert float(row["p"]) == pytest.approx(2 * stats.t.sf(0.5 / math.sqrt(0.02 / 3), 4))
    assert float(row["first_above"]) == 1.0
    assert "| action repetition, final weights | +50.0% [" in text


def test_setups_whose_seeds_share_their_layers_are_compared_seed_by_seed(tmp_path):
    def run(label, seed, repetition, started_from=()):
        return replace(_run(label, seed, [{"phase": 0, "learn": ["fast"], "fresh_final_repetition": repetition}]),
                       started_from=frozenset(Path(p) for p in started_from))

    recipe = [run("p/tla-c", k, r) for k, r in enumerate([0.5, 0.6, 0.7])]
    # fast phases over the slow layers of the recipe's runs (/r/p/tla-c-<k>); the same but seed 2's from elsewhere
    values = [0.6, 0.8, 0.7]
    probe = [run("p/probe", k, r, [f"/r/p/tla-c-{k}"]) for k, r in enumerate(values)]
    aside = [run("p/aside", k, r, [f"/r/p/tla-c-{k}"] if k < 2 else ["/r/elsewhere"]) for k, r in enumerate(values)]
    rows = {(r["first"], r["second"]): r for r in _compared(recipe + probe + aside, tmp_path)}
    # probe against the recipe, seed by seed: differences 0.1, 0.2, 0.0, mean 0.1, sample std 0.1, se 0.1 / sqrt(3),
    # 2 degrees of freedom: t = sqrt(3), p = 1 - sqrt(3) / sqrt(5) = 0.2254; above in seeds 0 and 1, a tie in seed 2
    row = rows["probe", "tla-c"]
    assert row["paired"] == "True" and float(row["difference"]) == pytest.approx(0.1)
    assert float(row["p"]) == pytest.approx(p_two_sided_df2(math.sqrt(3))) == pytest.approx(0.2254, abs=1e-4)
    assert float(row["first_above"]) == pytest.approx(2.5 / 3)
    # the same values with seed 2's layers from elsewhere: independent samples (Welch's p 0.29, not the paired 0.23)
    assert rows["aside", "tla-c"]["paired"] == "False"
    assert float(rows["aside", "tla-c"]["p"]) == pytest.approx(welch(values, [0.5, 0.6, 0.7]).p)
    # two setups over one run's layers are paired with each other too; setups of other seeds are not
    assert rows["probe", "aside"]["paired"] == "False"  # seed 2: /r/p/tla-c-2 and /r/elsewhere share nothing
    both = [run("p/again", k, r, [f"/r/p/tla-c-{k}"]) for k, r in enumerate([0.7, 0.7, 0.7])]
    assert {r["paired"] for r in _compared(probe + both, tmp_path)} == {"True"}
    fewer = [run("p/fewer", k, r, [f"/r/p/tla-c-{k}"]) for k, r in enumerate([0.7, 0.7])]
    assert {r["paired"] for r in _compared(recipe + fewer, tmp_path)} == {"False"}


def test_a_setup_that_continued_another_setups_stacks_is_compared_with_the_phase_it_continued(tmp_path):
    def tla(seed, slow, fast):
        return _run("p/tla-c", seed, [{"phase": 0, "learn": ["slow"], "fresh_best_return_mean": slow},
                                      {"phase": 1, "learn": ["fast"], "fresh_best_return_mean": fast}])

    def probe(label, seed, value, continues):
        return replace(_run(label, seed, [{"phase": 0, "learn": ["fast"], "fresh_best_return_mean": value}]),
                       started_from=frozenset({Path(continues[0])}), continues=(Path(continues[0]), continues[1]))

    recipe = [tla(k, slow, fast) for k, (slow, fast) in enumerate([(1.0, 3.0), (2.0, 5.0), (4.0, 4.0)])]
    # fast phases over each seed's slow layer (phase 0 of /r/p/tla-c-<k>): 3, 5, 4 against it, as in
    # test_paired_by_hand: differences 2, 3, 0, mean 5/3, sample std sqrt(7/3)
    over_slow = [probe("p/probe", k, v, (f"/r/p/tla-c-{k}", 0)) for k, v in enumerate([3.0, 5.0, 4.0])]
    rows = {(r["first"], r["second"]): r for r in _compared(recipe + over_slow, tmp_path)}
    row = rows["probe phase 0 (fast)", "tla-c phase 0 (slow)"]
    assert row["paired"] == "True" and float(row["difference"]) == pytest.approx(5 / 3)
    assert float(row["p"]) == pytest.approx(p_two_sided_df2((5 / 3) / (math.sqrt(7 / 3) / math.sqrt(3))))
    assert float(row["first_above"]) == pytest.approx(2.5 / 3)
    assert rows["probe", "tla-c"]["paired"] == "True"  # and against the recipe's stacks, as setups
    # no phase row where a seed's stack came from elsewhere, where two seeds continued one run, or where the phase
    # continued is the other's last (the setups' comparison is that one)
    elsewhere = [*over_slow[:2], probe("p/probe", 2, 4.0, ("/r/elsewhere", 0))]
    one_run = [*over_slow[:2], probe("p/probe", 2, 4.0, ("/r/p/tla-c-1", 0))]
    last = [probe("p/probe", k, v, (f"/r/p/tla-c-{k}", 1)) for k, v in enumerate([3.0, 5.0, 4.0])]
    for probes in (elsewhere, one_run, last):
        assert not [r for r in _compared(recipe + probes, tmp_path) if r["first"].startswith("probe phase")]


def test_setups_trained_in_different_phases_are_compared_on_the_whole_runs_auc(tmp_path):
    def write(name, seed, phases, weights=None):
        path = tmp_path / name / f"seed{seed}"
        path.mkdir(parents=True)
        (path / "results.json").write_text(json.dumps({"env": "Pendulum-v1", "seed": seed, "label": f"p/{name}",
                                                       "phases": [{"phase": i, **p} for i, p in enumerate(phases)]}))
        layers = "".join(f'[[layers]]\nname = "{layer}"\n' + (f'weights = "{(weights or {}).get(layer)}"\n'
                                                                if layer in (weights or {}) else "")
                         for layer in ("slow", "fast"))
        (path / "recipe.toml").write_text(f"[train]\nseed = {seed}\n" + layers)
        (path / "metrics.csv").write_text("phase,learn,step,return_mean\n" + "".join(
            f"{i},{'+'.join(p['learn'])},{step},-900\n" for i, p in enumerate(phases) for step in (0, 10)))

    # TLA-C: 40k steps at AUC 0.2, then 10k at 0.5 (seed 0) or 0.6 (seed 1): over the whole run
    # (0.2 * 40000 + 0.5 * 10000) / 50000 = 0.26 and 0.28; TD3 50k steps at 0.3 and 0.32 in one phase
    for seed, last in enumerate([0.5, 0.6]):
        write("tla-c", seed, [{"learn": ["slow"], "steps": 40000, "auc": 0.2}, {"learn": ["fast"], "steps": 10000,
                                                                               "auc": last}])
        write("td3", seed, [{"learn": ["fast"], "steps": 50000, "auc": 0.3 + 0.02 * seed}])
        write("td3-again", seed, [{"learn": ["fast"], "steps": 50000, "auc": 0.3 + 0.01 * seed}])
    runs = find_runs([tmp_path])
    assert [r.final["run_auc"] for r in runs if r.method == "tla-c"] == pytest.approx([0.26, 0.28])
    rows = {(r["first"], r["second"], r["measure"]): r for r in _compared(runs, tmp_path / "report")}
    # 0.27 against 0.31: the last phase's AUC alone (0.55 against 0.31) says the opposite
    assert float(rows["tla-c", "td3", "AUC, whole run"]["difference"]) == pytest.approx(-0.04)
    assert float(rows["tla-c", "td3", "AUC"]["difference"]) == pytest.approx(0.24)
    # two setups of one phase each: their AUC once
    assert ("td3-again", "td3", "AUC") in rows and ("td3-again", "td3", "AUC, whole run") not in rows
    # a phase without an AUC (no return range) gives none for the whole run
    write("no-range", 0, [{"learn": ["slow"], "steps": 10, "auc": None}, {"learn": ["fast"], "steps": 10, "auc": 0.5}])
    assert "run_auc" not in find_runs([tmp_path / "no-range"])[0].final
    # a fast phase over each seed's slow layer (phase 0 of tla-c) continues its 40k steps at AUC 0.2:
    # (0.2 * 40000 + 0.8 * 10000) / 50000 = 0.32 and (8000 + 0.9 * 10000) / 50000 = 0.34, against TD3's 0.3 and 0.32
    for seed in (0, 1):
        write("over-slow", seed, [{"learn": ["fast"], "steps": 10000, "auc": 0.8 + 0.1 * seed}],
              {"slow": f"{tmp_path}/tla-c/seed{{seed}}/checkpoints/slow.pt"})
    over_slow = find_runs([tmp_path / "over-slow"])
    assert [r.final["run_auc"] for r in over_slow] == pytest.approx([0.32, 0.34])
    rows = {(r["first"], r["second"], r["measure"]): r for r in _compared(runs + over_slow, tmp_path / "again")}
    assert float(rows["over-slow", "td3", "AUC, whole run"]["difference"]) == pytest.approx(0.02)
    # and a run over that one's fast layer continues both: (8000 + 8000 + 0.5 * 10000) / 60000 = 0.35
    write("over-fast", 0, [{"learn": ["fast"], "steps": 10000, "auc": 0.5}],
          {"fast": f"{tmp_path}/over-slow/seed0/checkpoints/fast.pt"})
    assert find_runs([tmp_path / "over-fast"])[0].final["run_auc"] == pytest.approx(0.35)
    # none where the weights came from a file outside a run, or from a phase whose results cannot be read
    write("from-file", 0, [{"learn": ["fast"], "steps": 10, "auc": 0.5}], {"slow": f"{tmp_path}/slow.pt"})
    assert "run_auc" not in find_runs([tmp_path / "from-file"])[0].final
    (tmp_path / "tla-c" / "seed1" / "results.json").write_text("{")
    write("over-broken", 1, [{"learn": ["fast"], "steps": 10, "auc": 0.5}],
          {"slow": f"{tmp_path}/tla-c/seed1/checkpoints/slow.pt"})
    assert "run_auc" not in find_runs([tmp_path / "over-broken"])[0].final


def _compared(runs, out):
    write_report(group(runs), out)
    return list(csv.DictReader((out / "comparisons.csv").open()))


@pytest.mark.parametrize("other", ["unfinished", "not real-time"])
def test_unfinished_setups_and_other_settings_are_not_compared(tmp_path, other):
    one = [{"phase": 0, "learn": ["fast"], "return_mean": 1.0}]
    runs = [_run("hopper/td3-realtime", s, one) for s in (0, 1)] + [
        _run("hopper/tla", s, one, finished=other != "unfinished", realtime=other != "not real-time") for s in (0, 1)]
    text = write_report(group(runs), tmp_path)
    assert "## Comparisons over seeds" not in text
    assert (tmp_path / "comparisons.csv").read_text().splitlines() == [
        "env,first,second,measure,paired,first_seeds,second_seeds,difference,low,high,p,p_holm,first_above"]


def _setups_over(envs):
    """Finished single-phase setups of TD3 and TLA in each of `envs` ({env: (tla returns, td3 returns)})."""
    runs = []
    for env, (tla, td3) in envs.items():
        for label, values in ((f"{env}/td3-realtime", td3), (f"{env}/tla-realtime", tla)):
            runs += [Run(Path(f"/r/{env}-{label}-{k}"), env, label, k, True, {"return_mean": v}, ((0, 1.0),),
                         phases=({"phase": 0, "return_mean": v},)) for k, v in enumerate(values)]
    return group(runs)


def test_a_method_against_another_across_environments_by_hand(tmp_path):
    # Hopper: TLA 0, 2 against TD3 1, 1: (0 > 1) no, (2 > 1) yes, twice each: 0.5. Walker: 5, 5 against 1, 1: 1.
    # Averaged: 0.75. The bootstrap keeps Walker at 1 and draws Hopper's TLA seeds as (0, 0), (2, 2) or one of
    # each, with chances 1/4, 1/4, 1/2: Hopper 0, 1 or 0.5, so the mean 0.5, 1 or 0.75, each of the two tails
    # holding a quarter of the resamples: the 2.5% and 97.5% points are 0.5 and 1.
    setups = _setups_over({"Hopper-v5": ([0.0, 2.0], [1.0, 1.0]), "Walker2d-v5": ([5.0, 5.0], [1.0, 1.0])})
    (row,) = across_envs(setups)
    assert (row.first, row.second, row.envs) == ("tla-realtime", "td3-realtime", ("Hopper-v5", "Walker2d-v5"))
    assert row.measure == "return, final evaluation"
    assert (row.above, row.low, row.high) == (0.75, 0.5, 1.0)
    text = write_report(setups, tmp_path)
    assert ("| tla-realtime | td3-realtime | Hopper-v5, Walker2d-v5 | return, final evaluation | 0.75 [0.50, 1.00] |"
            in text)
    (written,) = csv.DictReader((tmp_path / "across-envs.csv").open())
    assert written == {"first": "tla-realtime", "second": "td3-realtime", "envs": "Hopper-v5 Walker2d-v5",
                       "measure": "return, final evaluation", "first_above": "0.75", "low": "0.5", "high": "1.0"}


def test_one_environment_is_not_an_aggregate_and_seeds_alike_give_a_half(tmp_path):
    assert across_envs(_setups_over({"Hopper-v5": ([0.0, 2.0], [1.0, 1.0])})) == []
    (row,) = across_envs(_setups_over({"A-v0": ([3.0, 3.0], [3.0, 3.0]), "B-v0": ([1.0], [1.0])}))
    assert (row.above, row.low, row.high) == (0.5, 0.5, 0.5)  # every pair a tie, in every resample
