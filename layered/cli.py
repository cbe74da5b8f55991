"""The `layered` command: train a recipe, evaluate a run, sweep recipes over seeds, report."""

from __future__ import annotations

import argparse
import json
import math
import os
import signal
import statistics
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Any, NoReturn

# Only light modules here, so that --help and usage errors answer at once: each command imports
# what it needs (torch, the learners, the environments) when it runs.
from layered import __version__
from layered.deploy import FAULT_ACTIONS, Settings
from layered.errors import BadInput, Diverged
from layered.interrupt import Stopped
from layered.layer_process import Fault, LayerFault, Link
from layered.plugins import load_plugins
from layered.progress import count
from layered.report import DEFAULT_SWEEP, plot_episode, results_table

if TYPE_CHECKING:
    from layered.rundir import RunInfo

EXIT_BAD_INPUT = 2
EXIT_DIVERGED = 1
EXIT_SIGNAL = {"SIGINT": 130, "SIGTERM": 143}


def _threshold(text: str) -> float:
    """An evaluation threshold: a finite number >= 0 (NaN would silently turn thresholding off)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not (math.isfinite(value) and value >= 0):
        raise argparse.ArgumentTypeError(f"a threshold is a finite number >= 0, got {text!r}")
    return value


THRESHOLD_HELP = "evaluation threshold as a fraction of max action (default: the recipe's)"


def _thresholds(text: str) -> list[float]:
    return [_threshold(x.strip()) for x in text.split(",") if x.strip()]


def _plugin_option(parser: argparse.ArgumentParser, note: str = "") -> None:
    help_text = "import your own combiner, learner, order or env family first (repeatable)"
    parser.add_argument("--plugin", action="append", default=[], metavar="FILE.py|MODULE",
                        help=f"{help_text}{', ' + note if note else ''}")


class _Parser(argparse.ArgumentParser):
    """argparse whose usage errors are one line, like every other refusal of the command."""

    def error(self, message: str) -> NoReturn:
        self.exit(EXIT_BAD_INPUT, f"layered: error: {message} (see {self.prog} --help)\n")


def _positive(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None
    if value <= 0:
        raise argparse.ArgumentTypeError(f"must be positive, got {value}")
    return value


def _seed_count(text: str) -> int:
    """A sweep's `--seeds`: a count N (seeds 0..N-1)."""
    if not text.strip().isdigit() and ("-" in text.strip("-") or "," in text):
        raise argparse.ArgumentTypeError(f"a sweep takes a count N (seeds 0..N-1), got {text!r}; for other seeds, "
                                         "`layered train RECIPE --seeds A-B` trains them as one group")
    return _positive(text)


MAX_GROUP = 4096  # seeds in one group: more would not fit one process's memory anyway


def _seeds(text: str) -> list[int]:
    """`--seeds`: a count N (seeds 0..N-1), a range A-B (inclusive) or a list A,B,C."""
    try:
        if len(text) > 100_000:
            raise ValueError
        if "," in text:
            seeds = [int(part) for part in text.split(",")]
        elif "-" in text.strip("-"):
            first, last = (int(part) for part in text.split("-", 1))
            if last < first:
                raise argparse.ArgumentTypeError(f"a range A-B needs A at most B, got {text!r}")
            seeds = list(range(first, min(last, first + MAX_GROUP) + 1))
        elif text.strip().isdigit():
            if int(text) == 0:
                raise argparse.ArgumentTypeError("a count N trains seeds 0..N-1, so it is at least 1 (seed 0 alone: "
                                                 "--seeds 1, or --seed 0 as a single run)")
            seeds = list(range(min(int(text), MAX_GROUP + 1)))
        else:
            raise ValueError
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected N, A-B or A,B,C, got {text!r}") from None
    if not seeds or min(seeds) < 0 or max(seeds) > 2**32 - 1 or len(set(seeds)) != len(seeds):
        raise argparse.ArgumentTypeError(f"expected distinct seeds from 0 to 2**32-1, got {text[:40]!r}")
    if len(seeds) > MAX_GROUP:
        raise argparse.ArgumentTypeError(f"at most {MAX_GROUP} seeds in one group, got {text[:40]!r}")
    return seeds


Subcommands = argparse._SubParsersAction  # (argparse's type of `add_subparsers`: where each command's parser is added)


