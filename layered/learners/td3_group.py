"""TD3 for K seeds as one computation: the groundwork of training many seeds of a recipe in one process.

Each seed's networks are the very ones a single `TD3` learner of that seed starts with, stacked along
a leading seed axis: every linear layer is one `[K, in, out]` weight (both critics' one `[K, 2, in, out]`),
applied to the K seeds' minibatches with one batched matrix product. The K seeds' losses are summed, so
that one backward pass and one Adam step (elementwise) update each seed exactly as its own loss asks;
seeds never mix.
The replay buffers are one `[K, capacity, row]` tensor, sampled per seed in one selection of rows. Acting takes
one observation per seed, `[K, obs]`, and returns `[K, action]`.

Bit-identity with K single learners is not promised (a batched product sums in another order), but
a seed's numbers do not depend on the other seeds', and `seed_state_dict(k)` is seed k's state as a
single `TD3` learner's `state_dict`, so that each seed can be written, evaluated and resumed alone.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from typing import Any, NamedTuple

import numpy as np
import torch

from layered.learners.graphed import GraphedStep
from layered.learners.precision import autocast, loaded_precision, update_region
from layered.learners.stacked import StackedAdam, StackedMLP, StackedReplay, TwinMLP, follow, masked
from layered.learners.staging import Staging
from layered.learners.td3 import TD3, TD3Config, squash


def pick(t: torch.Tensor, seeds: torch.Tensor | None) -> torch.Tensor:
    """The rows of `seeds` of a [K, ...] tensor (all of them for None)."""
    return t if seeds is None else t.index_select(0, seeds)


def transition_rows(obs: np.ndarray, action: np.ndarray, reward: np.ndarray, next_obs: np.ndarray,
                    terminated: np.ndarray, discount: np.ndarray) -> np.ndarray:
    """One transition per seed as replay rows: obs, action, reward, next obs, not done, discount."""
    return np.concatenate([obs, action, np.asarray(reward)[:, None], next_obs,
                           1.0 - np.asarray(terminated, np.float32)[:, None], np.asarray(discount)[:, None]],
                          axis=1, dtype=np.float32)


DecisionPath = Sequence[tuple[np.ndarray, float, int]]
"""A repeating layer's decision, per period of its repeat: (its observation, its reward, discount units)."""

Mask = np.ndarray | torch.Tensor
"""Which seeds take part: [K] booleans on the host, or [K] 0s and 1s on the device (inside a captured step)."""


class Variant(NamedTuple):
    """Which captured update a step replays: with the actor's step or not, and whether the critics' and the
    actor's masks hold every seed (then Adam has no left-out seed to put back: a common case, and a cheaper
    graph)."""

    with_actor: bool
    every_critic: bool
    every_actor: bool


GroupLosses = dict[str, tuple[torch.Tensor, np.ndarray]]
"""What one update of a group returns: per loss name, its value for every seed ([K], on the device) and the
mask of the seeds whose update computed it (the others' values are meaningless)."""


def twinned(state: dict[str, Any]) -> dict[str, Any]:
    """A group's `resume_state` written when its critics were two stacks (`q1`, `q2` and their targets, Adam's
    moments the first's then the second's), as the one stack of twins holds it, so that such a group resumes."""
    pairs = (("critic", "q1", "q2"), ("critic_target", "q1_target", "q2_target"))
    nets = {name: net for name, net in state["nets"].items() if not any(name in pair[1:] for pair in pairs)}
    for name, first, second in pairs:
        a, b = state["nets"][first], state["nets"][second]
        nets[name] = {key: torch.stack([a[key], b[key]], dim=1) for key in a}
    opt = state["critic_opt"]
    n = len(opt["exp_avg"]) // 2
    critic_opt = {**opt, **{key: [torch.stack([m, opt[key][n + j]], dim=1) for j, m in enumerate(opt[key][:n])]
                            for key in ("exp_avg", "exp_avg_sq")}}
    return {**state, "nets": nets, "critic_opt": critic_opt}


