"""TD3 (Fujimoto et al., 2018) with the TLA paper's settings as defaults."""

from __future__ import annotations

import copy
import itertools
from collections.abc import Callable
from typing import Annotated, Any, Literal

import numpy as np
import torch
from gymnasium.spaces import Box
from pydantic import Field, model_validator
from torch import nn
from torch.func import functional_call

from layered.buffer import Batch, ReplayBuffer, Transition
from layered.learners.adam import Adam
from layered.learners.base import Flag, Learner, LearnerConfig, Losses, Whole
from layered.learners.precision import autocast, loaded_precision, resolve_precision, update_region
from layered.outputs import OutputLayout


class TD3Config(LearnerConfig):
    """TD3 settings; defaults are those of the TLA paper and of the original TD3."""

    kind: Literal["td3"] = "td3"
    hidden: tuple[Annotated[Whole, Field(gt=0)], ...] = (400, 300)
    """Hidden layer widths of the actor and of each critic."""
    lr: float = Field(default=3e-4, gt=0)
    """Adam learning rate of actor and critics."""
    batch_size: Whole = Field(default=256, gt=0)
    """Transitions per gradient update."""
    tau: float = Field(default=0.005, gt=0, le=1)
    """Polyak rate of the target networks."""
    policy_noise: float = Field(default=0.2, ge=0)
    """Std of target-policy smoothing noise, as a fraction of the action half-range."""
    noise_clip: float = Field(default=0.5, ge=0)
    """Clip of the smoothing noise, as a fraction of the action half-range."""
    exploration_noise: float = Field(default=0.1, ge=0)
    """Std of Gaussian exploration noise, as a fraction of the action half-range."""
    warmup_range: float = Field(default=1.0, gt=0, le=1)
    """Random warm-up actions are uniform over this fraction of the action range, about its centre
    (0.5 on a residual layer of twice the environment's range: uniform over the environment's)."""
    policy_delay: Whole = Field(default=2, gt=0)
    """Critic updates per actor and target update."""
    critic_warmup: Whole = Field(default=0, ge=0)
    """Critic updates before the actor's first: until then the actor keeps its initial policy (with
    `zero_output`, a residual layer that adds nothing) while the critic learns the values of what
    that policy does, and the targets follow the critic as usual."""
    actor_anchor: float = Field(default=0.0, ge=0)
    """Weight of a term in the actor's loss that holds its output near the middle of its range:
    mean ((output - middle) / half-range)², against the critic's value divided by its mean
    magnitude (TD3+BC's form, with the middle as the behaviour), so that a residual layer moves
    away from adding nothing only where its critic shows a clear gain. 0 leaves TD3's loss as is."""
    buffer_size: Whole = Field(default=1_000_000, gt=0)
    """Replay capacity in transitions."""
    device: Literal["cpu", "cuda", "auto"] = "cpu"
    """Where networks, replay buffer and updates live: `cuda` (a GPU), `cpu`, or `auto` (cuda where
    one is available). Exact resumes and the suite's checks are promised on CPU."""
    zero_output: Flag = False
    """Start the actor's last layer at zero, so that it outputs the middle of its range until it
    learns: a residual layer then starts by adding nothing to the layers above it."""
    precision: Literal["auto", "float32", "bfloat16", "tf32"] = "auto"
    """Precision of the updates' matrix products: `bfloat16` (autocast; weights, optimiser and acting
    stay float32), `float32`, `tf32` (float32 products in TensorFloat-32 on a GPU from Ampere on, for a
    task where bfloat16 learns worse; GPU only), or `auto`: bfloat16 where the device multiplies it in
    hardware (GPUs that do; CPUs with AVX-512 BF16, AMX or Arm BF16), float32 elsewhere. bfloat16 learns
    as float32 does on the tasks checked in docs/experiments.md, at about twice the update rate on such a CPU.
    A checkpoint records the precision its learner computed in; with `auto`, a run resumed from it
    (or started from its weights) keeps that precision wherever it runs. A run's run.json records it too,
    and `layered report` counts a recipe's runs in bfloat16 and in float32 as two setups."""
    compile: Literal["off", "inductor", "cudagraphs"] = "off"
    """Compile the critic and actor steps with torch.compile: `inductor` (its default mode), or
    `cudagraphs` (GPU only): the update replayed as CUDA graphs. The first updates then wait for
    compilation or capture; results match eager ones closely, not bit for bit. In a group
    (`--seeds`), `cudagraphs` captures the whole update of all its seeds (sampling, both critics, the
    actor's step, the targets) after three eager updates, as one CUDA graph per kind of update met
    (with the actor's step or without; every seed taking part, or some left out and put back), one of
    them replayed per update, and its acting, in training and in evaluations, as one more per number
    of observations a seed acts on at once (the very actions eager acting gives);
    `inductor` is refused there. A single run's learners with `cudagraphs` train as groups of one
    seed in the same way (`layered.learners.captured`). A GPU-trained run evaluated on a CPU acts
    there uncompiled."""


    def on_device(self, device: str) -> TD3Config:
        if device != "cpu":
            return self.model_copy(update={"device": device})
        # a GPU's settings mean nothing on a CPU, where a GPU-trained run is evaluated (acting is float32 anyway)
        return self.model_copy(update={"device": device, "compile": "off" if self.compile == "cudagraphs" else
                                       self.compile, "precision": "float32" if self.precision == "tf32" else
                                       self.precision})

    def unavailable(self) -> list[tuple[str, str]]:
        if torch.cuda.is_available():
            return []
        problems = []
        if self.device == "cuda":
            problems.append(("learner.device", "'cuda' asked for, but torch sees no CUDA GPU here (use 'cpu' or "
                             "'auto')"))
        if self.compile == "cudagraphs":
            problems.append(("learner.compile", "'cudagraphs' asked for, but torch sees no CUDA GPU here (use "
                             "'inductor' or 'off')"))
        if self.precision == "tf32":
            problems.append(("learner.precision", "'tf32' asked for, but torch sees no CUDA GPU here (use "
                             "'float32', 'bfloat16' or 'auto')"))
        return problems

    @model_validator(mode="after")
    def _gpu_settings_need_a_gpu(self) -> TD3Config:
        if self.device == "cpu":
            if self.compile == "cudagraphs":
                raise ValueError("compile = 'cudagraphs' needs the learner on a GPU: device = 'cuda' or 'auto'")
            if self.precision == "tf32":
                raise ValueError("precision = 'tf32' is a GPU's: device = 'cuda' or 'auto' (on a CPU: 'float32', "
                                 "'bfloat16' or 'auto')")
        return self


