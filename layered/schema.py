"""The recipe schema: typed, frozen sections with a one-line docstring per key, and the wording of
their errors, which name the source, the key and what was expected."""

from __future__ import annotations

from collections.abc import Iterable, Iterator, Mapping
from typing import Any, Literal, get_args

from pydantic import BaseModel, ConfigDict, Field, ValidationInfo, field_validator, model_validator

from layered.combiners import COMBINERS
from layered.envs import env_info
from layered.errors import BadInput
from layered.learners import LEARNERS, Flag, LearnerConfig, Whole
from layered.outputs import OutputLayout


class RecipeError(BadInput, ValueError):
    """A recipe that cannot be used; each line names the source, the key (None: the file as a whole) and
    what was expected."""

    UNNAMED = "recipe"
    """The source of a recipe checked where its file is not known (a built recipe's weights, settings)."""

    def __init__(self, source: str, problems: Iterable[tuple[str | None, str]]) -> None:
        self.source, self.problems = source, list(problems)
        self.lines = [f"{source}: {message}" if key is None else f"{source}: {key or '(top level)'}: {message}"
                      for key, message in self.problems]
        super().__init__("\n".join(self.lines))

    def named(self, source: str) -> RecipeError:
        """The same problems named by `source` (the file and how it was changed), where they had no source."""
        return RecipeError(source, self.problems) if self.source == self.UNNAMED else self


class Section(BaseModel):
    """Base of every recipe table: frozen, unknown keys are errors, attribute docstrings documented."""

    model_config = ConfigDict(extra="forbid", frozen=True, use_attribute_docstrings=True, allow_inf_nan=False)


class EnvConfig(Section):
    """The environment every layer controls."""

    id: str
    """Environment id, `family:name`; a bare name is a Gymnasium id, e.g. `Pendulum-v1`."""
    return_range: tuple[float, float] | None = None
    """(worst, best) return that normalises the AUC; defaults to the environment registry's."""
    workers: Whole | Literal["auto"] = "auto"
    """Processes that step a group's environments (`layered train --seeds`), several each: 0 steps them
    in the training process; `auto` takes half the cores on machines with 4 or more, else 0. Where they
    step changes no number. A single run's evaluation episodes step in its own process."""
    threads: Whole | Literal["auto"] = "auto"
    """Threads that step a group's environments in each process that steps them (the training process, or
    each worker), a slice of the rows each, and a single run's evaluation episodes played side by side;
    MuJoCo's step runs in parallel in them. 0 steps the rows in the
    process's own thread. `auto`: while training, one in the training process (the rows step beside the
    update) where it has 2 cores or more, and none in workers; for evaluations of Gymnasium's MuJoCo tasks,
    the cores shared out among the processes that step the rows. Where they step changes no number."""
    wait: Literal["auto", "sleep", "spin"] = "auto"
    """How a group's training process and its environment workers wait for each other: `sleep` in their pipes
    (no core used meanwhile), `spin` polling them (an answer within microseconds, a core kept busy by each
    waiting process); `auto` spins where the learners are on a GPU and each worker and the training process
    has a core of its own with one to spare, else sleeps. How they wait changes no number."""

    @field_validator("workers", "threads", mode="before")
    @classmethod
    def _count_or_auto(cls, value: Any, info: ValidationInfo) -> Any:
        if value != "auto" and not (isinstance(value, int) and not isinstance(value, bool) and value >= 0):
            raise ValueError(f"give a number of {'processes' if info.field_name == 'workers' else 'threads'}, "
                             f"0 or more, or 'auto' (got {value!r})")
        return value

    @field_validator("return_range")
    @classmethod
    def _worst_below_best(cls, value: tuple[float, float] | None) -> tuple[float, float] | None:
        if value is not None and not value[0] < value[1]:
            raise ValueError(f"the worst return must be below the best, as [worst, best] (got {list(value)})")
        return value


class CombineConfig(Section):
    """The default combiner of every layer, and its evaluation threshold."""

    kind: str = "residual-clip"
    """Combiner name: `residual-clip` or `gate` (or any registered one)."""
    eval_threshold: float = Field(default=0.3, ge=0)
    """At evaluation, lower residual contributions whose effect is below this fraction of the
    maximum action are zeroed; 0 disables thresholding."""
    per_dimension: Flag = False
    """Threshold each action dimension on its own instead of all dimensions together."""