def _parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="layered", description="Temporally layered control stacks.")
    parser.add_argument("--version", action="version", version=f"layered {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)
    _train_parser(sub)
    _resume_parser(sub)
    _eval_parser(sub)
    _export_parser(sub)
    _sweep_parser(sub)
    _deploy_parser(sub)
    _report_parser(sub)
    return parser


def _train_parser(sub: Subcommands) -> None:
    """The options of `layered train`: a training run."""
    tr = sub.add_parser(
        "train", help="train a recipe and write a run directory",
        usage="layered train RECIPE [key=value ...] [--out DIR] [--seed S] [--steps N] [--threads T] [--force] "
        "[--seeds N|A-B|A,B,C] [--tensorboard] [--device {cpu,cuda,auto}] [--plugin FILE.py|MODULE]",
        epilog="key=value pairs override recipe values, e.g. train.warmup=500 layers.fast.period=2",
    )
    tr.add_argument("recipe", help="recipe TOML file, or a shipped recipe by name (pendulum/tla-c)")
    tr.add_argument("--out", type=Path, help="run directory (default runs/<recipe>-s<seed>-<time>)")
    tr.add_argument("--seed", type=int, help="same as train.seed=S")
    tr.add_argument("--seeds", type=_seeds, help="train several seeds as one group in this process: N (0..N-1), "
                    "A-B or A,B,C; each seed gets its own run directory OUT/seed<k>")
    tr.add_argument("--steps", type=_positive, help="cap every training phase at N environment steps")
    tr.add_argument("--threads", type=_positive, help="torch threads (use 1 per process when running several)")
    tr.add_argument("--force", action="store_true", help="start over in an --out that holds a stopped or finished run")
    tr.add_argument("--device", choices=["cpu", "cuda", "auto"], help="where the learners run (learner.device)")
    tr.add_argument("--tensorboard", action="store_true",
                    help="also write TensorBoard event files (as log.tensorboard=true; extra "
                    "layered-control[tensorboard])")
    _plugin_option(tr)


def _resume_parser(sub: Subcommands) -> None:
    """The options of `layered resume`: resuming a stopped run or group."""
    rs = sub.add_parser("resume", help="continue a stopped run from its last checkpoint",
                        epilog="the run continues with the recipe and --steps it was started with, but for the "
                        "settings --set changes")
    rs.add_argument("run_dir", type=Path, help="run directory of a stopped run, or of a stopped group or its seeds")
    rs.add_argument("--steps", type=_positive, help="must be the --steps the run was started with (a check)")
    rs.add_argument("--threads", type=_positive, help="torch threads (default: those the run trained with, at most "
                    "this machine's cores)")
    rs.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", dest="settings",
                    help="continue with a changed setting (a layer's learner settings, action_penalty, updates), "
                    "e.g. --set layers.fast.learner.lr=1e-4 after a divergence; in every seed of a group; recorded "
                    "in run.json")


def _eval_parser(sub: Subcommands) -> None:
    """The options of `layered eval`: evaluating a run or a group."""
    ev = sub.add_parser("eval", help="evaluate a trained run directory, or every seed of a group")
    ev.add_argument("run_dir", type=Path, help="run directory of a trained run (of one still training or stopped: "
                    "the phase under way at its best weights so far), or a group's directory: every seed evaluated "
                    "as the group evaluates them, their learners stacked")
    ev.add_argument("--episodes", type=_positive, help="episodes (default: the recipe's eval.episodes)")
    ev.add_argument("--threshold", type=_threshold, help=THRESHOLD_HELP)
    ev.add_argument("--weights", choices=["final", "best"],
                    help="the last phase's final weights or those of its best evaluation (default: the recipe's "
                    "train.select; layers of earlier phases as they were handed on); of a run not finished, final "
                    "takes the phase under way's weights at its last checkpoint")
    ev.add_argument("--fresh", action="store_true",
                    help="on the fresh episodes that training evaluated each phase's final and best weights on "
                    "(seeded train.seed + eval.fresh_seed_offset; default episodes: eval.fresh_episodes), not on "
                    "those of its evaluations during training")
    ev.add_argument("--threads", type=_positive, help="the cores it computes on: torch's threads (default: those the "
                    "run trained with) and those its environments step in (default: every core)")
    _plugin_option(ev, "besides those the run was trained with")
    ev.add_argument("--plot", action="store_true", help="also plot the last episode: who acted when, and the action")
    ev.add_argument("--threshold-sweep", type=_thresholds, nargs="?", const=DEFAULT_SWEEP, metavar="X,Y,...",
                    help="evaluate at each threshold (default 0, 0.1, ..., 1) and plot return and action frequency")
    ev.add_argument("--video", action="store_true",
                    help="write an MP4 per episode (default 1 episode) with a strip of who decided and who acted")
    ev.add_argument("--gallery", nargs="?", const="", metavar="LAYER",
                    help="render the states where LAYER (default: the fastest) acts, as gallery-LAYER.png")


def _export_parser(sub: Subcommands) -> None:
    """The options of `layered export`: exporting a trained stack."""
    ex = sub.add_parser(
        "export", help="write a trained stack as files that run without the training code",
        epilog="then, with torch (or onnxruntime) alone: from layered_runtime import load_stack; "
        "stack = load_stack(DIR); stack.reset(); action = stack.step(obs)",
    )
    ex.add_argument("run_dir", type=Path, help="run directory of a trained run")
    ex.add_argument("--format", choices=["torchscript", "onnx"], default="torchscript",
                    help="policy files for torch alone (default) or for onnxruntime (extra layered-control[onnx])")
    ex.add_argument("--out", type=Path, help="export directory (default RUN_DIR/export-FORMAT)")
    ex.add_argument("--weights", choices=["final", "best"],
                    help="the last phase's final or best weights (default: the recipe's train.select; layers of "
                    "earlier phases as they were handed on)")
    ex.add_argument("--threshold", type=_threshold, help=THRESHOLD_HELP)
    ex.add_argument("--episodes", type=_positive, default=3,
                    help="episodes on which the export is checked against the library and timed (default 3)")
    _plugin_option(ex, "besides those the run was trained with")


