"""The learner contract: acting is separate from learning, and state is plain tensors."""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Mapping
from typing import Annotated, Any, ClassVar

import numpy as np
import torch
from gymnasium.spaces import Box
from pydantic import BaseModel, ConfigDict, Field, Strict
from torch import nn

from layered.buffer import ReplayBuffer, Transition
from layered.errors import BadInput
from layered.outputs import OutputLayout
from layered.registry import Registry


Whole = Annotated[int, Strict()]
"""A whole-number setting of a recipe: a string such as "4", a float or a bool is refused, not converted."""
Flag = Annotated[bool, Strict()]
"""A true/false setting of a recipe: a string or a number is refused, not converted."""


class LearnerConfig(BaseModel):
    """Base of every learner's settings: frozen, and unknown keys are errors."""

    model_config = ConfigDict(extra="forbid", frozen=True, use_attribute_docstrings=True, allow_inf_nan=False)

    kind: str
    """Registered name of the learner."""
    gamma: float = Field(default=0.99, ge=0, le=1)
    """Discount per decision of the layer (or per base step, see train.discount)."""

    def on_device(self, device: str) -> LearnerConfig:
        """These settings with the learner placed on `device` (`cpu`, `cuda`), for a learner that has
        a choice of device; the same settings for one that has none."""
        return self

    def unavailable(self) -> list[tuple[str, str]]:
        """(key, why) for each setting this machine cannot honour (a GPU asked for where there is none)."""
        return []


Losses = dict[str, torch.Tensor]
"""What one gradient update returns: each loss it computed (of the learner's `loss_names`) as a 0-d
tensor on the learner's device. The loop reads them back only when it logs or checkpoints, so that no
update waits for the device."""