class LayerConfig(Section):
    """One controller of the stack; layers are listed slowest first."""

    name: str = Field(pattern=r"^[A-Za-z_][A-Za-z0-9_-]*$")
    """Unique name, used in `sees`, in phases and as the agent's name."""
    period: Whole | None = Field(default=None, gt=0)
    """Base environment steps between decisions; must divide the period of the layer above."""
    response_time: float | None = Field(default=None, gt=0)
    """The period in seconds instead of steps; must be a whole number of the env's control timestep."""
    delay: Whole = Field(default=0, ge=0)
    """Decisions between choosing an action and its taking effect (1: the real-time setting)."""
    max_repeat: Whole = Field(default=1, ge=1)
    """Above 1 the layer also chooses for how many of its periods (1..max_repeat) to hold its
    output before deciding again, as TempoRL's skip policy; its output gains that count."""
    sees: list[str] = ["obs"]
    """What the layer observes: `obs` and the names of slower layers whose held actions it sees."""
    sees_in_flight: Flag | None = None
    """With a delay: the layer also sees, beside each of its outputs in flight, the outputs of the slower
    layers it sees that will act with it when it lands, so that it knows every action on its way to the
    environment (the delayed problem is then Markov at every step; without it, a layer whose slower layer
    decides between its own decisions does not see that layer's output acting now). Unset is false."""
    sees_executed: Flag | None = None
    """With a delay: the layer sees each of its outputs in flight as the action the environment will execute
    when it lands (with the other layers' outputs for that step, as far as they are decided), not as its own
    part of it: a slow layer then knows the faster layers' corrections on their way, as the paper authors'
    real-time code shows every layer the executed action. Alone in a stack it sees the same. Unset is false."""
    combine: str | None = None
    """How this layer merges with the layers below; defaults to `combine.kind`."""
    eval_threshold: float | None = Field(default=None, ge=0)
    """Overrides `combine.eval_threshold` for what this layer's combiner admits from the layer right below it (a
    residual combiner's; each layer further below is thresholded by the combiner of the layer above it)."""
    action_scale: float = Field(default=1.0, gt=0)
    """The layer's action range as a multiple of the environment's (2 lets a residual cancel)."""
    action_penalty: float = Field(default=0.0, ge=0)
    """Reward penalty per step: this times the mean of |action| / the layer's action bound."""
    action_penalty_unit: Literal["reward", "reward-per-step"] = "reward"
    """`reward`: the penalty is in the environment's reward (the paper's); `reward-per-step`: in
    units of its return range per step ((best - worst return) / episode steps), so one value
    weighs the same against tasks of other reward scales."""
    action_penalty_from: Literal["landing", "decision"] | None = None
    """With a delay, when the penalty on an output is paid: while it acts (`landing`, unset), or from the
    step it is chosen, while it is in flight (`decision`), so that the transition of the decision that
    chose it pays it, as the paper authors' real-time code charges the fast action."""
    defer_reward_scale: tuple[float, float] = (2.0, 0.5)
    """Gate layers: factors on rewards r <= 0 and r > 0 earned while the layers below act."""
    defer_penalty: float = Field(default=0.0, ge=0)
    """Gate layers: reward penalty per base step while the layers below act (p per step)."""
    deviation_penalty: float = Field(default=0.0, ge=0)
    """Reward penalty per step: this times mean |executed action - action proposed by the
    nearest deferring gate at or above this layer| / max action (j)."""
    warmup: Whole | None = Field(default=None, ge=0)
    """Decisions this layer takes uniformly at random before it learns; default `train.warmup`."""
    updates: Whole = Field(default=1, gt=0)
    """Gradient updates of the layer's learner after each of its decisions once it learns; with
    `updates = period`, one per base step, as the authors' jointly trained slow layer and gate make."""
    learn_from_commits: Flag = False
    """For the layer right below a gate: in training, while the gate commits, the layer still
    decides at its period, and the gate's committed action (in a two-layer stack, the executed action)
    is recorded as its decision, so that it learns from every step, as the authors' jointly trained
    fast layer does (otherwise it learns only from the steps it acts on). Evaluation never asks it
    while the gate commits. Needs `delay = 0`, `max_repeat = 1` and no gate of the layer's own; while a
    gate higher up commits, the layer is not asked."""
    weights: str | None = None
    """A checkpoint the layer starts from instead of new networks: another run's
    `checkpoints/<name>.best.pt` or `<name>.pt` (a path relative to the recipe file that sets it).
    `{seed}` in it stands for the run's seed, so that each seed of a group or a sweep starts from its
    own (e.g. `runs/rt/tla/seed{seed}/checkpoints/slow.best.pt`). The run keeps a copy, so a layer
    that only acts here needs no phase of its own."""
    learner: dict[str, Any] = {}
    """Learner settings for this layer, over the recipe's `[learner]` table."""