def _sweep_parser(sub: Subcommands) -> None:
    """The options of `layered sweep`: a sweep over recipes, settings and seeds."""
    sw = sub.add_parser(
        "sweep", help="train every recipe with several seeds, in parallel processes",
        usage="layered sweep RECIPE... [key=value ...] [--seeds N] [--jobs J] [--threads T] [--out DIR] [--steps N] "
        "[--vectorize [--group-size N]] [--device {cpu,cuda,auto}] [--no-mps] [--backend {local,ray}] [--address ADDR] "
        "[--plugin FILE.py|MODULE]",
        epilog="key=a,b,c trains a setup per value (several such keys: every combination), each in its own "
        "directory; finished runs are skipped and stopped ones resume; then: layered report DIR",
    )
    sw.add_argument("recipes", nargs="+", metavar="RECIPE", help="recipe files (and key=value overrides)")
    sw.add_argument("--seeds", type=_seed_count, default=3, metavar="N",
                    help="seeds 0..N-1 of every setup (default 3); a count, where train --seeds also takes A-B, A,B,C")
    sw.add_argument("--jobs", type=_positive, default=os.cpu_count() or 1, help="parallel processes (default: cores)")
    sw.add_argument("--threads", type=_positive, help="torch threads in each process (default: the cores over the "
                    "processes that run at once; set it where other work shares the machine)")
    sw.add_argument("--out", type=Path, default=Path("runs/sweep"), help="sweep directory (default runs/sweep)")
    sw.add_argument("--steps", type=_positive, help="cap every training phase at N environment steps")
    sw.add_argument("--vectorize", action="store_true",
                    help="train the seeds of each setup as one group, in one process (as train --seeds)")
    sw.add_argument("--group-size", type=_positive, metavar="N",
                    help="with --vectorize: cut each setup's seeds into groups of N, each a process of its own "
                    "(DIR/<setup>/seeds<a>-<b>/seed<k>), so that one setup's groups train at once on their shares "
                    "of the cores, or of a GPU")
    sw.add_argument("--device", choices=["cpu", "cuda", "auto"],
                    help="where the learners run (learner.device); with cuda, the --jobs processes share the GPU, "
                    "under CUDA MPS (started for the sweep where it is installed and not running)")
    sw.add_argument("--no-mps", action="store_true", help="on CUDA, do not start MPS: the workers take turns")
    sw.add_argument("--backend", choices=["local", "ray"], default="local",
                    help="local processes (default) or Ray tasks (needs the extra layered-control[ray])")
    sw.add_argument("--address", help="Ray cluster address (default: start a local Ray)")
    _plugin_option(sw)


def _deploy_parser(sub: Subcommands) -> None:
    """The options of `layered deploy`: deploying a trained stack as processes."""
    dp = sub.add_parser(
        "deploy", help="run a trained stack with each layer in a process of its own, against the clock",
        epilog="writes DIR/<setting>.json, DIR/deploy.md and, over several settings, DIR/deploy.png; "
        "how to read them: docs/distributed.md",
    )
    dp.add_argument("run_dir", type=Path, help="run directory of a trained run")
    dp.add_argument("--speed", type=_speeds, metavar="X,Y,...",
                    help="times real time, one setting per value (default 1)")
    dp.add_argument("--lockstep", action="store_true",
                    help="also (or, without --speed, only) a setting without a clock, as fast as the layers answer: "
                    "the driver waits for every answer, and must execute layered eval's actions (unless a --fault is "
                    "injected)")
    dp.add_argument("--episodes", type=_positive, default=3, help="episodes per setting (default 3)")
    dp.add_argument("--link-delay", action="append", default=[], metavar="[LAYER=]5ms±2ms",
                    help="delay each message to and from a layer (every layer without LAYER=); repeatable")
    dp.add_argument("--fault", action="append", default=[], metavar="LAYER:die@N|LAYER:stall@N",
                    help="make a layer's process die or stall at its N-th request; repeatable")
    dp.add_argument("--on-fault", choices=FAULT_ACTIONS, default="hold",
                    help="when a layer's process dies or stalls: go on without it (default; the slower layers "
                    "act alone, a slower layer's last output stays) or stop")
    dp.add_argument("--weights", choices=["final", "best"],
                    help="the last phase's final or best weights (default: the recipe's train.select; layers of "
                    "earlier phases as they were handed on)")
    dp.add_argument("--threshold", type=_threshold, help=THRESHOLD_HELP)
    dp.add_argument("--out", type=Path, help="where to write (default RUN_DIR/deploy)")
    dp.add_argument("--transport", choices=["process", "ray"], default="process",
                    help="each layer a local process (default) or a Ray actor (extra layered-control[ray])")
    dp.add_argument("--address", help="with --transport ray: the Ray cluster's address (default: start a local Ray)")
    _plugin_option(dp, "besides those the run was trained with")


def _report_parser(sub: Subcommands) -> None:
    """The options of `layered report`: the report over finished runs."""
    rep = sub.add_parser("report", help="aggregate finished runs over seeds into the paper's tables and figures")
    rep.add_argument("runs", type=Path, nargs="+", help="run directories, or folders that hold them")
    rep.add_argument("--unfinished", action="store_true",
                     help="also report runs still training or stopped before their end, each at its last evaluation "
                     "(as setups of their own, marked unfinished)")
    rep.add_argument("--out", type=Path, help="report directory (default runs/report-<time>)")
    rep.add_argument("--no-extra-evals", action="store_true",
                     help="draw only from what the runs hold; by default each run's missing threshold sweep (Fig. 2) "
                     "and gallery are evaluated once and kept in its eval/ folder")
    rep.add_argument("--threads", type=_positive, help="the cores those evaluations compute on: torch's threads and "
                     "those their environments step in (default: every core)")


def _fail(message: str) -> int:
    print(f"layered: error: {message}", file=sys.stderr)
    return EXIT_BAD_INPUT


