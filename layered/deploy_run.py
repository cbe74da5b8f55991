"""A deployment of a trained run: export it, start one process per layer, play each setting's episodes,
compare with `layered eval`'s episodes, and write what was measured (`<setting>.json`, `deploy.md`,
and, over several settings, `deploy.png`)."""

from __future__ import annotations

import json
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from layered.agents import make_aec_env
from layered.deploy import Driver, Settings, Stop
from layered.deploy_measures import largest_difference, layer_measures, run_measures
from layered.envs import control_timestep, env_info, make_env
from layered.evaluate import episode_seeds, run_episode
from layered.export import export_stack
from layered.latency import TOLERANCE
from layered.layer_process import LayerEnd, LayerFault, LayerProcess, Link
from layered.ray_cluster import start_ray
from layered.report import pyplot
from layered.rules import Rules
from layered.run_evals import TrainedRun

START_TIMEOUT_S = 120.0  # a layer's process imports torch and loads its policy
LONG_S = 60.0  # a setting whose episodes would take longer against the clock says so before it starts


def library_episodes(run: TrainedRun, episodes: int, threshold: float | None) -> list[tuple[float, np.ndarray]]:
    """`layered eval`'s episodes (seeded `episode_seeds(run.seed, episodes)`), played one after another through the
    agent view, as the deployed layers act: each one's return and executed actions."""
    env = make_aec_env(run.recipe, active=run.active, evaluation=True, threshold=threshold, keep_trace=True)
    played = []
    for seed in episode_seeds(run.seed, episodes):
        measures = run_episode(env, run.learners, seed)
        played.append((measures.ret, np.asarray([r.action for r in env.trace], np.float32)))
    env.close()
    return played


def start_layers(rules: Rules, directory: Path, settings: Settings, seed: int,
                 transport: str = "process") -> dict[int, LayerEnd]:
    """One process (or Ray actor) per present layer, each with its link and fault, ready to answer."""
    kind: Any = LayerProcess
    if transport == "ray":
        from layered.layer_ray import RayLayer

        kind = RayLayer
    ends: dict[int, LayerEnd] = {}
    try:
        for i in rules.active:
            name = rules.layers[i].name
            ends[i] = kind(name, directory, "torchscript", settings.links.get(name, Link()), settings.faults.get(name),
                           seed * 1000 + i)
        for end in ends.values():
            end.wait_ready(START_TIMEOUT_S)
    except BaseException:
        for end in ends.values():
            end.close()
        raise
    return ends


def deploy(run: TrainedRun, settings: Sequence[Settings], episodes: int, out: Path, threshold: float | None = None,
           notify: Callable[[str], None] = print, transport: str = "process",
           address: str | None = None) -> list[dict[str, Any]]:
    """Deploy `run` under each of `settings` for `episodes` episodes, its layers carried by `transport`
    (Ray: on the cluster at `address`, default a local one); one row of measures per setting, each also
    written to `out/<label>.json`."""
    if transport == "ray" and any(link.mean_s for setting in settings for link in setting.links.values()):
        raise LayerFault("--link-delay emulates a link between local processes; with Ray actors the network's "
                         "own delays apply")
    made = not out.exists()
    out.mkdir(parents=True, exist_ok=True)
    ray = start_ray(address) if transport == "ray" else None
    try:
        return _deploy(run, settings, episodes, out, threshold, notify, transport)
    except BaseException:
        if made and not any(out.iterdir()):  # (refused before anything was written: leave no empty folder)
            out.rmdir()
        raise
    finally:
        if ray is not None:
            ray.shutdown()


def _deploy(run: TrainedRun, settings: Sequence[Settings], episodes: int, out: Path, threshold: float | None,
            notify: Callable[[str], None], transport: str) -> list[dict[str, Any]]:
    directory = export_stack(run.recipe, run.learners, run.active, out / "export-torchscript", "torchscript",
                             threshold)
    rules = Rules.from_json(json.loads((directory / "stack.json").read_text())["rules"])
    timestep = control_timestep(run.recipe.env.id) or 1.0
    reference = library_episodes(run, episodes, threshold)
    tolerance = TOLERANCE * float(np.max(rules.high - rules.low))
    env = make_env(run.recipe.env.id)
    steps = env_info(run.recipe.env.id).episode_steps
    how = {"run": str(run.path.resolve()), "weights": run.weights or run.recipe.train.select, "threshold": threshold,
           "transport": transport, "episodes_asked": episodes}
    rows = []
    try:
        for k, setting in enumerate(settings):
            processes = start_layers(rules, directory, setting, run.seed, transport)
            driver = Driver(rules, processes, timestep, setting, notify)
            if not setting.lockstep and steps and (longest := episodes * steps * timestep / setting.speed) > LONG_S:
                notify(f"{setting.label}: {episodes} episode{'s' * (episodes > 1)} of up to {steps} steps at "
                       f"{timestep / setting.speed:.3g} s a step take up to {longest / 60:.1f} minutes")
            played, stopped = [], False
            try:
                for n, seed in enumerate(episode_seeds(run.seed, episodes), start=1):
                    played.append(driver.play(env, seed))
                    if n < episodes:
                        notify(f"{setting.label}: episode {n} of {episodes}: return {played[-1].ret:.1f}")
            except Stop:
                stopped = True
            finally:
                for process in processes.values():
                    process.close()
            row = {**_row(setting, driver, played, reference, timestep, tolerance), **how,
                   "pids": [process.pid for process in processes.values()]}
            (out / f"{setting.label}.json").write_text(json.dumps(row, indent=2) + "\n")
            rows.append(row)
            notify(f"{setting.label}: return {row['return_mean']:.1f} (eval {row['eval_return_mean']:.1f}) over "
                   f"{row['episodes']} episodes, {row['steps_per_s']:.0f} steps/s; written to "
                   f"{out / (setting.label + '.json')}" if played else f"{setting.label}: no episode completed")
            if stopped:
                if rest := settings[k + 1:]:
                    notify(f"the deployment ends (--on-fault stop): {', '.join(s.label for s in rest)} not played")
                break
    finally:
        env.close()
    (out / "deploy.md").write_text(table(rows) + "\n")
    if len(played_rows := [row for row in rows if row["episodes"]]) > 1:
        plot(played_rows, out / "deploy.png", f"{run.recipe.env.id}: {', '.join(run.active)} deployed as processes")
    return rows