class PhaseConfig(Section):
    """One training phase of an explicit order."""

    learn: list[str] = Field(min_length=1)
    """Layers that learn in this phase."""
    active: list[str] | None = None
    """Layers present in this phase (the `learn` layers among them); default: `learn` plus every layer trained
    before. A present layer must learn in some phase or start from `weights`."""
    steps: Whole | None = Field(default=None, gt=0)
    """Base environment steps of this phase; default `train.steps_per_phase`."""


class TrainConfig(Section):
    """How the stack is trained."""

    order: str = "slow-to-fast"
    """Training order: `slow-to-fast`, `fast-to-slow`, `joint` (every layer learns at once, in one
    phase), or `explicit` (with `phases`); or any registered one."""
    phases: list[PhaseConfig] | None = None
    """Explicit phases; giving them selects the `explicit` order."""
    steps_per_phase: Whole = Field(default=30_000, gt=0)
    """Base environment steps per phase."""
    checkpoint_every: Whole | None = Field(default=None, gt=0)
    """Environment steps between checkpoints of the whole training state, each taken at the next
    episode end; default `eval.every`. A stopped run resumes from its last checkpoint."""
    select: Literal["final", "best"] = "final"
    """Which weights of a finished phase's learning layers later phases and `layered eval` use:
    those at the phase's end (`final`) or at its best evaluation (`best`, the paper authors'
    protocol). Both are saved, and both are evaluated again on fresh episodes (eval.fresh_episodes)."""
    warmup: Whole = Field(default=1000, ge=0)
    """Decisions of each learning layer taken uniformly at random before updates start (a
    layer's own `warmup` overrides it)."""
    discount: Literal["decision", "step"] = "decision"
    """`decision`: gamma per decision of a layer; `step`: gamma**k for a decision spanning k steps."""
    seed: Whole = Field(default=0, ge=0, le=2**32 - 1)
    """Seed of the environment, the networks and the exploration, 0 to 2**32 - 1."""

    @model_validator(mode="before")
    @classmethod
    def _phases_select_explicit(cls, data: Any) -> Any:
        if isinstance(data, dict) and data.get("phases") is not None and "order" not in data:
            return {**data, "order": "explicit"}
        return data


class EvalConfig(Section):
    """How the stack is evaluated during and after training."""

    every: Whole = Field(default=5000, gt=0)
    """Base environment steps between evaluations within a phase."""
    episodes: Whole = Field(default=10, gt=0)
    """Deterministic episodes per evaluation."""
    seed_offset: Whole = 100
    """The evaluation episodes' seeds are drawn from train.seed plus this offset (one seed per episode)."""
    fresh_episodes: Whole = Field(default=100, ge=0)
    """At the end of each phase its final and its best weights are each evaluated on this many
    fresh episodes: the best of several evaluations overestimates, these do not. 0 skips it."""
    fresh_seed_offset: Whole = 1000
    """The fresh episodes' seeds are drawn from train.seed plus this offset."""


class LogConfig(Section):
    """What a run writes besides its CSV logs and results."""

    tensorboard: Flag = False
    """Also write TensorBoard event files (run directory's `tensorboard/`, one run per phase): every
    row of metrics.csv as scalars. Needs the extra `layered-control[tensorboard]`."""


DEFAULT_LEARNER = "td3"
"""The learner of a layer whose recipe names none."""


