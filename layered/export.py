"""`layered export`: a trained stack as files that run without the training code.

The directory holds one policy per present layer (TorchScript `.pt` or ONNX `.onnx`), `stack.json`
with what the runtime needs of the stack (periods, delays, what each layer sees, combiners with
their evaluation thresholds, output bounds), and `layered_runtime.py`, the runtime itself.
Everything in `stack.json` is read off the library's own evaluation `Stack`.
"""

from __future__ import annotations

import contextlib
import io
import json
import shutil
import warnings
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch

from layered import runtime
from layered.agents import make_aec_env
from layered.learners import Learner
from layered.recipe import Recipe
from layered.stack import Stack, combiner_kind

FORMATS = {"torchscript": ".pt", "onnx": ".onnx"}
RUNTIME_FILE = "layered_runtime.py"


class ExportError(ValueError):
    """A stack that the runtime cannot run (a plugin combiner, a learner without an exportable policy)."""


def stack_spec(recipe: Recipe, stack: Stack, backend: str) -> dict[str, Any]:
    """What the runtime needs of an evaluation stack, as plain JSON values."""
    layers = []
    for i, layer in enumerate(stack.layers):
        kind = combiner_kind(recipe, i)
        if kind not in (None, "residual-clip", "gate"):
            raise ExportError(f"layer {layer.name!r} merges through the combiner {kind!r}; the exported runtime "
                              "knows the built-in combiners residual-clip and gate only")
        threshold = layer.combiner.threshold if layer.combiner is not None else None
        layers.append({
            "name": layer.name, "period": layer.period, "delay": layer.delay, "sees": list(layer.sees),
            "combiner": kind, "per_dimension": recipe.combine.per_dimension,
            "threshold": None if threshold is None else [float(x) for x in threshold],
            "gate_dims": layer.layout.gate_dims, "max_repeat": layer.layout.max_repeat,
            "observation_dim": int(stack.observation_spaces[i].shape[0]),
            "output_low": [float(x) for x in layer.action_space.low],
            "output_high": [float(x) for x in layer.action_space.high],
        })
    return {
        "format": runtime.FORMAT, "backend": backend, "env": recipe.env.id,
        "active": [stack.layers[i].name for i in stack.active], "action_dim": stack.action_dim,
        "action_low": [float(x) for x in stack.low], "action_high": [float(x) for x in stack.high],
        "layers": layers,
    }


def _policy(learner: Learner, name: str) -> torch.nn.Module:
    try:
        return learner.policy()
    except NotImplementedError as e:
        raise ExportError(f"layer {name!r}: {e}") from None


def _write_policy(module: torch.nn.Module, obs_dim: int, path: Path) -> None:
    example = torch.zeros(obs_dim)
    if path.suffix == ".pt":
        with warnings.catch_warnings():  # TorchScript is deprecated upstream, yet it is what loads with torch alone
            warnings.simplefilter("ignore", DeprecationWarning)
            torch.jit.save(torch.jit.trace(module, (example,)), str(path))
        return
    with contextlib.redirect_stdout(io.StringIO()):  # the exporter narrates its passes
        torch.onnx.export(module, (example,), str(path), input_names=["obs"], output_names=["output"],
                          dynamo=True, external_data=False, verbose=False)


def export_stack(recipe: Recipe, learners: Mapping[str, Learner], active: list[str], out: Path, backend: str,
                 threshold: float | None = None) -> Path:
    """Write the evaluation stack of `recipe` with the `active` layers and these learners' policies to `out`."""
    if backend not in FORMATS:
        raise ExportError(f"unknown format {backend!r}; known: {', '.join(FORMATS)}")
    env = make_aec_env(recipe, active=active, evaluation=True, threshold=threshold)
    env.close()
    spec = stack_spec(recipe, env.stack, backend)
    modules = {name: _policy(learners[name], name) for name in active}
    out.mkdir(parents=True, exist_ok=True)
    for layer in spec["layers"]:
        if layer["name"] in modules:
            _write_policy(modules[layer["name"]], layer["observation_dim"], out / f"{layer['name']}{FORMATS[backend]}")
    shutil.copyfile(runtime.__file__, out / RUNTIME_FILE)
    (out / "stack.json").write_text(json.dumps(spec, indent=2) + "\n")
    return out