def _train(args: argparse.Namespace) -> int:
    from layered.recipe import device_settings, load_recipe, recipe_path
    from layered.rundir import check_new_run_dir
    from layered.runs import train

    if (args.seed is not None or args.seeds is not None) and (given := _seed_override(args.overrides)):
        return _fail(f"give the seed once: {'--seed' if args.seed is not None else '--seeds'} or {given}, not both")
    overrides = list(args.overrides) + ([f"train.seed={args.seed}"] if args.seed is not None else [])
    overrides += ["log.tensorboard=true"] if args.tensorboard else []
    plugins = load_plugins(args.plugin)
    overrides += device_settings(args.recipe, overrides, args.device) if args.device else []
    if args.seeds is not None:
        return _train_group(args, overrides, plugins)
    recipe = load_recipe(args.recipe, overrides)
    source = recipe_path(args.recipe)
    out = args.out or Path("runs") / f"{source.stem}-s{recipe.train.seed}-{time.strftime('%Y%m%d-%H%M%S')}"
    args.out = out
    if not args.force:
        check_new_run_dir(out)
    print(f"training {args.recipe} -> {out}", file=sys.stderr)
    train(recipe, out, max_steps=args.steps, label=_label(source), plugins=plugins, force=args.force)
    return _finished(out)


def _seed_override(overrides: Sequence[str]) -> str | None:
    """The override among `overrides` that sets train.seed, if any."""
    return next((o for o in overrides if o.partition("=")[0].strip() == "train.seed"), None)


def _label(source: Path) -> str:
    """A run's label (its setup in reports): `<folder>/<name>` of its recipe file, as a sweep labels it."""
    from layered.sweep import recipe_labels

    path = source.resolve()
    return recipe_labels([path])[path]


def _train_group(args: argparse.Namespace, overrides: list[str], plugins: list[str]) -> int:
    from layered.group import check_group, group_recipes, train_group
    from layered.recipe import recipe_path

    if args.seed is not None:
        return _fail("give --seed or --seeds, not both")
    recipes = group_recipes(args.recipe, args.seeds, overrides)
    check_group(recipes[0])
    source = recipe_path(args.recipe)
    out = args.out or Path("runs") / f"{source.stem}-group-{time.strftime('%Y%m%d-%H%M%S')}"
    args.out = out  # (stopped at once, it is resumed from here)
    outs = [out / f"seed{seed}" for seed in args.seeds]
    print(f"training {args.recipe}, seeds {args.seeds} as one group -> {out}", file=sys.stderr)
    results = train_group(recipes, outs, _label(source), args.steps, plugins=plugins, force=args.force)
    return _group_finished(out, args.seeds, results)


def _group_finished(out: Path, seeds: Sequence[int], results: list[list[dict[str, Any]]]) -> int:
    for seed, rows in zip(seeds, results, strict=True):
        print(f"seed {seed}: " + ", ".join(f"phase {row['phase']} return {row['return_mean']:.1f}" for row in rows))
    print(f"run directories: {out}/seed<k>; tables and figures: layered report {out}")
    return 0


def _resume(args: argparse.Namespace) -> int:
    from layered.group_state import group_dir
    from layered.rundir import RUN_CHECKPOINT, read_run_info
    from layered.runs import resume

    if (directory := group_dir(args.run_dir)) is not None:
        return _resume_group(args, directory)
    info = read_run_info(args.run_dir)
    load_plugins(info.plugins)
    _threads_as_trained(args, info)
    results = args.run_dir / "results.json"
    if results.exists() and (_readable(results) or not (args.run_dir / RUN_CHECKPOINT).exists()):
        return _nothing_to_resume(args, info, f"{args.run_dir} has finished")
    if results.exists():
        print(f"layered: {results} is damaged; writing the run's results again from its last checkpoint",
              file=sys.stderr)
    print(f"resuming {args.run_dir}", file=sys.stderr)
    resume(args.run_dir, max_steps=args.steps, settings=args.settings)
    return _finished(args.run_dir)


def _nothing_to_resume(args: argparse.Namespace, info: RunInfo, finished: str) -> int:
    """A finished run or group resumed: nothing to do (0), but for what the command asked that a stopped one would
    have refused or changed (2): another --steps, a --set."""
    from layered.rundir import steps_option

    if args.steps is not None and args.steps != info.max_steps:
        return _fail(f"{finished}; it was started with {steps_option(info.max_steps)}, not {steps_option(args.steps)}")
    if args.settings:
        return _fail(f"{finished}; --set changes the settings a stopped run continues with, and a finished one "
                     "continues no further")
    print(f"{finished}; nothing to resume", file=sys.stderr)
    return 0


def _readable(path: Path) -> bool:
    """Whether a JSON file reads whole."""
    try:
        json.loads(path.read_text())
    except (ValueError, UnicodeDecodeError):
        return False
    return True


def _resume_group(args: argparse.Namespace, directory: Path) -> int:
    from layered.group import resume_group
    from layered.group_state import group_info, seed_dirs

    info = group_info(directory)
    load_plugins(info.plugins)
    _threads_as_trained(args, info)
    if all((out / "results.json").exists() for out in seed_dirs(directory, info.group)):
        return _nothing_to_resume(args, info, f"the group in {directory} has finished")
    print(f"resuming the group of seeds {list(info.group)} in {directory}", file=sys.stderr)
    return _group_finished(directory, info.group, resume_group(directory, max_steps=args.steps,
                                                               settings=args.settings))


def _threads_as_trained(args: argparse.Namespace, info: RunInfo) -> None:
    """Compute with the torch threads the run trained with where `--threads` does not say (at most this machine's
    cores): the products of an evaluation sum in an order that depends on them, and so do its numbers' last digits."""
    from layered.cores import trained_threads

    threads = trained_threads(info.threads)
    if args.threads is None and threads is not None:
        import torch

        torch.set_num_threads(threads)