class Recipe(Section):
    """A whole experiment: environment, layer stack, combiners, learners, training and evaluation."""

    env: EnvConfig
    layers: list[LayerConfig] = Field(min_length=1)
    combine: CombineConfig = CombineConfig()
    learner: dict[str, Any] = {"kind": DEFAULT_LEARNER}
    """Learner settings shared by every layer (`kind` plus that learner's keys)."""
    train: TrainConfig = TrainConfig()
    eval: EvalConfig = EvalConfig()
    log: LogConfig = LogConfig()

    def layer_names(self) -> list[str]:
        """The layers' names, slowest first."""
        return [layer.name for layer in self.layers]

    def warmup(self, name: str) -> int:
        """Random decisions of layer `name` before it learns: its own `warmup`, else `train.warmup`."""
        own = self.layers[self.layer_names().index(name)].warmup
        return self.train.warmup if own is None else own

    def learner_config(self, index: int) -> LearnerConfig:
        """The validated learner settings of layer `index`: its own table over the shared one."""
        table = {"kind": DEFAULT_LEARNER, **self.learner, **self.layers[index].learner}
        return LEARNERS.get(table["kind"]).Config.model_validate(table)

    def return_range(self) -> tuple[float, float] | None:
        """The (worst, best) return of an episode: the recipe's `env.return_range`, else the registry's."""
        return self.env.return_range or env_info(self.env.id).return_range

    def threshold(self, index: int) -> float:
        """The evaluation threshold (fraction of max action) applied below layer `index`."""
        own = self.layers[index].eval_threshold
        return own if own is not None else self.combine.eval_threshold

    def period(self, index: int) -> int:
        """Layer `index`'s period in base steps (loading resolves every period, from response times too)."""
        period = self.layers[index].period
        assert period is not None, "load_recipe resolves every layer's period"
        return period

    def combiner_kind(self, index: int) -> str | None:
        """The combiner merging layer `index` with the layers below it; the fastest layer has none below."""
        if index == len(self.layers) - 1:
            return None
        return self.layers[index].combine or self.combine.kind

    def output_layout(self, index: int, action_dims: int) -> OutputLayout:
        """What layer `index` outputs: the env's action dims, its combiner's gate dims, and a repeat
        count if it repeats."""
        kind = self.combiner_kind(index)
        combiner = COMBINERS.get(kind) if kind is not None else None
        return OutputLayout(action_dims, combiner.gate_dims if combiner else 0, self.layers[index].max_repeat,
                            combiner.encoding if combiner else None)

    def reward_per_step(self) -> float | None:
        """The environment's return range per step, (best - worst return) / episode steps, if known."""
        info = env_info(self.env.id)
        return_range = self.return_range()
        if return_range is None or not info.episode_steps:
            return None
        return (return_range[1] - return_range[0]) / info.episode_steps

    def action_penalty(self, index: int) -> float:
        """Layer `index`'s action penalty in reward units (see `action_penalty_unit`)."""
        layer = self.layers[index]
        if layer.action_penalty_unit == "reward":
            return layer.action_penalty
        scale = self.reward_per_step()
        assert scale is not None, "recipes are checked to know the return range per step"
        return layer.action_penalty * scale


SEED = "{seed}"
"""In a layer's `weights` path, the run's seed: each seed of a group or sweep starts from its own file."""


def unset_by_default() -> frozenset[str]:
    """The dotted keys whose default is unset (None), a layer's as `layers.*.<key>`: a resolved recipe leaves such
    a key out while it is unset, so a run's recipe without it ran with it unset."""
    return frozenset(_unset_keys(Recipe, ""))


def _unset_keys(model: type[Section], prefix: str) -> Iterator[str]:
    for name, field in model.model_fields.items():
        tables = [t for t in (field.annotation, *get_args(field.annotation)) if isinstance(t, type)
                  and not get_args(t) and issubclass(t, Section)]
        if not field.is_required() and field.default is None:
            yield prefix + name
        elif tables:
            yield from _unset_keys(tables[0], f"{prefix}{name}.*." if name == "layers" else f"{prefix}{name}.")


def key_path(loc: Iterable[Any]) -> str:
    """`layers[1].period` from a pydantic location tuple."""
    out = ""
    for part in loc:
        out += f"[{part}]" if isinstance(part, int) else (f".{part}" if out else str(part))
    return out


def describe_error(error: Mapping[str, Any]) -> str:
    """A one-line account of a pydantic error: what was expected and what was given."""
    kind, msg = error["type"], error["msg"]
    if kind == "extra_forbidden":
        return "unknown key"
    if kind == "missing":
        return "required key is missing"
    if kind == "value_error":  # a check across fields: its own words say what is wrong
        return str(error["ctx"]["error"])
    given = error.get("input")
    return f"{msg[0].lower()}{msg[1:]} (got {given!r})" if not isinstance(given, dict) else msg