def resolve_device(name: str) -> torch.device:
    """The torch device of a `device` setting; `cuda` without a GPU is refused."""
    if name == "auto":
        name = "cuda" if torch.cuda.is_available() else "cpu"
    if name == "cuda" and not torch.cuda.is_available():
        raise ValueError("device 'cuda' asked for, but torch sees no CUDA GPU here (use 'cpu' or 'auto')")
    return torch.device(name)


def compiled(step: Callable[..., torch.Tensor], mode: str, device: torch.device) -> Callable[..., torch.Tensor]:
    """`step` as TD3Config.compile asks: eager, inductor, or inductor with CUDA graphs."""
    if mode == "off":
        return step
    if mode == "inductor":
        return torch.compile(step)
    if device.type != "cuda":
        raise ValueError(f"compile = 'cudagraphs' needs the learner on a GPU (device is {device.type!r})")
    graph = torch.compile(step, mode="reduce-overhead")

    def replayed(*args: Any) -> torch.Tensor:
        # a graph's output lives in its static memory, which the next replay overwrites; the loop keeps each
        # update's loss until it reads the losses back, so each replay starts a new step and its loss is copied
        torch.compiler.cudagraph_mark_step_begin()
        return graph(*args).clone()

    return replayed


def mlp(sizes: tuple[int, ...]) -> nn.Sequential:
    """ReLU multilayer perceptron with a linear last layer."""
    layers: list[nn.Module] = []
    for i, (a, b) in enumerate(itertools.pairwise(sizes)):
        layers.append(nn.Linear(a, b))
        if i < len(sizes) - 2:
            layers.append(nn.ReLU())
    return nn.Sequential(*layers)


def squash(x: torch.Tensor) -> torch.Tensor:
    """tanh of the actor's last layer, always in float32: bfloat16 rounds tanh to exactly ±1 beyond |x| ≈ 3, where
    its gradient is zero, and an actor pushed there (as real-time tasks push it) could never come back."""
    return torch.tanh(x.float())


class Actor(nn.Module):
    """Deterministic policy squashed into the action box by tanh."""

    centre: torch.Tensor
    scale: torch.Tensor

    def __init__(self, obs_dim: int, low: np.ndarray, high: np.ndarray, hidden: tuple[int, ...]) -> None:
        super().__init__()
        self.net = mlp((obs_dim, *hidden, len(low)))
        self.register_buffer("centre", torch.as_tensor((high + low) / 2, dtype=torch.float32))
        self.register_buffer("scale", torch.as_tensor((high - low) / 2, dtype=torch.float32))

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        return self.centre + self.scale * squash(self.net(obs))