def _finished(out: Path) -> int:
    print((out / "results.md").read_text())
    print(f"run directory: {out} (results.json, metrics.csv, curves.png, checkpoints/)")
    return 0


def _eval(args: argparse.Namespace) -> int:
    from layered.group_state import group_dir
    from layered.rundir import read_run_info
    from layered.run_evals import gallery, open_run, threshold_sweep

    if group_dir(args.run_dir) == args.run_dir:
        return _eval_group(args)
    run = replace(open_run(args.run_dir, args.weights, args.plugin, unfinished=True), fresh=args.fresh)
    _threads_as_trained(args, read_run_info(args.run_dir))
    _note_if_no_threshold(args, run)
    if args.gallery == "":
        args.gallery = run.active[-1]
    if args.gallery is not None and args.gallery not in run.active:
        return _fail(f"--gallery: no layer {args.gallery!r} in this stack; layers: {', '.join(run.active)}")
    episodes = args.episodes or run.episodes
    if args.threshold_sweep:
        _print_sweep(*threshold_sweep(run, args.threshold_sweep, episodes), run)
    if args.threshold is not None or args.plot or not (args.threshold_sweep or args.video):
        _evaluate_once(args, run, episodes)
    if args.video:
        from layered.video import write_videos

        try:
            videos = write_videos(run.recipe, run.learners, run.active, run.eval_dir, args.episodes or 1, run.seed,
                                  args.threshold)
        except ValueError as e:
            return _fail(f"--video: {e}")
        for path, ret in videos:
            print(f"video: {path} (return {ret:.1f})")
    if args.gallery is not None:
        png, acted, steps, shown = gallery(run, args.gallery, episodes, args.threshold)
        print(f"{args.gallery!r} acted at {acted} of the {steps} steps of {episodes} episode{'s' * (episodes > 1)} "
              f"({acted / max(steps, 1):.0%}); the {shown} most different states: {png}")
    return 0


def _note_if_no_threshold(args: argparse.Namespace, run: Any) -> None:
    """Say so where thresholds are asked for and no layer of the run's stack has a contribution they hold back."""
    from layered.stack import has_threshold

    if (args.threshold is not None or args.threshold_sweep) and not has_threshold(run.recipe, run.active):
        print(f"layered: note: no layer of this stack ({', '.join(run.active)}) has a contribution that a threshold "
              "holds back, so every threshold evaluates the same", file=sys.stderr)


def _eval_group(args: argparse.Namespace) -> int:
    """Every seed of the group in `args.run_dir` evaluated as the group evaluates them (`evaluate_group_runs`), each
    seed's row written to its own eval folder."""
    from layered.group_state import group_info
    from layered.run_evals import evaluate_group_runs, open_group

    one_run = [flag for flag, given in (("--plot", args.plot), ("--threshold-sweep", args.threshold_sweep),
                                        ("--video", args.video), ("--gallery", args.gallery is not None)) if given]
    if one_run:
        return _fail(f"{', '.join(one_run)}: of one run; {args.run_dir} is a group: name one of its seeds "
                     f"({args.run_dir / 'seed<k>'})")
    runs = open_group(args.run_dir, args.weights, args.plugin, args.fresh)
    _threads_as_trained(args, group_info(args.run_dir))
    _note_if_no_threshold(args, runs[0])
    episodes = args.episodes or runs[0].episodes
    results = evaluate_group_runs(runs, episodes, args.threshold, progress=True)
    written = [_write_evaluation(args, run, episodes, result, "-group") for run, result in zip(runs, results,
                                                                                              strict=True)]
    print(results_table([{**row, "phase": run.path.name} for run, (row, _) in zip(runs, written, strict=True)]))
    returns = [result.return_mean for result in results]
    mean, std = statistics.fmean(returns), statistics.pstdev(returns)
    names = {path.relative_to(run.path) for run, (_, path) in zip(runs, written, strict=True)}
    same = len(names) == 1  # (else each seed's weights are named by its own best step)
    over = args.run_dir / (names.pop() if same else Path("eval") / written[0][1].name)  # the seeds' mean, kept
    over.parent.mkdir(parents=True, exist_ok=True)
    over.write_text(json.dumps({"seeds": [run.recipe.train.seed for run in runs], "returns": returns,
                                "return_mean": mean, "return_std": std,
                                "files": [str(path.relative_to(args.run_dir)) for _, path in written]}, indent=2))
    print(f"over the {len(runs)} seeds: return {mean:.1f} ± {std:.1f} (population std): {over}")
    print(f"each seed's row: {written[0][1]}, " + ("and the same name in each seed's run directory" if same else
                                                    "and each seed's own eval folder (weights named by its best step)"))
    return 0


def _write_evaluation(args: argparse.Namespace, run: Any, episodes: int, result: Any,
                      suffix: str = "") -> tuple[dict[str, Any], Path]:
    """The run's evaluation `result` as a results row, written to its eval folder (`suffix`: after the file's name);
    the row and its file."""
    threshold = args.threshold if args.threshold is not None else "recipe"
    row = {"phase": "eval", "learn": [], "active": run.active, "auc": None, "threshold": threshold,
           "episodes": episodes, **result.row()}
    out = run.eval_dir / f"threshold-{threshold}-episodes-{episodes}{suffix}.json"
    out.write_text(json.dumps(row, indent=2))
    return row, out


def _evaluate_once(args: argparse.Namespace, run: Any, episodes: int) -> None:
    """The run's evaluation over `episodes` episodes, played side by side as its training's evaluations are;
    with --plot, the last of them played again through the agent view, for its trace."""
    from layered.run_evals import evaluate_trained

    result = evaluate_trained(run, episodes, args.threshold, progress=True)
    row, out = _write_evaluation(args, run, episodes, result)
    print(results_table([row]))
    print(f"written to {out}")
    if args.plot:
        png = out.with_suffix(".png")
        _plot_last_episode(args, run, episodes, png)
        print(f"episode plot: {png}")


