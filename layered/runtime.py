"""Run an exported stack without `layered`: numpy plus torch (TorchScript) or onnxruntime (ONNX).

`layered export` writes this file, as the package `layered_runtime/`, beside `stack.json` and one
policy file per layer, together with the library's own rules of a stack (`rules.py` and the
combiners it merges through, copied unchanged) and the source of any plugin combiner, so that a
robot loop needs only:

    from layered_runtime import load_stack
    stack = load_stack("exported/")     # TorchScript or ONNX, as stack.json's backend says
    stack.reset()                       # at the start of every episode
    action = stack.step(obs)            # once per base step: observation in, executed action out

It acts as `layered eval` does (no exploration), by the very rules the library trains and evaluates
with. The package imports nothing of `layered` (its imports are relative): keep it that way.
"""

from __future__ import annotations

import importlib.util
import json
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from . import combiners
from .rules import Rules

Policy = Callable[[np.ndarray], np.ndarray]


class ExportedStack:
    """A trained stack acting one base step at a time, from its `stack.json` spec and one policy per
    present layer."""

    def __init__(self, spec: dict[str, Any], policies: dict[str, Policy]) -> None:
        self.spec = spec
        self.rules = Rules.from_json(spec["rules"])
        self.names = [layer.name for layer in self.rules.layers]
        missing = [self.names[i] for i in self.rules.active if self.names[i] not in policies]
        if missing:
            raise ValueError(f"no policy for the present layers {missing}")
        self.policies = [policies.get(name) for name in self.names]
        self.decided: list[str] = []  # the layers that decided at the latest step
        self.contributions: dict[str, np.ndarray] = {}  # each reached layer's part of the latest action

    def reset(self) -> None:
        """Start an episode: step 0, nothing held and nothing in flight."""
        self.rules.reset()

    def step(self, obs: np.ndarray) -> np.ndarray:
        """The action to execute at this base step, given the environment's observation."""
        obs = np.asarray(obs, np.float32).reshape(1, -1)
        if obs.shape[1] != self.spec.get("env_observation_dims", obs.shape[1]):
            raise ValueError(f"the stack takes observations of {self.spec['env_observation_dims']} numbers (those of "
                             f"{self.spec['env']}, flattened), got {obs.shape[1]}")
        decided = self.rules.decide_all(obs, self._act)
        self.decided = [self.names[i] for i, rows in decided.items() if rows[0]]
        composition = self.rules.compose()
        self.contributions = {self.names[i]: composition.contributions[i][0].copy()  # the rules reuse their arrays
                              for i in self.rules.active if composition.reached[i][0]}
        self.rules.tick()
        return composition.action[0]

    def _act(self, i: int, seen: np.ndarray, rows: np.ndarray) -> np.ndarray:
        policy = self.policies[i]
        assert policy is not None, "only present layers decide, and each has a policy"
        return np.asarray(policy(seen[0]), np.float32).reshape(1, -1)  # one stack: one row


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


def load_plugin(path: Path) -> None:
    """Import a plugin combiner's file, as carried by the export. The file imports `layered.combiners`
    and registers itself there; while it loads, that name means this package's copy of the combiners,
    so that it registers here, whether or not the library is installed."""
    names = ("layered", "layered.combiners")
    saved = {name: sys.modules.get(name) for name in names}
    sys.modules["layered"], sys.modules["layered.combiners"] = sys.modules[__name__], combiners
    try:
        spec = importlib.util.spec_from_file_location(f"layered_runtime_plugin_{path.stem}", path)
        assert spec is not None and spec.loader is not None, f"{path} is not a Python file"
        spec.loader.exec_module(importlib.util.module_from_spec(spec))
    finally:
        for name, module in saved.items():
            if module is None:
                sys.modules.pop(name, None)
            else:
                sys.modules[name] = module


def load_stack(directory: str | Path, backend: str | None = None) -> ExportedStack:
    """The exported stack in `directory`; `backend` is `torchscript` or `onnx` (default: the one the
    directory holds)."""
    directory = Path(directory)
    spec = json.loads((directory / "stack.json").read_text())
    kinds = {layer["combiner"]["kind"] for layer in spec["rules"]["layers"] if layer["combiner"]}
    if not kinds <= set(combiners.COMBINERS):  # plugins this process has not imported yet
        for plugin in spec.get("plugins", []):
            load_plugin(directory / plugin)
    backend = backend or spec["backend"]
    policies = {name: load_policy(directory, name, backend) for name in spec["rules"]["active"]}
    return ExportedStack(spec, policies)


def load_policy(directory: str | Path, name: str, backend: str) -> Policy:
    """Layer `name`'s exported policy in `directory`, loaded with `backend` (`torchscript` or `onnx`)."""
    if backend not in BACKENDS:
        raise ValueError(f"unknown backend {backend!r}; known: {', '.join(BACKENDS)}")
    suffix, load = BACKENDS[backend]
    path = Path(directory) / f"{name}{suffix}"
    if not path.exists():
        raise FileNotFoundError(f"no {backend} policy {path}: export the run with --format {backend}")
    return load(path)
