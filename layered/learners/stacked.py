"""The building blocks of learners for K seeds as one computation: networks, Adam and replay buffers,
each stacked along a leading seed axis so that one operation serves every seed and seeds never mix."""

from __future__ import annotations

import copy
import functools
from collections.abc import Iterable, Iterator, Sequence
from typing import Any

import numpy as np
import torch
from torch import nn

from layered.buffer import put_rows, rows_since
from layered.learners.graphed import GraphedStep
from layered.learners.staging import Staging


def _stack(mlps: Sequence[nn.Sequential]) -> list[torch.Tensor]:
    """The seeds' MLPs (one each, of one shape) layer by layer in an MLP's parameter order (weight, bias,
    weight, bias ...): `[K, in, out]` weights and `[K, 1, out]` biases."""
    layers = [[m for m in mlp if isinstance(m, nn.Linear)] for mlp in mlps]
    stacked = []
    for j in range(len(layers[0])):
        stacked.append(torch.stack([seed[j].weight.detach().T for seed in layers]))
        stacked.append(torch.stack([seed[j].bias.detach()[None] for seed in layers]))
    return stacked


def _apply(x: torch.Tensor, params: Sequence[torch.Tensor]) -> torch.Tensor:
    """`x` through stacked linear layers (weight, bias, ...: one batched product each), ReLUs between them."""
    last = len(params) // 2 - 1
    for j, (weight, bias) in enumerate(zip(params[0::2], params[1::2], strict=True)):
        x = torch.baddbmm(bias, x, weight)
        x = torch.relu(x) if j < last else x
    return x


def _chosen(params: Iterable[torch.Tensor], frozen: bool, seeds: torch.Tensor | None) -> list[torch.Tensor]:
    """Stacked parameters, only those of `seeds` (indices; all for None), detached from autograd if `frozen`."""
    chosen = [t if seeds is None else t.index_select(0, seeds) for t in params]
    return [t.detach() for t in chosen] if frozen else chosen


def _name(prefix: str, j: int) -> str:
    """The name an `nn.Sequential` of linear layers and ReLUs gives its j-th parameter."""
    return f"{prefix}{j - j % 2}.{'weight' if j % 2 == 0 else 'bias'}"


class StackedMLP(nn.Module):
    """K multilayer perceptrons of the same shape, one per seed, as `[K, in, out]` weights."""

    def __init__(self, mlps: Sequence[nn.Sequential]) -> None:
        super().__init__()
        self.stacked = nn.ParameterList(nn.Parameter(t.contiguous()) for t in _stack(mlps))

    @property
    def weights(self) -> list[torch.Tensor]:
        """Each layer's weights, [K, in, out]."""
        return list(self.stacked)[0::2]

    def forward(self, x: torch.Tensor, frozen: bool = False, seeds: torch.Tensor | None = None) -> torch.Tensor:
        """`x`: [K, batch, in] -> [K, batch, out], or with `seeds` (indices) only those seeds' networks, `x`
        being [len(seeds), batch, in]; with `frozen`, the weights take no gradient."""
        return _apply(x, _chosen(self.stacked, frozen, seeds))

    def seed_state(self, k: int, prefix: str) -> dict[str, torch.Tensor]:
        """Seed k's weights under the names an `nn.Sequential` of linear layers and ReLUs gives them."""
        return {_name(prefix, j): _unstack(t, k, j) for j, t in enumerate(self.stacked)}

    @torch.no_grad()
    def load_seed_state(self, k: int, state: dict[str, torch.Tensor], prefix: str) -> None:
        """Set seed k's weights from what `seed_state` names them."""
        for j, t in enumerate(self.stacked):
            t[k] = _restack(state[_name(prefix, j)], j)


