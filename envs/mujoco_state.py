"""MuJoCo's part of an environment's state: the simulation's data and the model arrays a task changed.

`mj_getState` with `mjSTATE_INTEGRATION` holds everything `mj_step` reads from the data (time, positions,
velocities, actuator activations and history, controls, applied forces, mocap poses, the constraint
solver's warm start, plugin and user data). Restoring it is followed by `mj_forward`, which changes none of
it: dm_control steps from the kinematics its last step left (`mj_step2` first), so they must be current.
A step leaves some arrays as no forward pass from its state computes them (Gymnasium's envs step with
`mj_step`, whose body positions are those before its last substep, and Ant reads them before it steps): a
snapshot saves those arrays too. Arrays whose shape the pass changes (the contacts and constraint rows of the
last substep, which no step reads) keep the pass's values.

Some tasks also change the model per episode (a reacher's target, a maze's goal marker, a finger's damping):
a snapshot holds the model arrays that differ from those of a freshly made env, and restoring resets every
other array to the fresh one's.
"""

from __future__ import annotations

import copy
import functools
from typing import Any

import mujoco
import numpy as np
from gymnasium.envs.mujoco.mujoco_rendering import MujocoRenderer

from layered.envs.state import Capture, Reference, StateError, StateRules

INTEGRATION = mujoco.mjtState.mjSTATE_INTEGRATION


def data_state(data: mujoco.MjData) -> dict[str, Any]:
    """The integration state of `data`, and the arrays that a forward pass from that state computes otherwise."""
    integration = np.empty(mujoco.mj_stateSize(data.model, INTEGRATION))
    mujoco.mj_getState(data.model, data, integration, INTEGRATION)
    recomputed = copy.copy(data)
    mujoco.mj_forward(data.model, recomputed)
    return {"integration": integration,
            "left_by_step": {name: getattr(data, name).copy()
                             for name in _data_arrays() if _differs(data, recomputed, name)}}


def restore_data(data: mujoco.MjData, state: dict[str, Any]) -> None:
    """Put `data` into a saved state: the integration state, a forward pass from it, then the arrays the step had
    left otherwise; its model must be restored already."""
    mujoco.mj_setState(data.model, data, state["integration"], INTEGRATION)
    mujoco.mj_forward(data.model, data)
    for name, value in state["left_by_step"].items():
        getattr(data, name)[...] = value


@functools.cache
def _data_arrays() -> tuple[str, ...]:
    """The names of MjData's array fields (read from the data of an empty model)."""
    empty = mujoco.MjData(mujoco.MjModel.from_xml_string("<mujoco/>"))
    return tuple(name for name in dir(empty) if isinstance(getattr(empty, name), np.ndarray))


@functools.cache
def _model_arrays() -> tuple[str, ...]:
    """The names of MjModel's array fields (read from an empty model: the bindings do not list them)."""
    empty = mujoco.MjModel.from_xml_string("<mujoco/>")
    return tuple(name for name in dir(empty) if isinstance(getattr(empty, name), np.ndarray))


def _differs(mine: Any, other: Any, name: str) -> bool:
    """Whether the array field `name` of two models (or two data) has the same shape but not the same bits."""
    array, other_array = getattr(mine, name), getattr(other, name)
    return array.shape == other_array.shape and array.tobytes() != other_array.tobytes()


def model_changes(model: mujoco.MjModel, reference: mujoco.MjModel) -> dict[str, Any]:
    """The array fields of `model` that differ from `reference`'s (a freshly made env's model), and the model's
    signature (of its structure), which the restored model must share."""
    return {"signature": model.signature,
            "arrays": {name: getattr(model, name).copy()
                       for name in _model_arrays() if _differs(model, reference, name)}}


def restore_model(model: mujoco.MjModel, reference: mujoco.MjModel, changes: dict[str, Any]) -> None:
    """Make `model` equal to `reference` with `changes` applied."""
    if changes["signature"] != model.signature:
        raise StateError("its MuJoCo model is not the one snapshotted")
    arrays = changes["arrays"]
    for name in _model_arrays():
        if name in arrays:
            getattr(model, name)[...] = arrays[name]
        elif _differs(model, reference, name):
            getattr(model, name)[...] = getattr(reference, name)


def _save_model(model: mujoco.MjModel, reference: Reference) -> dict[str, Any]:
    """A model's changes from the same model in a fresh env."""
    return model_changes(model, reference())


def _load_model(model: mujoco.MjModel, changes: dict[str, Any], reference: Reference) -> mujoco.MjModel:
    """The model, its saved changes restored in place (the env's data and renderer refer to it)."""
    restore_model(model, reference(), changes)
    return model


def _save_data(data: mujoco.MjData, _: Reference) -> dict[str, Any]:
    """The state of a simulation's data, which needs no reference."""
    return data_state(data)


def _load_data(data: mujoco.MjData, state: dict[str, Any], _: Reference) -> mujoco.MjData:
    """The data, its saved state restored in place."""
    restore_data(data, state)
    return data


def save_physics(physics: Any, reference: Reference) -> dict[str, Any]:
    """The state of a dm_control physics, which holds its MuJoCo model and data as `.model.ptr` and `.data.ptr`."""
    return {"model": model_changes(physics.model.ptr, reference().model.ptr), "data": data_state(physics.data.ptr)}


def load_physics(physics: Any, state: dict[str, Any], reference: Reference) -> Any:
    """The dm_control physics put back into a saved state."""
    restore_model(physics.model.ptr, reference().model.ptr, state["model"])
    restore_data(physics.data.ptr, state["data"])
    return physics


MUJOCO = StateRules(
    captures=(Capture("mujoco_model", (mujoco.MjModel,), _save_model, _load_model),
              Capture("mujoco_data", (mujoco.MjData,), _save_data, _load_data)),
    static=(MujocoRenderer,),  # Gymnasium's renderer: views of the model and data, no state of its own
)
"""MuJoCo models (their changes) and data (their integration state)."""

