"""`layered export`: a trained stack as files that run without the training code.

The directory holds one policy per present layer (TorchScript `.pt` or ONNX `.onnx`), `stack.json`
(the rules of the evaluation stack as `Rules.to_json` writes them: periods, delays, what each layer
sees, combiners with their evaluation thresholds, output bounds), the package `layered_runtime/`
(the runtime with copies of the library's own rules and combiners) and, under `plugins/`, the
source of each plugin combiner the stack merges through.
"""

from __future__ import annotations

import contextlib
import io
import json
import logging
import math
import inspect
import shutil
import warnings
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch

from layered import combiners, outputs, registry, rules, runtime
from layered.agents import make_aec_env
from layered.errors import BadInput
from layered.learners import Learner
from layered.schema import Recipe
from layered.stack import Stack

FORMATS = {"torchscript": ".pt", "onnx": ".onnx"}
RUNTIME_PACKAGE = "layered_runtime"
# The modules the runtime is made of, as they are named in the exported package; they import each
# other relatively and nothing else of the library.
RUNTIME_MODULES = {"__init__.py": runtime, "rules.py": rules, "combiners.py": combiners, "outputs.py": outputs,
                   "registry.py": registry}


class ExportError(BadInput, ValueError):
    """A stack that cannot be exported (a learner without an exportable policy, an unknown format)."""


def plugin_sources(stack: Stack) -> list[Path]:
    """The files of the plugin combiners the stack merges through: those defined outside the library."""
    library = Path(combiners.__file__).parent
    files = {Path(inspect.getfile(type(layer.rules.combiner))).resolve()
             for layer in stack.layers if layer.rules.combiner is not None}
    return sorted(f for f in files if f.parent != library)


def stack_spec(recipe: Recipe, stack: Stack, backend: str, plugins: list[str], env_observation_dims: int
               ) -> dict[str, Any]:
    """What the runtime needs of an evaluation stack, as plain JSON values."""
    return {"backend": backend, "env": recipe.env.id, "rules": stack.rules.to_json(), "plugins": plugins,
            "env_observation_dims": env_observation_dims,
            "observation_dims": {layer.name: int(space.shape[0])
                                 for layer, space in zip(stack.layers, stack.observation_spaces, strict=True)}}


def _policy(learner: Learner, name: str) -> torch.nn.Module:
    try:
        return learner.policy()
    except NotImplementedError as e:
        raise ExportError(f"layer {name!r}: {e}") from None


def _write_policy(module: torch.nn.Module, obs_dim: int, path: Path) -> None:
    module.eval()  # (a policy acts as in evaluation, and the exporters warn of one left in training mode)
    example = torch.zeros(obs_dim)
    if path.suffix == ".pt":
        with warnings.catch_warnings():  # TorchScript is deprecated upstream, yet it is what loads with torch alone
            warnings.simplefilter("ignore", DeprecationWarning)
            torch.jit.save(torch.jit.trace(module, (example,)), str(path))
        return
    onnx_log = logging.getLogger("torch.onnx")
    level = onnx_log.level
    onnx_log.setLevel(logging.ERROR)  # it warns that torchvision's operators are not installed: none is used
    # it narrates its passes, and warns of deprecations inside torch that only torch can act on
    with contextlib.redirect_stdout(io.StringIO()), warnings.catch_warnings():
        warnings.simplefilter("ignore", FutureWarning)
        warnings.simplefilter("ignore", DeprecationWarning)
        try:
            torch.onnx.export(module, (example,), str(path), input_names=["obs"], output_names=["output"],
                              dynamo=True, external_data=False, verbose=False)
        finally:
            onnx_log.setLevel(level)


def export_stack(recipe: Recipe, learners: Mapping[str, Learner], active: list[str], out: Path, backend: str,
                 threshold: float | None = None) -> Path:
    """Write the evaluation stack of `recipe` with the `active` layers and these learners' policies to `out`."""
    if backend not in FORMATS:
        raise ExportError(f"unknown format {backend!r}; known: {', '.join(FORMATS)}")
    env = make_aec_env(recipe, active=active, evaluation=True, threshold=threshold)
    env.close()
    sources = plugin_sources(env.stack)
    spec = stack_spec(recipe, env.stack, backend, [f"plugins/{source.name}" for source in sources],
                      math.prod(env.base.observation_space.shape or (0,)))
    modules = {name: _policy(learners[name], name) for name in active}
    out.mkdir(parents=True, exist_ok=True)
    for name, module in modules.items():
        _write_policy(module, spec["observation_dims"][name], out / f"{name}{FORMATS[backend]}")
    (out / RUNTIME_PACKAGE).mkdir(exist_ok=True)
    for file, source in RUNTIME_MODULES.items():
        shutil.copyfile(inspect.getfile(source), out / RUNTIME_PACKAGE / file)
    for plugin in sources:
        (out / "plugins").mkdir(exist_ok=True)
        shutil.copyfile(plugin, out / "plugins" / plugin.name)
    (out / "stack.json").write_text(json.dumps(spec, indent=2) + "\n")
    return out
