"""Run an exported stack without `layered`: numpy plus torch (TorchScript) or onnxruntime (ONNX).

`layered export` copies this file into the export directory beside `stack.json` and one policy
file per layer, so that a robot loop needs only:

    from layered_runtime import load_stack
    stack = load_stack("exported/")     # picks TorchScript or ONNX from the files present
    stack.reset()                       # at the start of every episode
    action = stack.step(obs)            # once per base step: observation in, executed action out

It acts as `layered eval` does (no exploration): layers decide on their periods, hold their
outputs, land them after their delays, and merge through their combiners with the evaluation
thresholds. `layered.stack.Stack` is the reference; the export tests check that both execute the
same actions on real episodes. This file imports nothing of `layered`: keep it that way.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

FORMAT = 1
ADD, COMMIT, DEFER = "add", "commit", "defer"
Policy = Callable[[np.ndarray], np.ndarray]


class ExportedStack:
    """A trained stack acting one base step at a time, from its `stack.json` spec and one policy per
    present layer."""

    def __init__(self, spec: dict[str, Any], policies: dict[str, Policy]) -> None:
        if spec.get("format") != FORMAT:
            raise ValueError(f"stack.json has format {spec.get('format')!r}; this runtime reads format {FORMAT}")
        self.spec = spec
        self.layers = spec["layers"]
        self.names = [layer["name"] for layer in self.layers]
        self.active = [self.names.index(name) for name in spec["active"]]
        self.action_dim = int(spec["action_dim"])
        self.low = np.asarray(spec["action_low"], np.float32)
        self.high = np.asarray(spec["action_high"], np.float32)
        self.out_low = [np.asarray(layer["output_low"], np.float32) for layer in self.layers]
        self.out_high = [np.asarray(layer["output_high"], np.float32) for layer in self.layers]
        self.thresholds = [None if layer["threshold"] is None else np.asarray(layer["threshold"], np.float32)
                           for layer in self.layers]
        self.policies = [policies.get(name) for name in self.names]
        missing = [self.names[i] for i in self.active if self.policies[i] is None]
        if missing:
            raise ValueError(f"no policy for the present layers {missing}")
        self.decided: list[str] = []  # the layers that decided at the latest step
        self.contributions: dict[str, np.ndarray] = {}  # each reached layer's part of the latest action
        self.reset()

    def reset(self) -> None:
        """Start an episode: step 0, nothing held and nothing in flight."""
        self.t = 0
        self.held = [np.zeros_like(low) for low in self.out_low]
        self.inflight = [np.zeros((layer["delay"], len(low)), np.float32)
                         for layer, low in zip(self.layers, self.out_low, strict=True)]
        self.resume_at = [0] * len(self.layers)

    def step(self, obs: np.ndarray) -> np.ndarray:
        """The action to execute at this base step, given the environment's observation."""
        obs = np.asarray(obs, np.float32).ravel()
        self.decided = []
        i = self._next_due(0)
        while i is not None:
            self._hold(i, self.policies[i](self._observation(i, obs)))  # type: ignore[misc]
            self.decided.append(self.names[i])
            i = self._next_due(i + 1)
        action, contributions = self._walk(self.held)
        self.contributions = {self.names[i]: c for i, c in contributions.items()}
        self.t += 1
        return action

    def _next_due(self, start: int) -> int | None:
        for position, i in enumerate(self.active):
            if i >= start and self.t % self.layers[i]["period"] == 0 and self.t >= self.resume_at[i]:
                return i
            if self._route(position, i, self.held[i]) == COMMIT:
                return None
        return None

    def _hold(self, i: int, output: np.ndarray) -> None:
        layer = self.layers[i]
        output = np.minimum(np.maximum(np.asarray(output, np.float32).ravel(), self.out_low[i]), self.out_high[i])
        repeats = int(np.clip(np.rint(output[-1]), 1, layer["max_repeat"])) if layer["max_repeat"] > 1 else 1
        self.resume_at[i] = self.t + repeats * layer["period"]
        queue = self.inflight[i]
        if len(queue):
            output, queue[:-1], queue[-1] = queue[0].copy(), queue[1:].copy(), output
        self.held[i] = output

    def _observation(self, i: int, obs: np.ndarray) -> np.ndarray:
        layer = self.layers[i]
        lands = self._upcoming(i) + layer["delay"] * layer["period"]
        parts = [obs, *(self._in_effect(j, lands)[: self.action_dim] for j in layer["sees"])]
        for k in range(layer["delay"]):  # its own outputs in flight, as they will be executed
            entry = self.inflight[i][k]
            at = self._upcoming(i) + k * layer["period"]
            outputs = [entry if j == i else self._in_effect(j, at) for j in range(len(self.layers))]
            executed = self._walk(outputs)[1].get(i, np.zeros(self.action_dim, np.float32))
            parts += [executed, entry[self.action_dim:]]
        return np.concatenate(parts)

    def _upcoming(self, j: int) -> int:
        period = self.layers[j]["period"]
        return max(-(-self.t // period) * period, self.resume_at[j])

    def _in_effect(self, j: int, step: int) -> np.ndarray:
        queue, upcoming = self.inflight[j], self._upcoming(j)
        if step < upcoming or not len(queue):
            return self.held[j]
        return queue[min((step - upcoming) // self.layers[j]["period"], len(queue) - 1)]

    def _route(self, position: int, i: int, output: np.ndarray) -> str:
        layer = self.layers[i]
        if position == len(self.active) - 1 or layer["combiner"] != "gate":
            return ADD
        return COMMIT if output[self.action_dim + layer["gate_dims"] - 1] > 0 else DEFER

    def _admit(self, i: int, above: np.ndarray, contribution: np.ndarray) -> np.ndarray:
        """The part of a lower layer's contribution that layer i's combiner lets through."""
        threshold = self.thresholds[i]
        if self.layers[i]["combiner"] != "residual-clip" or threshold is None:
            return contribution
        effect = np.abs(self._clip(above + contribution) - self._clip(above))
        small = effect < threshold
        if self.layers[i]["per_dimension"]:
            return np.where(small, 0.0, contribution).astype(contribution.dtype)
        return np.zeros_like(contribution) if small.all() else contribution

    def _walk(self, outputs: Sequence[np.ndarray]) -> tuple[np.ndarray, dict[int, np.ndarray]]:
        total = np.zeros(self.action_dim, np.float32)
        contributions: dict[int, np.ndarray] = {}
        above: int | None = None
        for position, i in enumerate(self.active):
            own = outputs[i][: self.action_dim]
            if above is not None:
                own = self._admit(above, total, own)
            route = self._route(position, i, outputs[i])
            contributions[i] = np.zeros_like(own) if route == DEFER else own
            total = total + contributions[i]
            if route == COMMIT:
                break
            above = i
        return self._clip(total), contributions

    def _clip(self, action: np.ndarray) -> np.ndarray:
        """`action` within the action bounds (np.clip's result, at a third of its call overhead)."""
        return np.minimum(np.maximum(action, self.low), self.high)


def _torchscript_policy(path: Path) -> Policy:
    import warnings

    import torch

    with warnings.catch_warnings():  # TorchScript is deprecated upstream; it still loads with torch alone
        warnings.simplefilter("ignore", DeprecationWarning)
        module = torch.jit.load(str(path))

    def act(obs: np.ndarray) -> np.ndarray:
        with torch.inference_mode():
            return module(torch.from_numpy(obs)).numpy()

    return act


def _onnx_policy(path: Path) -> Policy:
    import onnxruntime

    options = onnxruntime.SessionOptions()
    options.intra_op_num_threads = options.inter_op_num_threads = 1  # one observation: threads only cost
    session = onnxruntime.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
    name = session.get_inputs()[0].name
    return lambda obs: session.run(None, {name: obs})[0]


BACKENDS: dict[str, tuple[str, Callable[[Path], Policy]]] = {
    "torchscript": (".pt", _torchscript_policy), "onnx": (".onnx", _onnx_policy),
}


def load_stack(directory: str | Path, backend: str | None = None) -> ExportedStack:
    """The exported stack in `directory`; `backend` is `torchscript` or `onnx` (default: the one the
    directory holds)."""
    directory = Path(directory)
    spec = json.loads((directory / "stack.json").read_text())
    backend = backend or spec["backend"]
    if backend not in BACKENDS:
        raise ValueError(f"unknown backend {backend!r}; known: {', '.join(BACKENDS)}")
    suffix, load = BACKENDS[backend]
    policies = {name: load(directory / f"{name}{suffix}") for name in spec["active"]}
    return ExportedStack(spec, policies)
