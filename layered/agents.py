"""The agent view: a PettingZoo AEC env in which each layer of a stack is an agent.

`agent_iter()` yields a layer only when it is due; `last()` gives it its own observation, the
shaped reward accumulated since its last decision and, in `info["transition"]`, that decision's
completed transition with its discount (`info["elapsed"]`: the base steps it spanned). This env
is the reference semantics the trainer drives directly.
"""

from __future__ import annotations

from typing import Any, ClassVar, Protocol

import gymnasium as gym
import numpy as np
from gymnasium.spaces import Box
from pettingzoo import AECEnv

from layered.envs import make_env
from layered.metrics import StepRecord
from layered.schema import Recipe
from layered.stack import Stack


class Watcher(Protocol):
    """Something that looks at evaluation episodes as they are played: videos, galleries."""

    def wants(self, step: int) -> bool:
        """Whether to render the state before base step `step` of the episode."""

    def __call__(self, step: int, frame: np.ndarray, record: StepRecord) -> None:
        """Base step `step`: the state rendered before it, and what was executed from it."""


class LayeredEnv(AECEnv[str, np.ndarray, np.ndarray | None]):
    """A PettingZoo AEC environment over a Gymnasium one: the stack's rules drive it, one agent per present layer."""

    metadata: ClassVar[dict[str, Any]] = {
        "name": "layered_v0", "is_parallelizable": False, "render_modes": ["rgb_array"],
    }

    def __init__(self, base: gym.Env, stack: Stack, keep_trace: bool = False) -> None:
        """With `keep_trace`, every base step of the current episode is kept in `trace`."""
        super().__init__()
        self.base = base
        self.stack = stack
        self.render_mode = base.render_mode
        self.possible_agents = [stack.layers[i].name for i in stack.active]
        self._index = {stack.layers[i].name: i for i in stack.active}
        self._observation_spaces = {n: stack.observation_spaces[i] for n, i in self._index.items()}
        self._action_spaces = {n: stack.layers[i].action_space for n, i in self._index.items()}
        self.keep_trace = keep_trace
        self.trace: list[StepRecord] = []
        self.watcher: Watcher | None = None
        self._obs: np.ndarray = np.zeros(base.observation_space.shape or (0,), np.float32)
        self._decided: list[str] = []
        self.episode_return = 0.0
        self.episode_steps = 0

    def observation_space(self, agent: str) -> Box:
        return self._observation_spaces[agent]

    def action_space(self, agent: str) -> Box:
        return self._action_spaces[agent]

    def reset(self, seed: int | None = None, options: dict[str, Any] | None = None) -> None:
        self._obs, _ = self.base.reset(seed=seed, options=options)
        if seed is not None:  # (so that a loop sampling `action_space(layer)` repeats itself given the seed)
            self.base.action_space.seed(seed)
            for k, name in enumerate(self.possible_agents):
                self._action_spaces[name].seed(seed + 1 + k)
        self.stack.reset()
        self.agents = list(self.possible_agents)
        self.rewards = dict.fromkeys(self.agents, 0.0)
        self._cumulative_rewards = dict.fromkeys(self.agents, 0.0)
        self.terminations = dict.fromkeys(self.agents, False)
        self.truncations = dict.fromkeys(self.agents, False)
        self.infos: dict[str, dict[str, Any]] = {a: {} for a in self.agents}
        self._decided = []
        self.trace = []
        self.episode_return = 0.0
        self.episode_steps = 0
        first = self.stack.next_due(0)
        assert first is not None, "every present layer decides at step 0"
        self.agent_selection = self.stack.layers[first].name

    def observe(self, agent: str) -> np.ndarray:
        return self.stack.observation(self._index[agent], self._obs)

    def step(self, action: np.ndarray | None) -> None:
        """The selected layer's decision; the environment then runs until some layer is due or the
        episode ends (`episode_steps` counts the base steps run)."""
        if not self.agents:
            raise RuntimeError("the episode has ended: reset the env before stepping it again")
        agent = self.agent_selection
        if self.terminations[agent] or self.truncations[agent]:
            self._was_dead_step(action)
            return
        if action is None:
            raise ValueError(f"layer {agent!r} is due and must be given an action, not None")
        self._check_action(agent, action)
        i = self._index[agent]
        self._cumulative_rewards[agent] = 0.0
        self.infos[agent] = {}
        self.rewards = dict.fromkeys(self.agents, 0.0)
        self.stack.decide(i, self.observe(agent), action)
        self._decided.append(agent)
        due = self.stack.next_due(i + 1)
        ended = False
        while due is None and not ended:
            ended = self._base_step()
            due = None if ended else self.stack.next_due(0)
        self._accumulate_rewards()
        if ended:
            for name in self.agents:
                self._complete(name)
            self.agent_selection = self.agents[0]
        else:
            assert due is not None
            self.agent_selection = self.stack.layers[due].name
            self._complete(self.agent_selection)

    def last(self, observe: bool = True) -> tuple[Any, float, bool, bool, dict[str, Any]]:
        if not self.agents:
            raise RuntimeError("the episode has ended: reset the env before asking for its last step")
        return super().last(observe)

    def _check_action(self, agent: str, action: np.ndarray) -> None:
        """Refuse an action of another size than the layer's action space, or with a NaN or an infinity in it (its
        output is clipped to the space when the stack holds it; the transition records it as given)."""
        output, space = np.asarray(action), self._action_spaces[agent]
        if output.size != int(np.prod(space.shape)):
            raise ValueError(f"layer {agent!r} was given an output of shape {output.shape}; its action space {space} "
                             f"takes {int(np.prod(space.shape))} number{'s' * (int(np.prod(space.shape)) != 1)}")
        if not np.isfinite(output).all():
            raise ValueError(f"layer {agent!r} was given a non-finite action {output.ravel().tolist()}")

    def _complete(self, agent: str) -> None:
        """It is `agent`'s turn: hand it the transition completed since its latest decision."""
        i = self._index[agent]
        decision = self.stack.decisions[i]
        if decision is not None:  # None: the layer has not decided yet this episode
            transition = self.stack.transition(i, self._cumulative_rewards[agent], self.observe(agent),
                                               self.terminations[agent])
            self.infos[agent] = {"elapsed": decision.elapsed, "transition": transition}

    def _base_step(self) -> bool:
        """Execute the composed action for one base step; True when the episode ended."""
        composition = self.stack.compose()
        watched = self.watcher is not None and self.watcher.wants(self.episode_steps)
        frame = np.asarray(self.base.render()) if watched else None
        obs = self._obs
        self._obs, reward, terminated, truncated, _ = self.base.step(composition.action)
        rewards = self.stack.layer_rewards(float(reward), composition)
        for i, r in rewards.items():  # (a layer that has not decided yet this episode has no reward to collect)
            if self.stack.decisions[i] is not None:
                self.rewards[self.stack.layers[i].name] += r
        self.stack.tick()
        self.stack.accrue(rewards, self._obs, ended=terminated or truncated)
        if self.keep_trace or frame is not None:
            # copies: the stack reuses its held arrays, and an env may reuse its observation's
            parts = {self.stack.layers[i].name: c.copy() for i, c in composition.contributions.items()}
            executed = StepRecord(composition.action, float(reward), tuple(self._decided), parts, np.array(obs))
            if self.keep_trace:
                self.trace.append(executed)
            if frame is not None and self.watcher is not None:
                self.watcher(self.episode_steps, frame, executed)
        self.episode_return += float(reward)
        self.episode_steps += 1
        self._decided = []
        if terminated or truncated:
            for name in self.agents:
                self.terminations[name] = bool(terminated)
                self.truncations[name] = bool(truncated) and not terminated
            return True
        return False

    def render(self) -> Any:
        return self.base.render()

    def close(self) -> None:
        self.base.close()


def make_aec_env(
    recipe: Recipe,
    seed: int | None = None,
    active: list[str] | None = None,
    evaluation: bool = False,
    threshold: float | None = None,
    keep_trace: bool = False,
    render_mode: str | None = None,
) -> LayeredEnv:
    """The AEC env of a recipe's stack (all layers present unless `active` names some), reset with `seed`: as
    training runs it, or with `evaluation` as evaluations do (contributions thresholded at the recipe's thresholds, or
    at `threshold`, a fraction of the maximum action); with `keep_trace` every base step of an episode is kept in
    `trace`, and `render_mode` is the environment's."""
    base = make_env(recipe.env.id, render_mode=render_mode)
    obs_space, action_space = base.observation_space, base.action_space
    assert isinstance(obs_space, Box) and isinstance(action_space, Box)
    stack = Stack(recipe, obs_space, action_space, active=active, evaluation=evaluation, threshold=threshold)
    env = LayeredEnv(base, stack, keep_trace=keep_trace)
    env.reset(seed=seed)
    return env
