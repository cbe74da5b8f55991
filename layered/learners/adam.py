"""Adam as a single learner steps it: torch's fused Adam kernel on a network's parameters, keeping and saving
the state that `torch.optim.Adam(fused=True)` keeps and saves, so that the numbers and the checkpoints are
that optimiser's. It is written out rather than taken from `torch.optim` because making any torch optimiser
imports torch's compiler (`torch._dynamo`: about a second and 70 MB of every process that trains or loads a
learner), which eager and CUDA-graph learners never use."""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

import torch

BETAS = (0.9, 0.999)
EPS = 1e-8
# the settings of torch's fused Adam that a saved state names beside the learning rate, as it names them
SETTINGS: dict[str, Any] = {"betas": BETAS, "eps": EPS, "weight_decay": 0, "amsgrad": False, "maximize": False,
                            "foreach": None, "capturable": False, "differentiable": False, "fused": True,
                            "decoupled_weight_decay": False}


class Adam:
    """Adam over `params` at learning rate `lr`: a parameter's moments and step count are made at its first
    step, as torch's are; a loaded state keeps the learning rate given here, not the saved one (so a run
    resumed with another `lr` takes it)."""

    def __init__(self, params: Iterable[torch.Tensor], lr: float) -> None:
        self.params = list(params)
        self.lr = lr
        self.state: dict[int, dict[str, torch.Tensor]] = {}  # by the parameter's index, once it has stepped
        self._settings = {**SETTINGS, "betas": (*BETAS,)}  # (an optimiser's own, saved as one object, as torch's)

    def zero_grad(self, set_to_none: bool = True) -> None:
        """Drop the parameters' gradients (the next backward pass makes new ones)."""
        assert set_to_none, "gradients are dropped, as torch's optimisers drop them by default"
        for p in self.params:
            p.grad = None

    @torch.no_grad()
    def step(self) -> None:
        """One Adam step of the parameters that have a gradient: their counts gain one, then the fused kernel."""
        stepped = [i for i, p in enumerate(self.params) if p.grad is not None]
        if not stepped:
            return
        grads = [g for g in (self.params[i].grad for i in stepped) if g is not None]
        self.make_state(stepped)
        states = [self.state[i] for i in stepped]
        counts = [s["step"] for s in states]
        torch._foreach_add_(counts, 1)
        torch._fused_adam_([self.params[i] for i in stepped], grads,
                           [s["exp_avg"] for s in states], [s["exp_avg_sq"] for s in states], [], counts,
                           amsgrad=False, lr=self.lr, beta1=BETAS[0], beta2=BETAS[1], weight_decay=0.0, eps=EPS,
                           maximize=False, grad_scale=None, found_inf=None)

    def for_compiled_steps(self) -> None:
        """Prepare to be stepped inside a `torch.compile`d function: every moment made now, and the step run
        eagerly, apart from the compiled graph (inductor cannot take the fused kernel's writes into tensors made
        outside it), so that it computes as an eager learner's."""
        self.make_state()
        self.step = torch.compiler.disable(self.step)  # type: ignore[method-assign]

    def make_state(self, indices: Iterable[int] | None = None) -> None:
        """Make the moments and count of the parameters of `indices` (default all) that have none yet."""
        for i in range(len(self.params)) if indices is None else indices:
            if i not in self.state:
                p = self.params[i]
                self.state[i] = {"step": torch.tensor(0.0, dtype=torch.float32, device=p.device),
                                 "exp_avg": torch.zeros_like(p, memory_format=torch.preserve_format),
                                 "exp_avg_sq": torch.zeros_like(p, memory_format=torch.preserve_format)}

    def state_dict(self) -> dict[str, Any]:
        """The state as `torch.optim.Adam(fused=True).state_dict()` gives it: the moments and counts themselves
        by parameter index, and one parameter group."""
        return {"state": dict(self.state),  # (each parameter's own state, as torch gives it)
                "param_groups": [{"lr": self.lr, **self._settings, "params": list(range(len(self.params)))}]}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore a state that `state_dict` (or torch's Adam) gave, each tensor copied onto its parameter's
        device; the learning rate stays this optimiser's."""
        (group,) = state["param_groups"]
        if len(group["params"]) != len(self.params):
            raise ValueError(f"an optimiser state of {len(group['params'])} parameters, for {len(self.params)}")
        self.state = {}
        for i, saved in state["state"].items():
            p = self.params[int(i)]
            self.state[int(i)] = {name: value.to(dtype=torch.float32 if name == "step" else p.dtype, device=p.device,
                                           copy=True) for name, value in saved.items()}