def _plot_last_episode(args: argparse.Namespace, run: Any, episodes: int, png: Path) -> None:
    """Who acted when in the last episode of the evaluation, played again through the agent view."""
    from layered.agents import make_aec_env
    from layered.evaluate import episode_seeds, run_episode

    env = make_aec_env(run.recipe, active=run.active, evaluation=True, threshold=args.threshold, keep_trace=True)
    try:
        measures = run_episode(env, run.learners, episode_seeds(run.seed, episodes)[-1])
        at = "the recipe's threshold" if args.threshold is None else f"threshold {args.threshold:g}"
        plot_episode(env.trace, env.possible_agents, png, f"{run.title}: episode {episodes - 1} (the last of "
                     f"{episodes}), return {measures.ret:.1f}, {at}", (env.stack.low, env.stack.high))
    finally:
        env.close()


def _print_sweep(rows: list[dict[str, Any]], written: Path, run: Any) -> None:
    from layered.report import plot_threshold_sweep
    from layered.stack import has_threshold

    none = "" if has_threshold(run.recipe, run.active) else "; no threshold applies to this stack: the lines are flat"
    plot_threshold_sweep(rows, written.with_suffix(".png"), f"{run.title}: threshold sweep "
                         f"({count(rows[0]['episodes'], 'episode')} at each threshold{none})")
    print("| threshold | return | action repetition | decisions |\n|---|---|---|---|")
    for r in rows:
        print(f"| {r['threshold']:g} | {r['return_mean']:.1f} ± {r['return_std']:.1f} | {r['repetition']:.1%} "
              f"| {r['decisions']:.1f} |")
    print(f"written to {written} and {written.with_suffix('.png').name}")


def _export(args: argparse.Namespace) -> int:
    import torch

    from layered.export import export_stack
    from layered.latency import compare
    from layered.run_evals import open_run

    if args.format == "onnx" and not _installed("onnxruntime", "onnxscript"):
        return _fail("--format onnx needs the extra layered-control[onnx]: pip install -e '.[onnx]' in the checkout")
    run = open_run(args.run_dir, args.weights, args.plugin)
    recipe, learners, active = run.recipe, run.learners, run.active
    out = args.out or args.run_dir / f"export-{args.format}"
    torch.set_num_threads(1)  # decisions are timed on one core, as on a robot's controller
    if out.is_dir():  # an earlier export's check stands for none of this one's files
        (out / "check.json").unlink(missing_ok=True)
    export_stack(recipe, learners, active, out, args.format, args.threshold)
    print(f"exported {', '.join(active)} ({args.format}) to {out}")
    result = compare(recipe, learners, active, out, args.episodes, run.seed,
                     args.threshold)
    how = {"run": str(args.run_dir.resolve()), "weights": run.weights or recipe.train.select,
           "threshold": args.threshold}
    (out / "check.json").write_text(json.dumps({**how, **result.row()}, indent=2) + "\n")
    verdict = "the same executed actions" if result.matches else "DIFFERENT executed actions"
    print(f"checked against the library on the observations of {result.episodes} episodes ({result.steps} steps): "
          f"{verdict} (largest difference {result.max_difference:.2g}, tolerance {result.tolerance:.2g} for "
          f"float32 kernels); return closed loop: library {result.library_return:.1f}, "
          f"exported {result.exported_return:.1f}")
    print("| time per base step, one thread | median µs | p99 µs |\n|---|---|---|")
    for name, latency in (("library (agent view)", result.library), (f"exported ({args.format})", result.exported)):
        print(f"| {name} | {latency.median_us:.1f} | {latency.p99_us:.1f} |")
    print(f"written to {out / 'check.json'}; how to run it: docs/deploy.md")
    return 0 if result.matches else 1


def _deploy(args: argparse.Namespace) -> int:
    import torch

    from layered.deploy_run import deploy, table
    from layered.run_evals import open_run

    if args.address and args.transport != "ray":
        return _fail("--address names a Ray cluster: give it with --transport ray")
    run = open_run(args.run_dir, args.weights, args.plugin)
    try:
        links = _per_layer(args.link_delay, "=", Link.parse, run.active, "--link-delay", bare_for_all=True)
        faults = _per_layer(args.fault, ":", Fault.parse, run.active, "--fault", bare_for_all=False)
    except ValueError as e:
        return _fail(str(e))
    speeds = args.speed or ([] if args.lockstep else [1.0])
    settings = ([Settings(lockstep=True, links=links, faults=faults, on_fault=args.on_fault)] if args.lockstep
                else []) + [Settings(speed, False, links, faults, args.on_fault) for speed in speeds]
    out = args.out or args.run_dir / "deploy"
    torch.set_num_threads(1)
    before = signal.signal(signal.SIGTERM, _stopped_by_sigterm)  # (unwinding, every layer's process is stopped)
    try:
        rows = deploy(run, settings, args.episodes, out, args.threshold, transport=args.transport,
                      address=args.address)
    except RuntimeError as e:  # Ray is not installed
        return _fail(str(e))
    finally:
        signal.signal(signal.SIGTERM, before)  # (for a caller of `main` in its own process)
    print(table(rows))
    plotted = sum(1 for row in rows if row["episodes"]) > 1
    print(f"written to {out}: deploy.md{', deploy.png' if plotted else ''} and one JSON file per setting played")
    stopped = args.on_fault == "stop" and any(row["faults"] for row in rows)
    unequal = [row["setting"] for row in rows
               if row["lockstep"] and not row["faults"] and not row["same_actions_as_eval"]]
    if unequal:
        print("layered: lockstep did not execute layered eval's actions", file=sys.stderr)
    return 1 if stopped or unequal else 0


