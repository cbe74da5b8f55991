"""Name-to-class registries: the extension points for combiners, learners, orders and env families.

An entry is checked when it is registered, so that a plugin that cannot work is refused when it is imported, in
one line, rather than failing with a traceback once a run has begun: its name, and, for a registry of classes, that
it subclasses the registry's base, defines every abstract method and every class attribute the base declares, and
that its methods take what the library passes to the base's; for a registry of functions, that it takes the
library's arguments.

Pure Python, no dependencies: the exported runtime carries a copy of this file (for combiners).
"""

from __future__ import annotations

import inspect
import re
from collections.abc import Callable, Iterator
from typing import Any, Generic, TypeVar

T = TypeVar("T")
NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]*")
"""A registered name: what recipes write as `kind`, and an env family's `family:` prefix."""
CLASS_VARIABLE = re.compile(r"(typing\.)?ClassVar\b")


class Registry(Generic[T]):
    """A dict from name to entry, filled by a decorator, with errors that list the known names. Entries are classes
    deriving from `base`, or where `arguments` is given functions called with that many positional arguments."""

    def __init__(self, kind: str, base: type | None = None, arguments: int | None = None) -> None:
        self.kind = kind
        self.base = base
        self.arguments = arguments
        self._entries: dict[str, T] = {}

    def register(self, name: str) -> Callable[[T], T]:
        """Decorator that registers its target under `name`; a name can be taken only once, and an entry that does
        not fit (`unfit`) is refused: a ValueError or TypeError that says why."""

        def add(entry: T) -> T:
            if not isinstance(name, str) or not NAME.fullmatch(name):
                raise ValueError(f"{self.kind} name {name!r}: a name is letters, digits, '_', '.' and '-', "
                                 "beginning with a letter or digit")
            if name in self._entries:
                raise ValueError(f"{self.kind} {name!r} is already registered")
            if (why := self.unfit(entry)) is not None:
                raise TypeError(f"{self.kind} {name!r}: {why}")
            self._entries[name] = entry
            return entry

        return add

    def unfit(self, entry: Any) -> str | None:
        """Why `entry` cannot be one of this registry's entries, or None."""
        if self.base is not None:
            return _unfit_class(entry, self.base)
        if self.arguments is not None:
            if not callable(entry):
                return f"{entry!r} is not callable"
            if not _takes(entry, self.arguments):
                return f"it takes {_signature(entry)}, but is called with {self.arguments} positional arguments"
        return None

    def get(self, name: str) -> T:
        """The entry called `name`, or a KeyError naming the known entries (`unknown`)."""
        if name not in self._entries:
            raise KeyError(self.unknown(name))
        return self._entries[name]

    def unknown(self, name: str) -> str:
        """What to say of a name nothing is registered under: the known ones, and where one of the user's own comes
        from."""
        return (f"unknown {self.kind} {name!r}; known: {', '.join(sorted(self._entries))} (one of your own: load its "
                "plugin with --plugin)")

    def name_of(self, entry: T) -> str:
        """The name `entry` is registered under, or a KeyError."""
        for name, registered in self._entries.items():
            if registered is entry:
                return name
        raise KeyError(f"{entry!r} is not a registered {self.kind}")

    def names(self) -> list[str]:
        """Registered names, sorted."""
        return sorted(self._entries)

    def __contains__(self, name: object) -> bool:
        return name in self._entries

    def __iter__(self) -> Iterator[str]:
        return iter(self.names())


def _unfit_class(entry: Any, base: type) -> str | None:
    """Why the class `entry` cannot stand where the library uses a `base`, or None."""
    if not (isinstance(entry, type) and issubclass(entry, base)):
        return f"{entry!r} is not a subclass of {base.__name__}"
    if inspect.isabstract(entry):
        undefined = ", ".join(sorted(getattr(entry, "__abstractmethods__", ())))
        return f"it does not define {undefined}, which every {base.__name__} must"
    declared = [name for klass in base.__mro__ for name, annotation in vars(klass).get("__annotations__", {}).items()
                if CLASS_VARIABLE.match(str(annotation)) and not hasattr(base, name)]
    if unset := [name for name in declared if not hasattr(entry, name)]:
        return f"it does not set {', '.join(unset)}, which every {base.__name__} declares"
    for klass in base.__mro__[:-1]:  # (object's own methods aside)
        for name, theirs in vars(klass).items():
            if name.startswith("_") and name != "__init__":
                continue
            ours = inspect.getattr_static(entry, name)
            mine, given = _function(ours), _function(theirs)
            if ours is theirs or mine is None or given is None:
                continue
            positional, keywords = _parameters(given)
            if not _takes(mine, positional, keywords):
                return (f"its {name}{_signature(mine)} does not take what the library passes to every "
                        f"{base.__name__}'s {name}{_signature(given)}")
    return None


def _function(member: Any) -> Callable[..., Any] | None:
    """The plain function behind a method, class method or static method; None for anything else."""
    if isinstance(member, (classmethod, staticmethod)):
        member = member.__func__
    return member if inspect.isfunction(member) else None


def _parameters(function: Callable[..., Any]) -> tuple[int, list[str]]:
    """How many positional parameters `function` has (its first, self or cls, included) and its keyword-only ones."""
    parameters = inspect.signature(function).parameters.values()
    positional = sum(p.kind in (p.POSITIONAL_ONLY, p.POSITIONAL_OR_KEYWORD) for p in parameters)
    return positional, [p.name for p in parameters if p.kind == p.KEYWORD_ONLY]


def _takes(function: Callable[..., Any], positional: int, keywords: list[str] | tuple[()] = ()) -> bool:
    """Whether `function` can be called with `positional` positional arguments and the `keywords`."""
    try:
        inspect.signature(function).bind(*range(positional), **dict.fromkeys(keywords))
    except TypeError:
        return False
    except ValueError:  # no signature to read (a builtin): nothing to check
        pass
    return True


def _signature(function: Callable[..., Any]) -> str:
    try:
        return str(inspect.signature(function))
    except ValueError:
        return "(...)"