class Learner(ABC):
    """A layer's policy and the algorithm that trains it from the layer's own transitions."""

    Config: ClassVar[type[LearnerConfig]]
    loss_names: ClassVar[tuple[str, ...]] = ()
    """The losses `update` may return, in the order the logs list them (metrics.csv's `<name>_loss_<layer>`)."""
    device: torch.device = torch.device("cpu")
    """Where the learner's networks and updates live."""

    def __init__(self, obs_space: Box, action_space: Box, layout: OutputLayout, config: LearnerConfig,
                 seed: int) -> None:
        """`action_space` bounds the layer's whole output, whose entries `layout` names."""
        if (why := self.unfit(layout)) is not None:
            raise ValueError(f"the {config.kind} learner cannot drive a layer that outputs {layout.describe()}: {why}")
        self.obs_space = obs_space
        self.action_space = action_space
        self.layout = layout
        self.config = config
        self.rng = np.random.default_rng(seed)

    @classmethod
    def unfit(cls, layout: OutputLayout) -> str | None:
        """Why this learner cannot drive a layer whose output is laid out as `layout`; None if it can.
        Recipes are checked with it before anything is built."""
        return None

    def random_action(self) -> np.ndarray:
        """A uniform sample from the action space, drawn from this learner's own generator."""
        low, high = self.action_space.low, self.action_space.high
        return self.rng.uniform(low, high).astype(np.float32)

    @abstractmethod
    def act(self, obs: np.ndarray, explore: bool) -> np.ndarray:
        """The action for `obs`; with `explore`, perturbed for exploration. Never learns."""

    def greedy(self, obs: np.ndarray) -> np.ndarray:
        """The outputs without exploration for a batch of observations (`obs`: [n, obs] -> [n, size]): an
        evaluation's episodes played side by side. One `act` per row unless a learner acts on batches itself."""
        return np.stack([self.act(row, explore=False) for row in obs])

    def policy(self) -> nn.Module:
        """The deterministic policy as a torch module of its own: one float32 observation vector in,
        what `act(obs, explore=False)` returns out. `layered export` writes it."""
        raise NotImplementedError(f"the {self.config.kind!r} learner has no exportable policy (Learner.policy)")

    def computes_in(self) -> str:
        """The precision its updates' products are computed in, as resolved on its device and from the weights it
        started from: `float32` unless the learner has a precision setting (TD3's `auto` depends on the machine, so
        each run records this in its run.json)."""
        return "float32"

    @abstractmethod
    def act_macs(self) -> int:
        """Multiply-accumulates of one `act` call (the networks it evaluates), for the compute measure."""

    @abstractmethod
    def observe(self, transition: Transition) -> None:
        """Store a transition for later updates."""

    @abstractmethod
    def update(self) -> Losses | None:
        """One learning step from stored transitions, and the losses it computed; None while there is too
        little data."""

    @abstractmethod
    def state_dict(self) -> dict[str, Any]:
        """Networks and optimiser states as tensors, for a checkpoint."""

    @abstractmethod
    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore what `state_dict` returned."""

    @property
    def replays(self) -> Mapping[str, ReplayBuffer]:
        """The learner's replay buffers by part (`layered.buffer.ReplayBuffer`s), which a run's checkpoint keeps
        apart from `resume_state`, writing only what each stored since the last (`layered.replay_journal`);
        none by default (a learner keeping its replay in `resume_state` resumes as well, at the full cost)."""
        return {}

    def resume_state(self) -> dict[str, Any]:
        """Everything needed to continue training exactly but `replays`: `state_dict` and random state."""
        return {"policy": self.state_dict(), "rng": self.rng.bit_generator.state}

    def load_resume_state(self, state: dict[str, Any]) -> None:
        """Restore what `resume_state` returned."""
        self.load_state_dict(state["policy"])
        self.rng.bit_generator.state = state["rng"]


CHECKPOINTED = (torch.Tensor, bool, int, float, complex, str, bytes, type(None), torch.dtype, torch.device, torch.Size)
"""What a checkpoint holds besides containers (dicts, lists, tuples, sets): what torch reads back weights-only."""


def is_plugin(learner: Learner) -> bool:
    """Whether the learner's class comes from outside the library: the checks below are for those (the test suite
    checks the shipped ones)."""
    return not type(learner).__module__.startswith("layered.")


def check_plugin_learner(learner: Learner, layer: str) -> None:
    """Refuse, in one line and before a run starts, a plugin learner whose `state_dict` or `resume_state` holds what a
    checkpoint cannot read back (a numpy array), or whose `load_state_dict` or `load_resume_state` cannot take what
    they return: either would surface only at a phase's end or on resuming, after its training."""
    kind = f"learner {learner.config.kind!r} (layer {layer!r})"
    for method, state in (("state_dict", learner.state_dict()), ("resume_state", learner.resume_state())):
        if (found := _unreadable(state, "")) is not None:
            where, value = found
            raise BadInput(f"{kind}: its {method}() holds a {type(value).__module__}.{type(value).__qualname__} at "
                           f"{where or 'its top'}; a checkpoint holds tensors, Python numbers and strings, in dicts, "
                           "lists and tuples (torch reads it back weights-only)")
    for method, load in (("state_dict", learner.load_state_dict), ("resume_state", learner.load_resume_state)):
        try:
            load(getattr(learner, method)())
        except Exception as e:
            raise BadInput(f"{kind}: load_{method}() cannot take what {method}() returns ({type(e).__name__}: {e})"
                           ) from None


def checked_losses(learner: Learner, layer: str, losses: Losses) -> Losses:
    """An update's `losses`, refused in one line unless each is one of the learner's `loss_names` and a tensor: a
    plugin's loss of another name was dropped from the logs unsaid, and a Python number failed later, in a traceback."""
    for name, value in losses.items():
        if name not in type(learner).loss_names or not isinstance(value, torch.Tensor):
            raise BadInput(f"learner {learner.config.kind!r} (layer {layer!r}): its update returned {name!r} as a "
                           f"{type(value).__qualname__}; it returns 0-d tensors named in its loss_names "
                           f"{type(learner).loss_names}")
    return losses


def _unreadable(value: Any, where: str) -> tuple[str, Any] | None:
    """The first value in `value` (and where) that a checkpoint cannot read back, or None."""
    if isinstance(value, dict):
        items: Any = value.items()
    elif isinstance(value, list | tuple | set | frozenset):
        items = enumerate(value)
    else:
        return None if isinstance(value, CHECKPOINTED) else (where, value)
    for key, item in items:
        if (found := _unreadable(item, f"{where}[{key!r}]")) is not None:
            return found
    return None


LEARNERS: Registry[type[Learner]] = Registry("learner", Learner)
