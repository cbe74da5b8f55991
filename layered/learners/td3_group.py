"""TD3 for K seeds as one computation: the groundwork of training many seeds of a recipe in one process.

Each seed's networks are the very ones a single `TD3` learner of that seed starts with, stacked along
a leading seed axis: every linear layer is one `[K, in, out]` weight, applied to the K seeds'
minibatches with one batched matrix product. The K seeds' losses are summed, so that one backward
pass and one Adam step (elementwise) update each seed exactly as its own loss asks; seeds never mix.
The replay buffers are one `[K, capacity, row]` tensor, sampled per seed in one gather. Acting takes
one observation per seed, `[K, obs]`, and returns `[K, action]`.

Bit-identity with K single learners is not promised (a batched product sums in another order), but
a seed's numbers do not depend on the other seeds', and `seed_state_dict(k)` is seed k's state as a
single `TD3` learner's `state_dict`, so that each seed can be written, evaluated and resumed alone.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import torch
from torch import nn

from layered.learners.td3 import TD3, TD3Config, adam


class StackedMLP(nn.Module):
    """K multilayer perceptrons of the same shape, one per seed, as `[K, in, out]` weights."""

    def __init__(self, mlps: Sequence[nn.Sequential]) -> None:
        super().__init__()
        layers = [[m for m in mlp if isinstance(m, nn.Linear)] for mlp in mlps]
        stacked = []
        for j in range(len(layers[0])):  # weight, bias, weight, bias ...: the order of an MLP's parameters
            stacked.append(nn.Parameter(torch.stack([seed[j].weight.detach().T for seed in layers]).contiguous()))
            stacked.append(nn.Parameter(torch.stack([seed[j].bias.detach()[None] for seed in layers]).contiguous()))
        self.stacked = nn.ParameterList(stacked)

    @property
    def weights(self) -> list[torch.Tensor]:
        """Each layer's weights, [K, in, out]."""
        return list(self.stacked)[0::2]

    @property
    def biases(self) -> list[torch.Tensor]:
        """Each layer's biases, [K, 1, out]."""
        return list(self.stacked)[1::2]

    def forward(self, x: torch.Tensor, frozen: bool = False) -> torch.Tensor:
        """`x`: [K, batch, in] -> [K, batch, out]; with `frozen`, the weights take no gradient."""
        last = len(self.stacked) // 2 - 1
        for j, (weight, bias) in enumerate(zip(self.weights, self.biases, strict=True)):
            if frozen:
                weight, bias = weight.detach(), bias.detach()
            x = torch.baddbmm(bias, x, weight)
            x = torch.relu(x) if j < last else x
        return x

    def seed_state(self, k: int, prefix: str) -> dict[str, torch.Tensor]:
        """Seed k's weights under the names an `nn.Sequential` of linear layers and ReLUs gives them."""
        return {**{f"{prefix}{2 * j}.weight": w[k].T.contiguous() for j, w in enumerate(self.weights)},
                **{f"{prefix}{2 * j}.bias": b[k, 0].clone() for j, b in enumerate(self.biases)}}


