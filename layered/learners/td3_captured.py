"""The `td3` learner that recipes name: TD3 (`layered.learners.td3`), which with `compile = "cudagraphs"` on a
GPU trains as a group of one seed (`layered.learners.td3_group`).

A group's GPU path captures the whole update (sampling, both critics, the delayed actor step, the soft
updates) as one CUDA graph, captures acting as another, and sends observations and transitions through
page-locked memory, so that nothing waits for the update in flight. A single TD3 learner compiled by
torch.compile (mode reduce-overhead) replays its critic and actor steps as two graphs, but samples with
indices made on the host, acts eagerly and copies from pageable memory: on an H200 one HalfCheetah-v5
seed's training steps ran at 284 steps/s that way, and at 941 as a group of one on the same machine. So this learner
hands its networks to a group of one, and acts, stores and updates through it; its state dicts are the
single learner's (`TD3Group.seed_state_dict`), so its checkpoints load into a plain TD3 anywhere (a CPU
evaluating a GPU-trained run). With `compile` off or `inductor` it is TD3 as it is.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from gymnasium.spaces import Box
from torch import nn

from layered.buffer import Transition
from layered.learners.base import LEARNERS, Losses
from layered.learners.td3 import TD3, TD3Config
from layered.learners.td3_group import TD3Group
from layered.outputs import OutputLayout


def captures(config: TD3Config, device: torch.device) -> bool:
    """Whether a `td3` learner of `config` on `device` trains through a group of one (its update captured)."""
    return config.compile == "cudagraphs" and device.type == "cuda"


@LEARNERS.register("td3")
class CapturedTD3(TD3):
    """TD3, through a group of one seed where its update is captured as CUDA graphs."""

    def __init__(self, obs_space: Box, action_space: Box, layout: OutputLayout, config: TD3Config,
                 seed: int) -> None:
        super().__init__(obs_space, action_space, layout, config, seed)
        self._seed = seed
        self._captured = captures(config, self.device)
        self._group: TD3Group | None = None

    @property
    def group(self) -> TD3Group | None:
        """The group of one that trains this learner (None unless its update is captured), made when first
        needed: a learner that only lends its networks to a group of many seeds never makes one."""
        if self._captured and self._group is None:
            self._group = TD3Group([self], seed=self._seed)
        return self._group

    def act(self, obs: np.ndarray, explore: bool) -> np.ndarray:
        if (group := self.group) is None:
            return super().act(obs, explore)
        return group.act(np.asarray(obs, np.float32)[None], explore)[0]

    def observe(self, transition: Transition) -> None:
        if (group := self.group) is None:
            return super().observe(transition)
        t = transition
        group.observe(np.ravel(t.obs)[None], np.ravel(t.action)[None], np.array([t.reward]), np.ravel(t.next_obs)[None],
                      np.array([t.terminated]), np.array([t.discount]))

    def update(self) -> Losses | None:
        if (group := self.group) is None:
            return super().update()
        losses = group.update()
        return None if losses is None else {name: values[0] for name, (values, _) in losses.items()}

    # Until its group is made, the learner's own networks and optimisers hold its state (weights loaded into
    # them go on into the group when it is made), so that loading and saving weights make no group.

    def policy(self) -> nn.Module:
        if self._group is not None:
            self.actor.load_state_dict(self._group.seed_state_dict(0)["actor"])  # (the group holds the weights)
        return super().policy()

    def state_dict(self) -> dict[str, Any]:
        return super().state_dict() if self._group is None else self._group.seed_state_dict(0)

    def load_state_dict(self, state: dict[str, Any]) -> None:
        super().load_state_dict(state)  # (the precision it was trained in, kept as TD3 keeps it)
        if self._group is not None:
            self._group.load_seed_state_dict(0, state)
            self._group.precision = self.precision

    @property
    def replays(self) -> dict[str, Any]:
        if (group := self.group) is None:
            return super().replays
        return {"td3": group.replay}

    def resume_state(self) -> dict[str, Any]:
        if (group := self.group) is None:
            return super().resume_state()
        return {"group": group.resume_state(), "rng": self.rng.bit_generator.state}

    def load_resume_state(self, state: dict[str, Any]) -> None:
        if (group := self.group) is None:
            return super().load_resume_state(state)
        group.load_resume_state(state["group"])
        self.rng.bit_generator.state = state["rng"]