def _stopped_by_sigterm(signum: int, frame: Any) -> NoReturn:
    """A deployment's SIGTERM: one line, as a Ctrl-C's, then exit 143 (stopping every layer's process)."""
    print("\nlayered: SIGTERM: stopped at once; every layer's process is stopped; the settings that finished are "
          "written", file=sys.stderr)
    sys.exit(EXIT_SIGNAL["SIGTERM"])


def _per_layer(values: list[str], separator: str, parse: Callable[[str], Any], layers: list[str],
               option: str, bare_for_all: bool) -> dict[str, Any]:
    """`LAYER<sep>value` entries parsed per layer name; with `bare_for_all`, a bare value is that of every layer not
    named. A layer given twice (or two bare values) is refused, rather than the last one silently taking over."""
    named, bare = {}, []
    for value in values:
        name, found, text = value.partition(separator)
        if not found and bare_for_all:
            bare.append(parse(value))
            continue
        if not found or name not in layers:
            raise ValueError(f"{option} {value!r}: name a layer of this stack ({', '.join(layers)}) "
                             f"as LAYER{separator}…")
        if name in named:
            raise ValueError(f"{option}: layer {name!r} is given twice; give it once")
        named[name] = parse(text)
    if len(bare) > 1:
        raise ValueError(f"{option}: {len(bare)} values for every layer; give one (and LAYER{separator}… for a layer "
                         "of its own)")
    return {**{layer: bare[0] for layer in layers if bare}, **named}