class TwinMLP(nn.Module):
    """K seeds' pairs of multilayer perceptrons of one shape (TD3's two critics) as `[K, 2, in, out]` weights:
    a seed's two networks computed on one input together, one batched product per layer for every seed and
    twin (half the operations of two stacks, each seed's numbers as the two stacks give them)."""

    def __init__(self, firsts: Sequence[nn.Sequential], seconds: Sequence[nn.Sequential]) -> None:
        super().__init__()
        self.stacked = nn.ParameterList(nn.Parameter(torch.stack([a, b], dim=1).contiguous())
                                        for a, b in zip(_stack(firsts), _stack(seconds), strict=True))

    def forward(self, x: torch.Tensor, frozen: bool = False, seeds: torch.Tensor | None = None,
                first: bool = False) -> torch.Tensor:
        """`x`: [K, batch, in] -> both twins' outputs, [K, 2, batch, out]; with `first` the first twin's alone,
        [K, batch, out]. `seeds` and `frozen` as `StackedMLP`'s."""
        params = _chosen(self.stacked, frozen, seeds)
        if first:
            return _apply(x, [t[:, 0] for t in params])
        k = x.shape[0]
        both = _apply(x.unsqueeze(1).expand(k, 2, *x.shape[1:]).flatten(0, 1), [t.flatten(0, 1) for t in params])
        return both.unflatten(0, (k, 2))

    def seed_state(self, k: int, prefixes: tuple[str, str]) -> dict[str, torch.Tensor]:
        """Seed k's two networks under the names two `nn.Sequential`s under `prefixes` give them."""
        return {_name(prefix, j): _unstack(t[:, i], k, j)
                for i, prefix in enumerate(prefixes) for j, t in enumerate(self.stacked)}

    @torch.no_grad()
    def load_seed_state(self, k: int, state: dict[str, torch.Tensor], prefixes: tuple[str, str]) -> None:
        """Set seed k's two networks from what `seed_state` names them."""
        for i, prefix in enumerate(prefixes):
            for j, t in enumerate(self.stacked):
                t[k, i] = _restack(state[_name(prefix, j)], j)