class TD3Group:
    """K TD3 learners of one configuration, one per seed, updated together."""

    def __init__(self, learners: Sequence[TD3], seed: int = 0) -> None:
        """Stack `learners` (new ones, of the same spaces and settings, one per seed); `seed` seeds the
        group's own generators (minibatch indices, smoothing and exploration noise)."""
        first = learners[0]
        self.config: TD3Config = first.config
        if self.config.precision != "float32" or self.config.compile != "off" or self.config.actor_anchor:
            raise ValueError("a TD3 group runs in float32, eagerly, without actor_anchor (for now)")
        self.k = len(learners)
        self.device = first.device
        self.action_space = first.action_space
        self.actor = StackedMLP([learner.actor.net for learner in learners]).to(self.device)
        self.q1 = StackedMLP([learner.critic.q1 for learner in learners]).to(self.device)
        self.q2 = StackedMLP([learner.critic.q2 for learner in learners]).to(self.device)
        self.actor_target = StackedMLP([learner.actor_target.net for learner in learners]).to(self.device)
        self.q1_target = StackedMLP([learner.critic_target.q1 for learner in learners]).to(self.device)
        self.q2_target = StackedMLP([learner.critic_target.q2 for learner in learners]).to(self.device)
        for target in (self.actor_target, self.q1_target, self.q2_target):
            target.requires_grad_(False)
        self.actor_opt = adam(self.actor.parameters(), self.config.lr)
        self.critic_opt = adam([*self.q1.parameters(), *self.q2.parameters()], self.config.lr)
        self._targets: list[torch.Tensor] = [*self.actor_target.parameters(), *self.q1_target.parameters(),
                                             *self.q2_target.parameters()]
        self._sources: list[torch.Tensor] = [*self.actor.parameters(), *self.q1.parameters(), *self.q2.parameters()]
        self.centre, self.scale = first.actor.centre.to(self.device), first.actor.scale.to(self.device)
        self._low, self._high = first._low, first._high
        self.obs_dim, self.act_dim = first.obs_space.shape[0], first.action_space.shape[0]
        widths = (self.obs_dim, self.act_dim, 1, self.obs_dim, 1, 1)  # obs, action, reward, next, not done, discount
        self._cuts = np.cumsum((0, *widths)).tolist()
        self._rows = torch.empty((self.k, self.config.buffer_size, self._cuts[-1]), device=self.device)
        self.sizes = torch.zeros(self.k, dtype=torch.long, device=self.device)
        self._next = torch.zeros(self.k, dtype=torch.long, device=self.device)
        self.torch_rng = torch.Generator(self.device).manual_seed(seed)
        self.rng = np.random.default_rng(seed)
        self.updates = 0

    def _actions(self, obs: torch.Tensor, net: StackedMLP) -> torch.Tensor:
        return self.centre + self.scale * torch.tanh(net(obs))

    @torch.inference_mode()
    def act(self, obs: np.ndarray, explore: bool) -> np.ndarray:
        """Each seed's action for its observation (`obs`: [K, obs] -> [K, action]); with `explore`,
        Gaussian noise of `exploration_noise` times the half-range, clipped to the bounds."""
        x = torch.as_tensor(np.asarray(obs, np.float32), device=self.device)[:, None]
        action = self._actions(x, self.actor)[:, 0].cpu().numpy()
        if explore:
            low, high = self.action_space.low, self.action_space.high
            noise = self.rng.normal(0.0, self.config.exploration_noise, action.shape) * (high - low) / 2
            action = np.clip(action + noise, low, high)
        return action.astype(np.float32)

    def observe(self, obs: np.ndarray, action: np.ndarray, reward: np.ndarray, next_obs: np.ndarray,
                terminated: np.ndarray, discount: np.ndarray, rows: np.ndarray | None = None) -> None:
        """Store one transition per seed ([K, ...] arrays), or only in the seeds of the `rows` mask."""
        k = np.arange(self.k) if rows is None else np.flatnonzero(rows)
        data = np.concatenate([obs, action, np.asarray(reward)[:, None], next_obs,
                               1.0 - np.asarray(terminated, np.float32)[:, None], np.asarray(discount)[:, None]],
                              axis=1, dtype=np.float32)
        seeds = torch.as_tensor(k, device=self.device)
        at = self._next[seeds]
        self._rows[seeds, at] = torch.as_tensor(data[k], device=self.device)
        self._next[seeds] = (at + 1) % self.config.buffer_size
        self.sizes[seeds] = torch.clamp(self.sizes[seeds] + 1, max=self.config.buffer_size)

    def sample(self) -> tuple[torch.Tensor, ...]:
        """A minibatch per seed, drawn uniformly from its own buffer: obs, action, reward, next obs,
        not done, discount, each [K, batch, width]."""
        u = torch.rand((self.k, self.config.batch_size), generator=self.torch_rng, device=self.device)
        idx = (u * self.sizes[:, None]).long()
        rows = torch.gather(self._rows, 1, idx[:, :, None].expand(-1, -1, self._cuts[-1]))
        return tuple(rows[:, :, a:b] for a, b in zip(self._cuts, self._cuts[1:], strict=False))

    def update(self) -> dict[str, torch.Tensor] | None:
        """One TD3 update of every seed; the losses per seed ([K] tensors), as a single learner names them."""
        if int(self.sizes.min()) == 0:
            return None
        batch = self.sample()
        noise = torch.randn(batch[1].shape, generator=self.torch_rng, device=self.device)
        critic = self.critic_step(batch, noise)
        self.updates += 1
        if self.updates % self.config.policy_delay:
            return {"critic": critic}
        return {"critic": critic, "actor": self.actor_step(batch[0])}

    def critic_step(self, batch: tuple[torch.Tensor, ...], noise: torch.Tensor) -> torch.Tensor:
        """One critic step of every seed on its minibatch, with standard-normal smoothing `noise`; the
        losses per seed."""
        obs, action, reward, next_obs, not_done, discount = batch
        cfg = self.config
        with torch.no_grad():
            noise = (noise * cfg.policy_noise).clamp(-cfg.noise_clip, cfg.noise_clip)
            next_action = (self._actions(next_obs, self.actor_target) + noise * self.scale).clamp(self._low, self._high)
            pair = torch.cat([next_obs, next_action], dim=-1)
            target = reward + not_done * discount * torch.min(self.q1_target(pair), self.q2_target(pair))
        pair = torch.cat([obs, action], dim=-1)
        losses = (self.q1(pair) - target).square().mean(dim=(1, 2)) + (self.q2(pair) - target).square().mean(dim=(1, 2))
        self.critic_opt.zero_grad(set_to_none=True)
        losses.sum().backward()
        self.critic_opt.step()
        return losses.detach()

    def actor_step(self, obs: torch.Tensor) -> torch.Tensor:
        """One actor step of every seed through its Q1, then the soft update of every target; the losses."""
        q1 = self.q1(torch.cat([obs, self._actions(obs, self.actor)], dim=-1), frozen=True)
        losses = -q1.mean(dim=(1, 2))
        self.actor_opt.zero_grad(set_to_none=True)
        losses.sum().backward()
        self.actor_opt.step()
        with torch.no_grad():
            torch._foreach_lerp_(self._targets, self._sources, self.config.tau)
        return losses.detach()

    def seed_state_dict(self, k: int) -> dict[str, Any]:
        """Seed k's networks as a single `TD3` learner's `state_dict` holds them (the optimisers' moments
        per seed too), so that the seed's checkpoint is an ordinary one."""
        def critic(q1: StackedMLP, q2: StackedMLP) -> dict[str, torch.Tensor]:
            return {**q1.seed_state(k, "q1."), **q2.seed_state(k, "q2.")}

        return {
            "actor": {**self.actor.seed_state(k, "net."), "centre": self.centre.clone(), "scale": self.scale.clone()},
            "critic": critic(self.q1, self.q2),
            "actor_target": {**self.actor_target.seed_state(k, "net."), "centre": self.centre.clone(),
                             "scale": self.scale.clone()},
            "critic_target": critic(self.q1_target, self.q2_target),
            "actor_opt": _seed_adam(self.actor_opt, k), "critic_opt": _seed_adam(self.critic_opt, k),
            "updates": self.updates, "torch_rng": self.torch_rng.get_state(),
        }


def _seed_adam(optimizer: torch.optim.Adam, k: int) -> dict[str, Any]:
    """Seed k's part of a stacked Adam's state, in the layout of a single network's Adam (weights as
    `[out, in]`, biases as `[out]`)."""
    state = optimizer.state_dict()
    per_seed = {}
    for index in range(sum(len(group["params"]) for group in optimizer.param_groups)):
        moments = state["state"].get(index)
        if moments is None:
            continue

        def part(t: torch.Tensor, weight: bool = index % 2 == 0) -> torch.Tensor:  # weights and biases alternate
            return t[k].T.contiguous() if weight else t[k, 0].clone()

        per_seed[index] = {"step": moments["step"].clone(), "exp_avg": part(moments["exp_avg"]),
                           "exp_avg_sq": part(moments["exp_avg_sq"])}
    return {"state": per_seed, "param_groups": state["param_groups"]}
