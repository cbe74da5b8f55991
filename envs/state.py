"""An environment's exact state as plain data, so that a checkpoint taken mid-episode continues it bit for bit.

The state is read from the env's instance attributes, down its wrappers and every object they hold:
plain values (None, bool, int, float, str) stay as they are; numpy arrays are copied, numpy scalars become
tagged 0-d arrays; lists, tuples and dicts of these keep their shape; random
generators save their bit generator's state. Other stateful types (MuJoCo's model and data, dm_control's
physics) go through a `Capture`; spaces, specs, renderers and functions are the env's interface, not its
state, and are left out (`StateRules.static`). Anything else stops the snapshot with a `StateError`
naming where it was found.

A snapshot holds only dicts, lists, tuples, str, int, float, bool, None and numpy arrays of the dtypes a tensor
holds: a group's checkpoint stores the arrays as tensors, which `torch.load(..., weights_only=True)` reads back
(`layered.group_state`), while the environments' worker processes, which take the snapshots, never import torch.
Restoring sets the same attributes on an env made the same way (its objects are restored in place, so what they
share stays shared) and deletes the attributes that the snapshotted env did not have yet.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass
from types import BuiltinFunctionType, FunctionType, MethodType
from typing import Any

import numpy as np
from gymnasium.envs.registration import EnvSpec
from gymnasium.spaces import Space

Reference = Callable[[], Any]
"""The same attribute in a freshly made env of the same id, made on first use: what a `Capture` may save
only the changes from."""

PLAIN = (type(None), bool, int, float, str)
CONTAINERS = (list, tuple, dict)
TENSOR_DTYPES = frozenset(np.dtype(name) for name in (
    "bool", "uint8", "uint16", "uint32", "uint64", "int8", "int16", "int32", "int64", "float16", "float32", "float64",
    "complex64", "complex128"))
"""The array dtypes a snapshot may hold: those `torch.from_numpy` takes (in this machine's byte order)."""


class StateError(ValueError):
    """A part of an env's state that cannot be captured, or a snapshot that does not fit the env."""


@dataclass(frozen=True)
class Capture:
    """How the state of one kind of object that is not plain data is saved and put back."""

    kind: str
    types: tuple[type, ...]
    save: Callable[[Any, Reference], Any]
    """(the value, its reference) -> its state as plain data."""
    load: Callable[[Any, Any, Reference], Any]
    """(the restored env's current value, the saved state, the reference) -> the value to set."""


@dataclass(frozen=True)
class StateRules:
    """Which types a snapshot captures beyond plain data, and which it leaves out as holding no state."""

    captures: tuple[Capture, ...]
    static: tuple[type, ...]

    def __add__(self, other: StateRules) -> StateRules:
        """The rules of both."""
        return StateRules(self.captures + other.captures, self.static + other.static)


def encode_data(value: Any, where: str) -> Any:
    """`value` (plain values, numpy arrays and scalars, and lists, tuples and dicts of them) as plain data."""
    if type(value) in PLAIN:
        return value
    if isinstance(value, np.ndarray):
        return _array(value, where)
    if isinstance(value, np.generic):
        return {"kind": "scalar", "value": _array(np.asarray(value), where)}
    if type(value) is list:
        return [encode_data(item, f"{where}[{i}]") for i, item in enumerate(value)]
    if type(value) is tuple:
        return tuple(encode_data(item, f"{where}[{i}]") for i, item in enumerate(value))
    if type(value) is dict:
        return {"kind": "dict", "items": [(encode_data(k, where), encode_data(v, f"{where}[{k!r}]"))
                                          for k, v in value.items()]}
    raise StateError(f"{where} holds a {type(value).__name__}, whose state has no known capture")


def decode_data(state: Any) -> Any:
    """The value `encode_data` made `state` from, sharing no memory with `state`."""
    if isinstance(state, np.ndarray):
        return state.copy()
    if isinstance(state, list):
        return [decode_data(item) for item in state]
    if isinstance(state, tuple):
        return tuple(decode_data(item) for item in state)
    if isinstance(state, dict) and state["kind"] == "scalar":
        return state["value"][()]
    if isinstance(state, dict):
        return {decode_data(k): decode_data(v) for k, v in state["items"]}
    return state


def _array(array: np.ndarray, where: str) -> np.ndarray:
    """A copy of `array`, which must be of a dtype that a tensor can hold."""
    if array.dtype not in TENSOR_DTYPES:
        raise StateError(f"{where} is an array of {array.dtype}, which a tensor cannot hold")
    return array.copy()


def _is_data(value: Any) -> bool:
    """Whether `value` is one that `encode_data` takes (it checks what its containers hold)."""
    return type(value) in PLAIN or type(value) in CONTAINERS or isinstance(value, np.ndarray | np.generic)


def _has_attributes(value: Any) -> bool:
    """Whether `value` is an instance whose state lives in its attributes (a class's or a slotted object's does not)."""
    return isinstance(getattr(value, "__dict__", None), dict)


def _class_name(value: Any) -> str:
    """The module and name of the class of `value`, which a restored object must share."""
    return f"{type(value).__module__}.{type(value).__qualname__}"


def _save_generator(generator: np.random.Generator, _: Reference) -> Any:
    """A numpy Generator's bit generator state (which names the bit generator's class)."""
    return encode_data(generator.bit_generator.state, "a Generator")


def _load_generator(_: Any, state: Any, __: Reference) -> np.random.Generator:
    """A new Generator in the saved state."""
    decoded = decode_data(state)
    bit_generator = getattr(np.random, decoded["bit_generator"])
    if not (isinstance(bit_generator, type) and issubclass(bit_generator, np.random.BitGenerator)):
        raise StateError(f"{decoded['bit_generator']!r} is not a numpy bit generator")
    generator = np.random.Generator(bit_generator())
    generator.bit_generator.state = decoded
    return generator


def _save_random_state(random: np.random.RandomState, _: Reference) -> Any:
    """A legacy RandomState's state (dm_control's tasks draw from one)."""
    return encode_data(random.get_state(legacy=False), "a RandomState")


def _load_random_state(_: Any, state: Any, __: Reference) -> np.random.RandomState:
    """A new RandomState in the saved state."""
    random = np.random.RandomState()
    random.set_state(decode_data(state))
    return random


GENERATORS = StateRules(
    captures=(Capture("generator", (np.random.Generator,), _save_generator, _load_generator),
              Capture("random_state", (np.random.RandomState,), _save_random_state, _load_random_state)),
    static=(),
)

INTERFACE = StateRules(captures=(), static=(Space, EnvSpec, FunctionType, MethodType, BuiltinFunctionType))
"""An env's spaces, its spec and the functions it holds (e.g. an observation wrapper's): no state of the episode."""


class StateWalk:
    """Saves or restores one env's state under `rules`; `fresh` makes (once) an env of the same id for references."""

    def __init__(self, rules: StateRules, fresh: Callable[[], Any]) -> None:
        self.rules, self.fresh = rules, fresh
        self.captures = {capture.kind: capture for capture in rules.captures}

    def save(self, env: Any) -> dict[str, Any]:
        """The state of `env` and everything it holds, as plain data."""
        return self._save_object(env, ())

    def restore(self, env: Any, state: dict[str, Any]) -> None:
        """Put `env`, made the same way as the snapshotted env, into `state`."""
        self._restore_object(env, state, ())

    def _reference(self, path: tuple[str, ...]) -> Reference:
        """The attribute at `path` in the fresh env, looked up (and the env made) only when asked for."""
        return lambda: functools.reduce(getattr, path, self.fresh())

    def _stateful(self, obj: Any) -> dict[str, Any]:
        """The attributes of `obj` that can hold state."""
        return {name: value for name, value in vars(obj).items() if not isinstance(value, self.rules.static)}

    def _save_object(self, obj: Any, path: tuple[str, ...]) -> dict[str, Any]:
        """An object's class and the state of its attributes."""
        attributes = {name: self._save_value(value, (*path, name)) for name, value in self._stateful(obj).items()}
        return {"kind": "object", "class": _class_name(obj), "attributes": attributes}

    def _save_value(self, value: Any, path: tuple[str, ...]) -> Any:
        """The state of one attribute's value."""
        for capture in self.rules.captures:
            if isinstance(value, capture.types):
                return {"kind": capture.kind, "state": capture.save(value, self._reference(path))}
        if _is_data(value):
            return encode_data(value, _where(path))
        if _has_attributes(value):
            return self._save_object(value, path)
        raise StateError(f"{_where(path)} holds a {type(value).__name__}, whose state has no known capture")

    def _restore_object(self, obj: Any, state: dict[str, Any], path: tuple[str, ...]) -> None:
        """Set the saved attributes of `obj` and delete those it gained since."""
        if state["class"] != _class_name(obj):
            raise StateError(f"{_where(path)} was a {state['class']}, not a {_class_name(obj)}")
        saved = state["attributes"]
        for name in self._stateful(obj).keys() - saved.keys():
            delattr(obj, name)
        for name, value in saved.items():
            setattr(obj, name, self._restore_value(getattr(obj, name, None), value, (*path, name)))

    def _restore_value(self, current: Any, state: Any, path: tuple[str, ...]) -> Any:
        """The value an attribute gets back; objects are restored in place."""
        kind = state.get("kind") if isinstance(state, dict) else None
        if kind == "object":
            if not _has_attributes(current):
                raise StateError(f"{_where(path)} holds no object to restore a {state['class']} into")
            self._restore_object(current, state, path)
            return current
        if kind in self.captures:
            return self.captures[kind].load(current, state["state"], self._reference(path))
        return decode_data(state)


def _where(path: tuple[str, ...]) -> str:
    """An attribute path as the error messages write it."""
    return f"its attribute {'.'.join(path)}" if path else "the env"