def _speeds(text: str) -> list[float]:
    try:
        speeds = [float(part) for part in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: expected numbers, e.g. 1,2,5,10 (--lockstep: as fast as "
                                         "possible)") from None
    if not all(0 < speed < math.inf for speed in speeds):
        raise argparse.ArgumentTypeError(f"{text!r}: a speed must be above 0 and finite")
    return speeds


def _installed(*modules: str) -> bool:
    import importlib.util

    return all(importlib.util.find_spec(m) is not None for m in modules)


def _report(args: argparse.Namespace) -> int:
    from layered.report import write_report
    from layered.summary import find_runs, group

    if args.out is not None and args.out.exists() and not args.out.is_dir():
        return _fail(f"{args.out}: is a file, not a directory")  # (before any evaluation it would follow)
    try:
        runs = find_runs(args.runs, args.unfinished)
    except FileNotFoundError as e:
        return _fail(str(e))
    if not args.no_extra_evals:
        from layered.run_evals import missing_figure_evals, run_figure_evals

        todo = [(r.path, missing) for r in runs if r.finished and (missing := missing_figure_evals(r.path))]
        for k, (path, missing) in enumerate(todo):
            print(f"[{k + 1}/{len(todo)}] {path}: evaluating {' and '.join(missing)}", file=sys.stderr)
            run_figure_evals(path, missing)
    setups = group(runs)
    out = args.out or Path("runs") / f"report-{time.strftime('%Y%m%d-%H%M%S')}"
    print(write_report(setups, out))
    print(f"report directory: {out} (report.md, summary.csv, seeds.csv, comparisons.csv, across-envs.csv, curves.csv, "
          "curves.png and the figures report.md shows)")
    return 0


def _sweep(args: argparse.Namespace) -> int:
    from layered.cuda_mps import shared_gpu
    from layered.sweep import on_gpu, plan, process_count, run_local, run_ray

    overrides = [a for a in args.recipes if "=" in a] + args.overrides
    if given := _seed_override(overrides):
        return _fail(f"{given}: a sweep gives each run its seed (--seeds N: seeds 0..N-1)")
    recipes = [a for a in args.recipes if "=" not in a]
    plugins = load_plugins(args.plugin)
    if args.group_size is not None and not args.vectorize:
        return _fail("--group-size cuts a setup's seeds into groups: it needs --vectorize")
    if args.address and args.backend != "ray":
        return _fail("--address names a Ray cluster: give it with --backend ray")
    if args.threads is not None and args.backend == "ray":
        return _fail("--threads sets the threads of local processes; a Ray task computes on one thread")
    jobs = plan(recipes, args.seeds, args.out, overrides, args.steps, plugins, args.group_size, args.device)
    if args.vectorize:
        from layered.group import check_group
        from layered.recipe import load_recipe
        from layered.schema import RecipeError

        if args.backend == "ray":
            return _fail("--vectorize runs groups in local processes; it does not combine with --backend ray")
        for job in {job.label: job for job in jobs}.values():
            try:
                check_group(load_recipe(job.recipe))
            except RecipeError as e:
                raise e.named(f"{job.label} (--vectorize)") from None
    if args.backend == "ray":
        try:
            outcomes = run_ray(jobs, args.address)
        except RuntimeError as e:
            return _fail(str(e))
    else:
        processes = process_count(jobs, args.jobs, args.vectorize)
        with shared_gpu(processes if on_gpu(jobs) and not args.no_mps else 1) as line:
            if line is not None:
                print(f"layered: note: {line}", file=sys.stderr)
            outcomes, stop = run_local(jobs, args.jobs, args.vectorize, args.threads)
        if stop.received:
            print(f"layered: {stop.summary()}", file=sys.stderr)
            return EXIT_SIGNAL[stop.received[0]]
    failed = [o for o in outcomes if o.status == "failed"]
    print(f"{len(outcomes) - len(failed)} of {len(jobs)} runs finished in {args.out}; "
          f"tables and figures: layered report {args.out}")
    return 1 if failed else 0


COMMANDS = {"train": _train, "resume": _resume, "eval": _eval, "export": _export, "sweep": _sweep, "report": _report,
            "deploy": _deploy}
# The modules each command runs on, with what they import (torch, the learners, the environments: seconds).
LOADS = {"train": ("layered.runs", "layered.group"), "resume": ("layered.runs", "layered.group"),
         "eval": ("layered.run_evals",), "export": ("layered.export",), "sweep": ("layered.sweep",),
         "report": ("layered.summary",), "deploy": ("layered.deploy_run",)}


def main(argv: list[str] | None = None) -> int:
    """Entry point; returns 2 on bad input with one line per problem and no traceback, 1 when
    training diverged, 130 or 143 when SIGINT or SIGTERM stopped it."""
    return run(parse(argv))


def parse(argv: list[str] | None = None) -> argparse.Namespace:
    """The command line's arguments, its `key=value` settings as `overrides`; a usage error exits with 2."""
    parser = _parser()
    if not (sys.argv[1:] if argv is None else argv):  # a bare `layered`: what it can do
        parser.print_help(sys.stderr)
        raise SystemExit(EXIT_BAD_INPUT)
    args, extra = parser.parse_known_args(_run_dir_first(sys.argv[1:] if argv is None else argv))
    unknown = [a for a in extra if a.startswith("-") or "=" not in a or args.command not in ("train", "sweep")]
    if unknown:
        hint = (" (a stopped run's setting is changed with --set KEY=VALUE)" if args.command == "resume" and
                any("=" in a and not a.startswith("-") for a in unknown) else "")
        print(f"layered: error: unrecognized arguments: {' '.join(unknown)}{hint} (see layered {args.command} --help)",
              file=sys.stderr)
        raise SystemExit(EXIT_BAD_INPUT)
    args.overrides = extra
    return args


def _run_dir_first(argv: list[str]) -> list[str]:
    """`eval --gallery RUN` (or `--threshold-sweep RUN`): the option, whose value may be left out, would take the
    run directory as the layer's name; a value that is a run's or a group's directory is taken as RUN instead."""
    optional_values = ("--gallery", "--threshold-sweep")
    if argv[:1] != ["eval"]:
        return argv
    for i, token in enumerate(argv[1:-1], start=1):
        value = Path(argv[i + 1])
        if token in optional_values and ((value / "run.json").exists() or any(value.glob("seed*/run.json"))):
            return [argv[0], argv[i + 1], *argv[1:i + 1], *argv[i + 2:]]
    return argv


def load(args: argparse.Namespace) -> None:
    """Import what the parsed command runs on, so that `layered.command` can do it while Ctrl-C is held."""
    import importlib

    for module in LOADS[args.command]:
        importlib.import_module(module)


def run(args: argparse.Namespace) -> int:
    """Carry out a parsed command line, as `main` says."""
    from layered.cores import cores_given

    if getattr(args, "threads", None):
        import torch

        torch.set_num_threads(args.threads)
    evaluating = args.command in ("eval", "report")  # (an evaluation's environments step on its cores too)
    try:
        with cores_given(getattr(args, "threads", None) if evaluating else None):
            return COMMANDS[args.command](args)
    except (BadInput, LayerFault) as e:  # an input it cannot use; a layer's process that died or stalled
        from layered.recipe import recipe_label
        from layered.schema import RecipeError

        if isinstance(e, RecipeError) and args.command == "train":  # (checked where the recipe's file is not known)
            e = e.named(recipe_label(args.recipe, args.overrides))
        for line in str(e).splitlines():
            _fail(line)
        return EXIT_BAD_INPUT
    except Stopped as e:
        print(f"layered: {e}", file=sys.stderr)
        return EXIT_SIGNAL.get(e.signal_name, 1)
    except Diverged as e:
        print(f"layered: diverged: {e}", file=sys.stderr)
        return EXIT_DIVERGED
    except KeyboardInterrupt:
        print(f"\nlayered: stopped at once; {_how_to_continue(args)}", file=sys.stderr)
        return EXIT_SIGNAL["SIGINT"]
    except OSError as e:  # e.g. an --out that cannot be created
        if isinstance(e, (FileExistsError, NotADirectoryError)) and e.filename and Path(e.filename).is_file():
            return _fail(f"{e.filename}: is a file, not a directory")
        if e.filename:
            return _fail(f"{e.filename}: {e.strerror or e}")
        return _fail(f"{e.strerror or e} (writing {getattr(args, 'out', None) or getattr(args, 'run_dir', '')}); "
                     f"{_how_to_continue(args)}")


def _how_to_continue(args: argparse.Namespace) -> str:
    if args.command == "sweep":
        return "running the same sweep again resumes every run from its last checkpoint"
    if args.command == "deploy":
        return "every layer's process was stopped; the settings that finished are written"
    if args.command == "export":
        out = args.out or args.run_dir / f"export-{args.format}"
        return f"{out} may hold an export that was not checked (it has no check.json); run the same command again"
    run = getattr(args, "out", None) or getattr(args, "run_dir", None)
    if run is not None and ((run / "run.json").exists() or any(run.glob("seed*/run.json"))):
        return f"continue from the last checkpoint with: layered resume {run}"
    return "nothing was saved; run the same command again"


if __name__ == "__main__":
    sys.exit(main())