class TD3Group:
    """K TD3 learners of one configuration, one per seed, updated together."""

    loss_names = TD3.loss_names

    def __init__(self, learners: Sequence[TD3], seed: int = 0) -> None:
        """Stack `learners` (of the same spaces and settings, one per seed: new ones, or ones started from
        weights, whose optimiser moments and update counts the group takes too); `seed` seeds the group's own
        generators (minibatch indices, smoothing, exploration and warm-up draws)."""
        first = learners[0]
        self.config: TD3Config = first.config
        if self.config.compile == "inductor" or self.config.actor_anchor:
            raise ValueError("a TD3 group runs eagerly or as CUDA graphs (compile 'off' or 'cudagraphs'), without "
                             "actor_anchor (for now)")
        self.k = len(learners)
        self.device = first.device
        self.precision = first.precision
        self.action_space = first.action_space
        self.actor = StackedMLP([learner.actor.net for learner in learners]).to(self.device)
        self.critic = TwinMLP([learner.critic.q1 for learner in learners],
                              [learner.critic.q2 for learner in learners]).to(self.device)
        self.actor_target = StackedMLP([learner.actor_target.net for learner in learners]).to(self.device)
        self.critic_target = TwinMLP([learner.critic_target.q1 for learner in learners],
                                     [learner.critic_target.q2 for learner in learners]).to(self.device)
        for target in (self.actor_target, self.critic_target):
            target.requires_grad_(False)
        self.actor_opt = StackedAdam(list(self.actor.parameters()), self.config.lr, self.k,
                                     first.actor_opt.state_dict())
        self.critic_opt = StackedAdam(list(self.critic.parameters()), self.config.lr, self.k,
                                      first.critic_opt.state_dict(), twins=True)
        Pair = tuple[list[torch.Tensor], list[torch.Tensor]]  # (targets, their sources)
        self._critic_pairs: Pair = (list(self.critic_target.parameters()), list(self.critic.parameters()))
        self._actor_pair: Pair = (list(self.actor_target.parameters()), list(self.actor.parameters()))
        self.centre, self.scale = first.actor.centre.to(self.device), first.actor.scale.to(self.device)
        self._low, self._high = first._low, first._high
        self.obs_dim, self.act_dim = first.obs_space.shape[0], first.action_space.shape[0]
        widths = (self.obs_dim, self.act_dim, 1, self.obs_dim, 1, 1)  # obs, action, reward, next, not done, discount
        self.captured = self.config.compile != "off"  # (its update, acting and stores as CUDA graphs on a GPU)
        self.replay = StackedReplay(self.k, self.config.buffer_size, widths, self.device, self.captured)
        self.torch_rng = torch.Generator(self.device).manual_seed(seed)
        self.staging = Staging(self.device)  # observations and masks on their way to the device
        self.rng = np.random.default_rng(seed)
        self.updates = np.zeros(self.k, np.int64)  # per seed
        # with compile = "cudagraphs": the update as CUDA graphs replayed on the masks of the seeds that update,
        # act and follow, which each update writes here; one graph per `Variant` met (`captured_step`)
        self._masks = torch.zeros((3, self.k), device=self.device)
        self._graphed: dict[Variant, GraphedStep[tuple[torch.Tensor, torch.Tensor | None]]] | None = (
            {} if self.captured else None)
        # and acting, as one more graph per number of observations a seed acts on at once (one in training, an
        # evaluation's lanes): the actor's kernels at one launch, on observations copied in (`actor_outputs`)
        self._acting: dict[int, tuple[torch.Tensor, GraphedStep[torch.Tensor]]] | None = (
            {} if self.captured else None)
        for k, learner in enumerate(learners):  # learners started from weights bring their moments and counts too,
            self.actor_opt.load_seed_state(k, learner.actor_opt.state_dict())  # as a single run keeps them
            self.critic_opt.load_seed_state(k, learner.critic_opt.state_dict())
            self.updates[k] = learner.updates

    def actions(self, obs: torch.Tensor, net: StackedMLP, seeds: torch.Tensor | None = None) -> torch.Tensor:
        """`net`'s actions for `obs` ([K, batch, obs], or those of `seeds`), squashed into the action bounds as the
        single actor does."""
        return self.centre + self.scale * squash(net(obs, seeds=seeds))

    @torch.inference_mode()
    def act(self, obs: np.ndarray, explore: bool) -> np.ndarray:
        """Each seed's action for its observation (`obs`: [K, obs] -> [K, action]); with `explore`,
        Gaussian noise of `exploration_noise` times the half-range, clipped to the bounds."""
        action = self.actor_outputs(obs[:, None])[:, 0].cpu().numpy()
        if explore:
            low, high = self.action_space.low, self.action_space.high
            noise = self.rng.normal(0.0, self.config.exploration_noise, action.shape) * (high - low) / 2
            action = np.clip(action + noise, low, high)
        return action.astype(np.float32)

    @torch.inference_mode()
    def greedy(self, obs: np.ndarray) -> np.ndarray:
        """Each seed's actions without exploration for `n` observations of its own (`obs`: [K, n, obs] ->
        [K, n, action]): the episodes of an evaluation, played side by side."""
        return self.actor_outputs(obs).cpu().numpy()

    def actor_outputs(self, obs: np.ndarray) -> torch.Tensor:
        """The actor's actions on the device for the host's `obs` ([K, n, obs]), to be read before the next call:
        eagerly, or with `cudagraphs` as the graph captured for n observations per seed (the same kernels,
        launched at once: the same actions), the observations copied straight into the tensor it reads."""
        if self._acting is None:
            return self.actions(self.staging.put(obs), self.actor)
        n = obs.shape[1]
        if n not in self._acting:
            with torch.inference_mode(False):  # an ordinary tensor, written in and out of inference mode alike
                seen = torch.zeros((self.k, n, self.obs_dim), device=self.device)
            self._acting[n] = (seen, GraphedStep(lambda: self.actions(seen, self.actor), self.device))
        seen, step = self._acting[n]
        self.staging.put(obs, out=seen)
        return step()

    def act_macs(self) -> int:
        """Multiply-accumulates of one seed's action (as a single learner's `act_macs`)."""
        return sum(w.shape[1] * w.shape[2] for w in self.actor.weights)

    def random_action(self) -> np.ndarray:
        """[K, action] warm-up actions: uniform over `warmup_range` of the range, about its centre."""
        low, high = self.action_space.low, self.action_space.high
        centre, half = (high + low) / 2, (high - low) / 2 * self.config.warmup_range
        return self.rng.uniform(centre - half, centre + half, (self.k, len(low))).astype(np.float32)

    def observe(self, obs: np.ndarray, action: np.ndarray, reward: np.ndarray, next_obs: np.ndarray,
                terminated: np.ndarray, discount: np.ndarray, rows: np.ndarray | None = None,
                paths: Sequence[DecisionPath] | None = None) -> None:
        """Store one transition per seed ([K, ...] arrays), or only in the seeds of the `rows` mask (a
        repeating layer's decision as a whole, its `paths` unused, as a single TD3 learner stores it)."""
        self.replay.add(transition_rows(obs, action, reward, next_obs, terminated, discount), rows)

    def sample(self) -> tuple[torch.Tensor, ...]:
        """A minibatch per seed, drawn uniformly from its own buffer: obs, action, reward, next obs,
        not done, discount, each [K, batch, width] (garbage for a seed with an empty buffer)."""
        return self.replay.sample(self.config.batch_size, self.torch_rng)

    def update(self, rows: np.ndarray | None = None) -> GroupLosses | None:
        """One TD3 update of the seeds in the `rows` mask (default all) that have stored a transition;
        the others are left exactly as they were. None when no seed updates. Captured as a CUDA graph, the losses
        are the graph's own tensors, which its next replay overwrites: copy them to keep them (`PendingLosses`)."""
        rows = (self.replay.stored > 0) if rows is None else rows & (self.replay.stored > 0)
        if not rows.any():
            return None
        self.updates[rows] += 1
        delayed = rows & (self.updates % self.config.policy_delay == 0)
        acting = delayed & (self.updates > self.config.critic_warmup)
        with_actor = bool(acting.any())
        variant = Variant(with_actor, bool(rows.all()), with_actor and bool(acting.all()))
        with update_region(self.precision):
            if self._graphed is None:
                critic, actor = self._update_step(rows, acting, delayed, variant)
            else:
                self.staging.put(np.stack([rows, acting, delayed]), out=self._masks)
                critic, actor = self.captured_step(variant)()
        losses = {"critic": (critic, rows)}
        if actor is not None:
            losses["actor"] = (actor, acting)
        return losses

    def captured_step(self, variant: Variant) -> GraphedStep[tuple[torch.Tensor, torch.Tensor | None]]:
        """The update of `variant` on the device's masks, as the CUDA graph it is captured as (made when first
        asked for)."""
        assert self._graphed is not None, "a group with compile = 'off' updates eagerly"
        if variant not in self._graphed:
            rows, acting, delayed = self._masks
            self._graphed[variant] = GraphedStep(
                functools.partial(self._update_step, rows, acting, delayed, variant),
                self.device, [self.torch_rng])
        return self._graphed[variant]

    def _update_step(self, rows: Mask, acting: Mask, delayed: Mask, variant: Variant
                     ) -> tuple[torch.Tensor, torch.Tensor | None]:
        """A critic step of the `rows` seeds, an actor step of the `acting` ones (if `variant` has one), and the
        critics' targets of the `delayed` ones that do not act yet followed; the losses per seed. The masks
        are on the host, or on the device for a step that never reads them back (a captured one, which
        `variant` tells which of its masks hold every seed)."""
        batch = self.sample()
        noise = torch.randn(batch[1].shape, generator=self.torch_rng, device=self.device)
        critic = self.critic_step(batch, noise, rows, variant.every_critic)
        actor = self.actor_step(batch[0], acting, variant.every_actor) if variant.with_actor else None
        if isinstance(delayed, torch.Tensor) or (delayed & ~acting).any():
            follow(*self._critic_pairs, (self._weights(delayed) - self._weights(acting)) * self.config.tau)
        return critic, actor

    def _weights(self, rows: Mask) -> torch.Tensor:
        """A mask as the device's [K] float mask of 0s and 1s."""
        return rows if isinstance(rows, torch.Tensor) else masked(rows, self.device)

    def critic_step(self, batch: tuple[torch.Tensor, ...], noise: torch.Tensor, rows: Mask | None = None,
                    everyone: bool = False) -> torch.Tensor:
        """One critic step of the seeds in the `rows` mask (default all) on their minibatches,
        with standard-normal smoothing `noise`; the losses per seed. `everyone`: a device mask holds every
        seed (see `StackedAdam.step`)."""
        rows = np.ones(self.k, bool) if rows is None else rows
        seeds = self.subset(rows)
        obs, action, reward, next_obs, not_done, discount, noise = (pick(t, seeds) for t in (*batch, noise))
        cfg = self.config
        with torch.no_grad(), self._precision():
            noise = (noise * cfg.policy_noise).clamp(-cfg.noise_clip, cfg.noise_clip)
            next_action = (self.actions(next_obs, self.actor_target, seeds) + noise * self.scale
                           ).clamp(self._low, self._high)
            pair = torch.cat([next_obs, next_action], dim=-1)
            target = reward + not_done * discount * self.critic_target(pair, seeds=seeds).amin(dim=1)
        with self._precision():  # (each seed's loss: its two critics' mean squared errors, summed)
            errors = self.critic(torch.cat([obs, action], dim=-1), seeds=seeds) - target.unsqueeze(1)
            losses = errors.float().square().mean(dim=(2, 3)).sum(dim=1)
        self.critic_opt.zero_grad()
        losses.sum().backward()
        self.critic_opt.step(rows, everyone)
        return self._per_seed(losses.detach(), seeds)

    def actor_step(self, obs: torch.Tensor, rows: Mask | None = None, everyone: bool = False) -> torch.Tensor:
        """One actor step of the seeds in the `rows` mask (default all) through their Q1, then the soft update
        of their targets; the losses per seed. `everyone`: as `critic_step`'s."""
        rows = np.ones(self.k, bool) if rows is None else rows
        seeds = self.subset(rows)
        obs = pick(obs, seeds)
        with self._precision():
            q1 = self.critic(torch.cat([obs, self.actions(obs, self.actor, seeds)], dim=-1), frozen=True, seeds=seeds,
                             first=True)
            losses = -q1.float().mean(dim=(1, 2))
        self.actor_opt.zero_grad()
        losses.sum().backward()
        self.actor_opt.step(rows, everyone)
        every = everyone or (seeds is None and isinstance(rows, np.ndarray))  # (a host mask that `subset` kept whole)
        weight = self.config.tau if every else self._weights(rows) * self.config.tau
        follow(*self._actor_pair, weight)
        follow(*self._critic_pairs, weight)
        return self._per_seed(losses.detach(), seeds)

    def subset(self, rows: Mask) -> torch.Tensor | None:
        """The indices of the seeds in a host mask that leaves some out, whose networks alone a step then
        computes; None (every seed computed) for all seeds or a device mask, which the host does not read."""
        if isinstance(rows, torch.Tensor) or rows.all():
            return None
        return torch.as_tensor(np.flatnonzero(rows), device=self.device)

    def _per_seed(self, values: torch.Tensor, seeds: torch.Tensor | None) -> torch.Tensor:
        """[K] values from those of `seeds` (0 for the others)."""
        return values if seeds is None else torch.zeros(self.k, device=self.device).index_copy_(0, seeds, values)

    TWINS = ("q1.", "q2.")  # where a single TD3's critic keeps its two networks

    NETS = ("actor", "critic", "actor_target", "critic_target")

    @property
    def replays(self) -> dict[str, StackedReplay]:
        """The replay buffer, which a group's checkpoint keeps apart from `resume_state` (layered.replay_journal)."""
        return {"td3": self.replay}

    def resume_state(self) -> dict[str, Any]:
        """Everything the group's later actions and updates depend on but its replay (see `replays`): networks,
        moments, counts and generators; `load_resume_state` continues from it exactly."""
        return {"nets": {name: getattr(self, name).state_dict() for name in self.NETS},
                "actor_opt": self.actor_opt.state_dict(), "critic_opt": self.critic_opt.state_dict(),
                "updates": torch.from_numpy(self.updates.copy()), "torch_rng": self.torch_rng.get_state(),
                "rng": self.rng.bit_generator.state, "precision": self.precision}

    def load_resume_state(self, state: dict[str, Any]) -> None:
        """Continue from what `resume_state` returned (or, before the two critics were one stack, its two stacks)."""
        state = twinned(state) if "q1" in state["nets"] else state
        for name in self.NETS:
            getattr(self, name).load_state_dict(state["nets"][name])
        self.actor_opt.load_state_dict(state["actor_opt"])
        self.critic_opt.load_state_dict(state["critic_opt"])
        self.updates[:] = state["updates"].numpy()
        self.torch_rng.set_state(state["torch_rng"])
        self.rng.bit_generator.state = state["rng"]
        self.precision = loaded_precision(self.config.precision, self.precision, state)

    def _precision(self) -> torch.autocast:
        """The precision of the update's matrix products (see TD3Config.precision): as a single learner's (no
        weight is cast twice in one region, so autocast's cache of casts, which a captured step forbids, is off)."""
        return autocast(self.precision, self.device, cache=False)

    def seed_state_dict(self, k: int) -> dict[str, Any]:
        """Seed k's networks as a single `TD3` learner's `state_dict` holds them (the optimisers' moments
        and counts per seed too), so that the seed's checkpoint is an ordinary one."""
        actor = {"centre": self.centre.clone(), "scale": self.scale.clone()}
        return {
            "actor": {**self.actor.seed_state(k, "net."), **actor},
            "critic": self.critic.seed_state(k, self.TWINS),
            "actor_target": {**self.actor_target.seed_state(k, "net."), **actor},
            "critic_target": self.critic_target.seed_state(k, self.TWINS),
            "actor_opt": self.actor_opt.seed_state(k), "critic_opt": self.critic_opt.seed_state(k),
            "updates": int(self.updates[k]), "torch_rng": self.torch_rng.get_state(), "precision": self.precision,
        }

    def load_seed_state_dict(self, k: int, state: dict[str, Any]) -> None:
        """Set seed k from a single `TD3` learner's `state_dict` (the group's generators stay as they are)."""
        self.actor.load_seed_state(k, state["actor"], "net.")
        self.actor_target.load_seed_state(k, state["actor_target"], "net.")
        self.critic.load_seed_state(k, state["critic"], self.TWINS)
        self.critic_target.load_seed_state(k, state["critic_target"], self.TWINS)
        self.actor_opt.load_seed_state(k, state["actor_opt"])
        self.critic_opt.load_seed_state(k, state["critic_opt"])
        self.updates[k] = int(state["updates"])