class StackedAdam:
    """Adam over stacked `[K, ...]` parameters with a step count per seed: a seed left out of an update
    keeps its parameters, moments and count exactly. Each seed's slice of each parameter (each twin's, for a
    `TwinMLP`'s) is handed to torch's fused Adam as a tensor of its own, with its own count, so that one call
    steps the chosen seeds with the arithmetic of a single network's (fused) Adam, bit for bit (the kernel
    computes a tensor's tail apart from its whole vectors, so the cut into tensors decides the rounding)."""

    def __init__(self, params: Sequence[torch.Tensor], lr: float, k: int, template: dict[str, Any],
                 twins: bool = False) -> None:
        """`template`: a single network's Adam `state_dict`, whose `param_groups` a seed's state takes. `twins`:
        the parameters are a `TwinMLP`'s, `[K, 2, ...]`, which a single network's Adam holds as the first twin's
        parameters, then the second's."""
        self.params = list(params)
        self._nets = 2 if twins else 1  # slices per seed
        self.lr = lr
        self.beta1, self.beta2 = template["param_groups"][0]["betas"]
        self.eps = template["param_groups"][0]["eps"]
        self.param_groups = template["param_groups"]
        self.exp_avg = [torch.zeros_like(p) for p in self.params]
        self.exp_avg_sq = [torch.zeros_like(p) for p in self.params]
        # one count per parameter and seed, as torch's Adam keeps one per parameter (fused Adam adds 1 to each)
        self._counts = torch.zeros((len(self.params), k), device=self.params[0].device)
        # every seed's slices of each parameter, moment and count (seed by seed, a twin's after the other's), cut
        # once: they are written in place only, so the slices stay theirs (a gradient is a new tensor at every
        # backward pass and is cut at each step)
        with torch.no_grad():  # (as `step` cuts and writes them)
            self._slices = [(self._cut(p), self._cut(m), self._cut(v), self._counts_cut(c)) for p, m, v, c
                            in zip(self.params, self.exp_avg, self.exp_avg_sq, self._counts, strict=True)]
        # and every seed's slices of all parameters, moments and counts in one list each (an update of every seed)
        self._every = [[view for views in part for view in views] for part in zip(*self._slices, strict=True)]

    def _cut(self, t: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """A stacked tensor's slices: a seed's, or each twin's of a seed, in turn."""
        return t.flatten(0, 1).unbind(0) if self._nets == 2 else t.unbind(0)

    def _counts_cut(self, counts: torch.Tensor) -> list[torch.Tensor]:
        """A parameter's [K] counts as its slices' counts: a seed's twins share the seed's."""
        return [n for n in counts.unbind(0) for _ in range(self._nets)]

    @property
    def steps(self) -> torch.Tensor:
        """Each seed's step count, [K]."""
        return self._counts[0]

    def zero_grad(self) -> None:
        for p in self.params:
            p.grad = None

    @torch.no_grad()
    def step(self, rows: np.ndarray | torch.Tensor, everyone: bool = False) -> None:
        """One Adam step of the seeds in `rows` from the parameters' gradients. `rows` is a [K] boolean mask on
        the host, and only its seeds are handed to Adam; or a [K] float mask of 0s and 1s on the device, and
        every seed is stepped and the others put back, without reading the mask on the host (for a captured
        update). `everyone`: the caller knows that the device mask holds every seed, so none is put back."""
        if isinstance(rows, np.ndarray):
            self._adam(np.flatnonzero(rows).tolist())
            return
        if everyone:
            self._adam(range(self._counts.shape[1]))
            return
        before = [t.clone() for t in (*self.params, *self.exp_avg, *self.exp_avg_sq)]
        self._adam(range(self._counts.shape[1]))
        for t, kept in zip((*self.params, *self.exp_avg, *self.exp_avg_sq), before, strict=True):
            t.copy_(torch.where(rows.view((-1,) + (1,) * (t.dim() - 1)) > 0, t, kept))
        self._counts -= 1 - rows  # (small whole numbers: exact)

    def _adam(self, seeds: Sequence[int]) -> None:
        """torch's fused Adam on the given seeds' slices of every parameter, each slice with its own count."""
        if not seeds:
            return
        every = len(seeds) == self._counts.shape[1]
        cuts = []  # each gradient's slices (a cut each: a Python index each cost more than Adam)
        for p in self.params:
            assert p.grad is not None, "step follows a backward pass through every parameter"
            cuts.append(self._cut(p.grad))
        # the counts of the seeds stepped get one more each, as fused Adam's own step adds 1 to every count it is
        # handed (here in one operation, not one per slice); then torch's fused Adam kernel itself on the slices
        if every:  # (the slices of every seed in one list, made once: only the gradients' are new)
            params, exp_avg, exp_avg_sq, counts = self._every
            grads = [g for cut in cuts for g in cut]
            self._counts += 1
        else:
            chosen = [k * self._nets + i for k in seeds for i in range(self._nets)]
            params, exp_avg, exp_avg_sq, counts = ([views[j] for views in part for j in chosen]
                                                   for part in zip(*self._slices, strict=True))
            grads = [cut[j] for cut in cuts for j in chosen]
            self._counts[:, list(seeds)] += 1
        torch._fused_adam_(params, grads, exp_avg, exp_avg_sq, [], counts, lr=self.lr, beta1=self.beta1,
                           beta2=self.beta2, weight_decay=0.0, eps=self.eps, amsgrad=False, maximize=False)

    def state_dict(self) -> dict[str, Any]:
        """Every seed's moments and step count, for resuming a group: the tensors themselves, as a module's
        `state_dict` gives its parameters (a checkpoint written beside training copies them first)."""
        return {"exp_avg": list(self.exp_avg), "exp_avg_sq": list(self.exp_avg_sq), "steps": self.steps}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore what `state_dict` returned (the learning rate stays the configuration's), in place: the slices
        that `step` hands to Adam are views of these very tensors."""
        for mine, saved in ((self.exp_avg, state["exp_avg"]), (self.exp_avg_sq, state["exp_avg_sq"])):
            for t, value in zip(mine, saved, strict=True):
                t.copy_(value)
        self._counts[:] = state["steps"].to(self._counts.device)

    def seed_state(self, k: int) -> dict[str, Any]:
        """Seed k's part, in the layout of a single network's Adam (weights `[out, in]`, biases `[out]`)."""
        state = {}
        if float(self.steps[k]):  # a seed never stepped has no moments, as a new Adam has none
            step = self.steps[k].detach().cpu()
            state = {index: {"step": step.clone(), "exp_avg": _unstack(m, k, j), "exp_avg_sq": _unstack(v, k, j)}
                     for index, j, m, v in self._singles()}
        return {"state": state, "param_groups": copy.deepcopy(self.param_groups)}

    def load_seed_state(self, k: int, state: dict[str, Any]) -> None:
        """Set seed k's part from a single network's Adam `state_dict`."""
        self._counts[:, k] = 0.0
        for index, j, m, v in self._singles():
            moments = state["state"].get(index)
            m[k], v[k] = (0.0, 0.0) if moments is None else (_restack(moments["exp_avg"], j),
                                                              _restack(moments["exp_avg_sq"], j))
            if moments is not None:
                self._counts[j, k] = float(moments["step"])

    def _singles(self) -> Iterator[tuple[int, int, torch.Tensor, torch.Tensor]]:
        """For each parameter of a single network's Adam: its index there, the index j of the stacked parameter
        holding it, and that parameter's moments as [K, ...] (a twin's view of them for `twins`)."""
        n = len(self.params)
        for i in range(self._nets):
            for j, (m, v) in enumerate(zip(self.exp_avg, self.exp_avg_sq, strict=True)):
                yield (i * n + j, j, m[:, i], v[:, i]) if self._nets == 2 else (j, j, m, v)


def _unstack(t: torch.Tensor, k: int, index: int) -> torch.Tensor:
    """Seed k's slice of a stacked weight (even index, `[K, in, out]`) or bias (odd, `[K, 1, out]`),
    as an `nn.Linear` holds it."""
    t = t.detach()
    return t[k].T.clone(memory_format=torch.contiguous_format) if index % 2 == 0 else t[k, 0].clone()


def _restack(t: torch.Tensor, index: int) -> torch.Tensor:
    """An `nn.Linear`'s weight or bias in the layout of one seed's slice of the stacked one."""
    return t.T if index % 2 == 0 else t[None]


class StackedReplay:
    """K seeds' replay buffers as one `[K, capacity, row]` tensor of rows cut into fields of the given
    widths; each seed samples uniformly from its own stored rows, all in one row selection."""

    def __init__(self, k: int, capacity: int, widths: Sequence[int], device: torch.device,
                 captured: bool = False) -> None:
        """`captured`: on a GPU, store as a CUDA graph (one for every seed's rows, one for a mask's), a launch
        instead of the eight of an eager store; on a CPU it changes nothing."""
        self.k, self.capacity = k, capacity
        self._cuts = np.cumsum((0, *widths)).tolist()
        self._rows = torch.empty((k, capacity, self._cuts[-1]), device=device)
        self.sizes = torch.zeros(k, dtype=torch.long, device=device)
        self._next = torch.zeros(k, dtype=torch.long, device=device)
        self._seeds = torch.arange(k, device=device)
        self._firsts = self._seeds[:, None] * capacity  # each seed's first row in [K * capacity, row]
        self._staging = Staging(device)
        self._stores: dict[bool, GraphedStep[None]] | None = {} if captured and device.type == "cuda" else None
        self.stored = np.zeros(k, np.int64)  # rows added per seed, known on the host

    def add(self, data: np.ndarray, rows: np.ndarray | None = None) -> None:
        """Store row `data[k]` ([K, row]) for every seed, or only for the seeds of the `rows` mask. Nothing is
        read back, so that on a GPU the host goes on at once: the mask travels with the rows."""
        if rows is None or rows.all():
            every, staged = True, self._staging.put(data)
        else:
            every, staged = False, self._staging.put(np.concatenate([data, rows[:, None]], axis=1, dtype=np.float32))
        if self._stores is None:
            self._store(staged, every)
        else:  # (on a GPU the staged tensor is the same at every call of its shape: the graph reads it there)
            if every not in self._stores:
                self._stores[every] = GraphedStep(functools.partial(self._store, staged, every), self._rows.device)
            self._stores[every]()
        self.stored += 1 if rows is None else rows

    def _store(self, staged: torch.Tensor, every: bool) -> None:
        """Write the staged rows (with the mask as a last column unless `every`) into each seed's next slot: a
        seed left out has its next slot written over with what it holds and its counts advanced by 0."""
        step: int | torch.Tensor = 1
        new = staged
        if not every:
            step = staged[:, -1] > 0
            new = torch.where(step[:, None], staged[:, :-1], self._rows[self._seeds, self._next])
        self._rows[self._seeds, self._next] = new
        self._next.add_(step).remainder_(self.capacity)
        self.sizes.add_(step).clamp_(max=self.capacity)

    def sample(self, batch: int, generator: torch.Generator) -> tuple[torch.Tensor, ...]:
        """A minibatch per seed, each field `[K, batch, width]` (garbage for a seed with nothing stored)."""
        u = torch.rand((self.k, batch), generator=generator, device=self._rows.device)
        idx = (u * self.sizes[:, None]).long() + self._firsts
        # whole rows picked out of the flattened buffers: on a CPU 4-12x a gather of their elements (K = 8-32)
        rows = self._rows.view(-1, self._cuts[-1]).index_select(0, idx.view(-1)).view(self.k, batch, -1)
        return tuple(rows[:, :, a:b] for a, b in zip(self._cuts, self._cuts[1:], strict=False))

    def seed_rows(self, k: int) -> list[np.ndarray]:
        """Seed k's stored rows in the order stored (until the buffer wraps), cut into fields."""
        rows = self._rows[k, : int(self.sizes[k])].cpu().numpy()
        return [rows[:, a:b] for a, b in zip(self._cuts, self._cuts[1:], strict=False)]

    def rows_since(self, since: np.ndarray) -> tuple[torch.Tensor, np.ndarray]:
        """`layered.buffer.rows_since` of the K buffers: what a group's checkpoint writes of them."""
        return rows_since(self._rows, self.stored, since)

    def restore(self, stored: np.ndarray, segments: Iterable[tuple[torch.Tensor, np.ndarray, np.ndarray]]) -> None:
        """Refill the buffers from `rows_since`'s outputs (see `layered.buffer.put_rows`) and set each seed's counts
        to `stored`."""
        put_rows(self._rows, stored, segments)
        self.stored[:] = stored
        self.sizes.copy_(torch.from_numpy(np.minimum(stored, self.capacity)))
        self._next.copy_(torch.from_numpy(stored % self.capacity))


def masked(rows: np.ndarray, device: torch.device) -> torch.Tensor:
    """A [K] boolean mask as a float mask of 0s and 1s on `device` (the weights of a masked soft update)."""
    return torch.as_tensor(rows, dtype=torch.float32, device=device)


@torch.no_grad()
def follow(targets: list[torch.Tensor], sources: list[torch.Tensor], weight: float | torch.Tensor) -> None:
    """The soft update of each target towards its source: by `weight` in every seed (all of them in one operation),
    or by `weight[k]` in seed k ([K]; 0 leaves a seed's as it is)."""
    if isinstance(weight, float):
        torch._foreach_lerp_(targets, sources, weight)
        return
    for target, source in zip(targets, sources, strict=True):
        target.lerp_(source, weight.view((-1,) + (1,) * (target.dim() - 1)))
