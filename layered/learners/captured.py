"""The learners that recipes name `td3`, `temporl` and `td3-gate`: each its single learner (`layered.learners.td3`,
`.temporl`, `.gate_td3`), which with `compile = "cudagraphs"` on a GPU trains as a group of one seed
(`layered.learners.td3_group`, `.choice_group`).

A group's GPU path captures the whole TD3 update (sampling, both critics, the delayed actor step, the soft
updates) as one CUDA graph, captures acting as another, and sends observations and transitions through
page-locked memory, so that nothing waits for the update in flight. A single TD3 learner compiled by
torch.compile (mode reduce-overhead) replays its critic and actor steps as two graphs, but samples with
indices made on the host, acts eagerly and copies from pageable memory: on an H200 one HalfCheetah-v5
seed's training steps ran at 284 steps/s that way, and at 941 as a group of one on the same machine. So
these learners hand their networks to a group of one, and act, store and update through it (a single run's
training steps then ran at 1,044 steps/s on an H200); their state dicts are the single learner's
(`seed_state_dict`), so their checkpoints load into a plain learner anywhere (a CPU evaluating a GPU-trained
run), and their own replay buffers stay on the host, unwritten. With `compile` off or `inductor` each is its
single learner as it is.
"""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np
import torch
from gymnasium.spaces import Box
from torch import nn

from layered.buffer import Transition
from layered.learners.base import LEARNERS, Learner, Losses
from layered.learners.choice import TD3WithChoice
from layered.learners.choice_group import GateTD3Group, TempoRLGroup
from layered.learners.gate_td3 import GateTD3
from layered.learners.td3 import TD3, TD3Config
from layered.learners.td3_group import TD3Group
from layered.learners.temporl import TempoRL
from layered.outputs import OutputLayout


def captures(config: TD3Config, device: torch.device) -> bool:
    """Whether a learner of `config` on `device` trains through a group of one (its update captured)."""
    return config.compile == "cudagraphs" and device.type == "cuda"


class GroupOfOne(Learner):
    """A single learner (`Single`) that trains through a group of one seed (`Group`) where its update is
    captured as CUDA graphs. Until the group is made, the learner's own networks and optimisers hold its state:
    weights loaded into them go on into the group when it is made (when the learner first acts, stores,
    updates or is checkpointed), so that loading and saving weights make no group."""

    Single: ClassVar[type[Learner]]
    Group: ClassVar[Any]  # a group class: (learners, seed) -> the group

    def __init__(self, obs_space: Box, action_space: Box, layout: OutputLayout, config: TD3Config, seed: int
                 ) -> None:
        super().__init__(obs_space, action_space, layout, config, seed)  # (the single learner's, next in line)
        self._seed = seed
        self._captured = captures(config, self.device)
        self._group: Any = None
        if self._captured:  # (the group keeps the replay: the learner's own buffers would take device memory unused)
            for buffer in super().replays.values():
                buffer.keep_on_host()

    @property
    def group(self) -> Any:
        """The group of one that trains this learner (None unless its update is captured), made when first
        needed: a learner that only lends its networks to a group of many seeds never makes one."""
        if self._captured and self._group is None:
            self._group = type(self).Group([self], self._seed)
        return self._group

    def act(self, obs: np.ndarray, explore: bool) -> np.ndarray:
        if (group := self.group) is None:
            return self.Single.act(self, obs, explore)
        return group.act(np.asarray(obs, np.float32)[None], explore)[0]

    def greedy(self, obs: np.ndarray) -> np.ndarray:
        if (group := self.group) is None:
            return self.Single.greedy(self, obs)
        return group.greedy(np.asarray(obs, np.float32)[None])[0]

    def observe(self, transition: Transition) -> None:
        if (group := self.group) is None:
            return self.Single.observe(self, transition)
        t = transition
        group.observe(np.ravel(t.obs)[None], np.ravel(t.action)[None], np.array([t.reward]), np.ravel(t.next_obs)[None],
                      np.array([t.terminated]), np.array([t.discount]), None, [t.path])

    def update(self) -> Losses | None:
        if (group := self.group) is None:
            return self.Single.update(self)
        losses = group.update()
        return None if losses is None else {name: values[0] for name, (values, _) in losses.items()}

    def policy(self) -> nn.Module:
        if self._group is not None:
            self.Single.load_state_dict(self, self._group.seed_state_dict(0))  # (the group holds the weights)
        return self.Single.policy(self)

    def state_dict(self) -> dict[str, Any]:
        return self.Single.state_dict(self) if self._group is None else self._group.seed_state_dict(0)

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.Single.load_state_dict(self, state)  # (and the precision it was trained in, kept as the learner keeps it)
        if self._group is not None:
            self._group.load_seed_state_dict(0, state)
            single: Any = getattr(self, "td3", self)  # (a choice learner's TD3 part, and its group's)
            getattr(self._group, "td3", self._group).precision = single.precision

    @property
    def replays(self) -> dict[str, Any]:
        return dict(super().replays if (group := self.group) is None else group.replays)

    def resume_state(self) -> dict[str, Any]:
        if (group := self.group) is None:
            return self.Single.resume_state(self)
        return {"group": group.resume_state(), "rngs": [rng.bit_generator.state for rng in self._own_generators()]}

    def load_resume_state(self, state: dict[str, Any]) -> None:
        if (group := self.group) is None:
            return self.Single.load_resume_state(self, state)
        group.load_resume_state(state["group"])
        for rng, saved in zip(self._own_generators(), state["rngs"], strict=True):
            rng.bit_generator.state = saved

    def _own_generators(self) -> list[np.random.Generator]:
        """The generators the learner draws from outside its group: its warm-up draws (a choice learner's
        action from its TD3 part's, its choice from its own)."""
        return [self.rng, *([self.td3.rng] if isinstance(self, TD3WithChoice) else [])]


@LEARNERS.register("td3")
class CapturedTD3(GroupOfOne, TD3):
    """TD3, through a group of one seed where its update is captured."""

    Single = TD3
    Group = TD3Group


@LEARNERS.register("temporl")
class CapturedTempoRL(GroupOfOne, TempoRL):
    """TempoRL, through a group of one seed where its update is captured."""

    Single = TempoRL
    Group = TempoRLGroup


@LEARNERS.register("td3-gate")
class CapturedGateTD3(GroupOfOne, GateTD3):
    """The jointly trained gate, through a group of one seed where its update is captured."""

    Single = GateTD3
    Group = GateTD3Group