def _row(setting: Settings, driver: Driver, played: list[Any], reference: list[tuple[float, np.ndarray]],
         timestep: float, tolerance: float) -> dict[str, Any]:
    """One setting's measures (deploy's `<setting>.json`): its episodes' returns and speed, how far its actions are
    from `layered eval`'s, and each layer's latencies."""
    difference = largest_difference([e.actions for e in played], [actions for _, actions in reference])
    layers = {}
    for i in driver.rules.active:
        layer = driver.rules.layers[i]
        mine = [d for d in driver.decisions if d.layer == i]
        layers[layer.name] = {"period_s": layer.period * timestep, **layer_measures(mine, layer.lag)}
    return {
        "setting": setting.label, "speed": setting.speed, "lockstep": setting.lockstep,
        "links": {name: str(link) for name, link in setting.links.items()},
        "faults": driver.faults, "completed": len(played) == len(reference) and not driver.faults,
        **run_measures(played, timestep),
        "eval_returns": [ret for ret, _ in reference[: len(played)]],
        "eval_return_mean": float(np.mean([ret for ret, _ in reference[: len(played)]])) if played else None,
        "max_action_difference": difference, "tolerance": tolerance,
        "same_actions_as_eval": bool(difference <= tolerance),
        "layers": layers,
    }


def _ms(value: float | None) -> str:
    return "-" if value is None else f"{value:.2f}"


def table(rows: Sequence[dict[str, Any]]) -> str:
    """The measures as a markdown table: one line per setting and layer."""
    lines = ["| setting | return (deployed) | return (eval) | same actions | steps/s | x real time | layer "
             "| latency median / p99 ms | missed | late | dropped | delay seen, steps:count | asked unseen |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for row in rows:
        first = True
        for name, layer in row["layers"].items():
            head = (f"| {row['setting']} | {row['return_mean']:.1f} ± {row['return_std']:.1f} | "
                    f"{row['eval_return_mean']:.1f} | {'yes' if row['same_actions_as_eval'] else 'no'} | "
                    f"{row['steps_per_s']:.0f} | {row['real_time_factor']:.1f} " if first and row["episodes"]
                    else "| | | | | | ")
            seen = " ".join(f"{k}:{n}" for k, n in layer["delay_seen"].items()) or "-"
            lines.append(f"{head}| {name} | {_ms(layer['latency_ms']['median'])} / {_ms(layer['latency_ms']['p99'])} "
                         f"| {layer['missed']} of {layer['settled']} | {layer['late']} | {layer['dropped']} | "
                         f"{seen} (trained {layer['scheduled_delay']}) | {layer['asked_unseen']} |")
            first = False
    return "\n".join(lines)


def _reached(row: dict[str, Any]) -> str:
    """A setting's name, with the speed it reached where that fell short of the one asked for by over a tenth."""
    if row["lockstep"] or row["real_time_factor"] is None or row["real_time_factor"] >= 0.9 * row["speed"]:
        return row["setting"]
    return f"{row['setting']} ({row['real_time_factor']:.1f}x reached)"


def plot(rows: Sequence[dict[str, Any]], out_png: Path, title: str) -> None:
    """Return, latency, misses and delay seen against the settings, one line per layer."""
    plt = pyplot()
    labels = [_reached(row) for row in rows]
    x = np.arange(len(rows))
    fig, axes = plt.subplots(2, 2, figsize=(11, 7.5), constrained_layout=True)
    ret, latency, missed, delay = axes.flat
    ret.errorbar(x, [r["return_mean"] for r in rows], [r["return_std"] for r in rows], marker="o", capsize=3,
                 label="deployed")
    ret.plot(x, [r["eval_return_mean"] for r in rows], "k--", label="layered eval")
    ret.set_ylabel("return")
    ret.legend()
    for name in rows[0]["layers"]:
        layers = [row["layers"][name] for row in rows]
        latency.plot(x, [layer["latency_ms"]["p99"] or np.nan for layer in layers], marker="o", label=name)
        missed.plot(x, [100 * layer["miss_rate"] for layer in layers], marker="o", label=name)
        delay.plot(x, [np.nan if layer["mean_delay_seen"] is None else layer["mean_delay_seen"] for layer in layers],
                   marker="o", label=name)
    latency.set_ylabel("decision latency p99 (ms)")
    latency.set_ylim(bottom=0)
    missed.set_ylabel("deadlines missed (%)")
    delay.set_ylabel("mean delay seen (base steps)")
    for ax in axes.flat:
        ax.set_xticks(x, labels, rotation=30, ha="right", fontsize=8)
        ax.grid(alpha=0.3)
    latency.legend()
    fig.suptitle(title)
    fig.savefig(out_png, dpi=120)
    plt.close(fig)