class TwinCritic(nn.Module):
    """Two independent Q-networks on (obs, action)."""

    def __init__(self, obs_dim: int, action_dim: int, hidden: tuple[int, ...]) -> None:
        super().__init__()
        self.q1 = mlp((obs_dim + action_dim, *hidden, 1))
        self.q2 = mlp((obs_dim + action_dim, *hidden, 1))

    def forward(self, obs: torch.Tensor, action: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        x = torch.cat([obs, action], dim=-1)
        return self.q1(x), self.q2(x)


def linear_macs(module: nn.Module) -> int:
    """Multiply-accumulates of one forward pass of a single input through `module`'s linear layers."""
    return sum(m.in_features * m.out_features for m in module.modules() if isinstance(m, nn.Linear))


class TD3(Learner):
    """Twin critics, delayed actor updates and target policy smoothing (registered as "td3" with its captured
    form, `layered.learners.captured`)."""

    Config = TD3Config
    config: TD3Config
    loss_names = ("critic", "actor")

    def __init__(self, obs_space: Box, action_space: Box, layout: OutputLayout, config: TD3Config,
                 seed: int) -> None:
        super().__init__(obs_space, action_space, layout, config, seed)
        self.device = resolve_device(config.device)
        self.precision = resolve_precision(config.precision, self.device)
        torch.manual_seed(seed)  # network initialisation, on the CPU whatever the device: the same weights
        self.torch_rng = torch.Generator(self.device).manual_seed(seed)  # target smoothing noise
        obs_dim, act_dim = obs_space.shape[0], action_space.shape[0]
        low, high = action_space.low.astype(np.float64), action_space.high.astype(np.float64)
        self.actor = Actor(obs_dim, low, high, config.hidden).to(self.device)
        if config.zero_output:
            last = self.actor.net[-1]
            assert isinstance(last, nn.Linear)
            nn.init.zeros_(last.weight)
            nn.init.zeros_(last.bias)
        self.critic = TwinCritic(obs_dim, act_dim, config.hidden).to(self.device)
        self.actor_target = copy.deepcopy(self.actor).requires_grad_(False)
        self.critic_target = copy.deepcopy(self.critic).requires_grad_(False)
        self.actor_opt = Adam(self.actor.parameters(), config.lr)
        self.critic_opt = Adam(self.critic.parameters(), config.lr)
        if config.compile != "off":  # the steps compiled below step them
            self.actor_opt.for_compiled_steps()
            self.critic_opt.for_compiled_steps()
        self.buffer = ReplayBuffer(obs_dim, act_dim, config.buffer_size, self.device)
        self.updates = 0
        self._low = torch.as_tensor(low, dtype=torch.float32, device=self.device)
        self._high = torch.as_tensor(high, dtype=torch.float32, device=self.device)
        self._half = (self._high - self._low) / 2
        self._half_host = (action_space.high - action_space.low) / 2  # the exploration noise's scale, on the host
        self._actor_layers = [(m.weight, m.bias) for m in self.actor.net if isinstance(m, nn.Linear)]
        self._target_pairs: list[tuple[list[torch.Tensor], list[torch.Tensor]]] = [
            (list(target.parameters()), list(net.parameters()))
            for net, target in ((self.actor, self.actor_target), (self.critic, self.critic_target))
        ]
        self._critic_step = compiled(self._critic_step_eager, config.compile, self.device)
        self._actor_step = compiled(self._actor_step_eager, config.compile, self.device)

    def random_action(self) -> np.ndarray:
        if self.config.warmup_range == 1.0:  # the whole range: the base draw, bit for bit as before the setting
            return super().random_action()
        low, high = self.action_space.low, self.action_space.high
        centre, half = (high + low) / 2, (high - low) / 2 * self.config.warmup_range
        return self.rng.uniform(centre - half, centre + half).astype(np.float32)

    @torch.inference_mode()
    def act(self, obs: np.ndarray, explore: bool) -> np.ndarray:
        # The actor's forward pass written out on its parameters: the same operations and numbers as
        # `self.actor(obs)`, without autograd and module-call overhead (acting happens every step).
        x = torch.from_numpy(np.ascontiguousarray(obs, np.float32)).to(self.device)
        for k, (weight, bias) in enumerate(self._actor_layers):
            x = nn.functional.linear(x, weight, bias)
            x = torch.relu(x) if k < len(self._actor_layers) - 1 else x
        action = (self.actor.centre + self.actor.scale * squash(x)).cpu().numpy()
        if explore:
            noise = self.rng.normal(0.0, self.config.exploration_noise, size=action.shape) * self._half_host
            action = np.clip(action + noise, self.action_space.low, self.action_space.high)
        return action.astype(np.float32)

    def greedy(self, obs: np.ndarray) -> np.ndarray:
        return self.act(obs, explore=False)  # (the actor's pass takes a batch as it takes one observation)

    def policy(self) -> nn.Module:
        return copy.deepcopy(self.actor).cpu().eval().requires_grad_(False)

    def act_macs(self) -> int:
        return linear_macs(self.actor)

    def computes_in(self) -> str:
        return self.precision

    def observe(self, transition: Transition) -> None:
        self.buffer.add(transition)

    def update(self) -> Losses | None:
        if len(self.buffer) == 0:
            return None
        with update_region(self.precision):
            return self._update()

    def _update(self) -> Losses:
        b = self.buffer.sample(self.config.batch_size, self.rng)
        # the smoothing noise is drawn here: a compiled step cannot draw from a generator
        noise = torch.randn(b.action.shape, generator=self.torch_rng, device=self.device)
        critic_loss = self._critic_step(b, noise)
        self.updates += 1
        if self.updates % self.config.policy_delay:
            return {"critic": critic_loss}
        if self.updates <= self.config.critic_warmup:
            self._follow(self._target_pairs[1:])  # the critic's targets alone: the actor waits
            return {"critic": critic_loss}
        return {"critic": critic_loss, "actor": self._actor_step(b.obs)}

    def _critic_step_eager(self, b: Batch, noise: torch.Tensor) -> torch.Tensor:
        """One critic step on `b`, with standard-normal `noise` for target smoothing; the loss."""
        cfg = self.config
        with torch.no_grad(), self._precision():
            noise = (noise * cfg.policy_noise).clamp(-cfg.noise_clip, cfg.noise_clip)
            next_action = (self.actor_target(b.next_obs) + noise * self._half).clamp(self._low, self._high)
            q1_next, q2_next = self.critic_target(b.next_obs, next_action)
            target = b.reward + b.not_done * b.discount * torch.min(q1_next, q2_next)
        with self._precision():
            q1, q2 = self.critic(b.obs, b.action)
            critic_loss = nn.functional.mse_loss(q1, target) + nn.functional.mse_loss(q2, target)
        self.critic_opt.zero_grad(set_to_none=True)
        critic_loss.backward()
        self.critic_opt.step()
        return critic_loss.detach()

    def _actor_step_eager(self, obs: torch.Tensor) -> torch.Tensor:
        """One actor step through Q1 and the soft update of both targets; the actor's loss."""
        # Q1 on detached weights: the actor's gradient flows through it, Q1's own is not computed
        frozen_q1 = {name: p.detach() for name, p in self.critic.q1.named_parameters()}
        with self._precision():
            action = self.actor(obs)
            q1 = functional_call(self.critic.q1, frozen_q1, (torch.cat([obs, action], dim=-1),))
            loss = -q1.mean()
            if self.config.actor_anchor:
                off_centre = ((action - self.actor.centre) / self.actor.scale).square().mean()
                loss = loss / q1.detach().abs().mean() + self.config.actor_anchor * off_centre
        self.actor_opt.zero_grad(set_to_none=True)
        loss.backward()
        self.actor_opt.step()
        self._follow(self._target_pairs)
        return loss.detach()

    @torch.no_grad()  # else each update's lerp joins the targets' autograd history, which then grows
    def _follow(self, pairs: list[tuple[list[torch.Tensor], list[torch.Tensor]]]) -> None:
        """The soft update of each (targets, sources) pair's targets towards its sources."""
        for targets, sources in pairs:
            torch._foreach_lerp_(targets, sources, self.config.tau)

    def _precision(self) -> torch.autocast:
        """The precision of the update's matrix products (see TD3Config.precision)."""
        return autocast(self.precision, self.device)

    def state_dict(self) -> dict[str, Any]:
        return {
            "actor": self.actor.state_dict(),
            "critic": self.critic.state_dict(),
            "actor_target": self.actor_target.state_dict(),
            "critic_target": self.critic_target.state_dict(),
            "actor_opt": self.actor_opt.state_dict(),
            "critic_opt": self.critic_opt.state_dict(),
            "updates": self.updates,
            "torch_rng": self.torch_rng.get_state(),
            "precision": self.precision,
        }

    @property
    def replays(self) -> dict[str, ReplayBuffer]:
        return {"td3": self.buffer}

    def load_resume_state(self, state: dict[str, Any]) -> None:
        super().load_resume_state(state)
        if "buffer" in state:  # a checkpoint of layered 0.1.0, which held the buffer
            self.buffer.load_fields(state["buffer"])

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.actor.load_state_dict(state["actor"])
        self.critic.load_state_dict(state["critic"])
        self.actor_target.load_state_dict(state["actor_target"])
        self.critic_target.load_state_dict(state["critic_target"])
        self.actor_opt.load_state_dict(state["actor_opt"])
        self.critic_opt.load_state_dict(state["critic_opt"])
        self.updates = int(state["updates"])
        self.torch_rng.set_state(state["torch_rng"])
        self.precision = loaded_precision(self.config.precision, self.precision, state)
