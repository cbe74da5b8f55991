"""The errors a `layered` command answers with an exit status and a line of text instead of a traceback.

A light module of its own, so that the command can tell them apart without importing what raises them."""

from __future__ import annotations


class BadInput(Exception):
    """An input a command cannot use: a recipe, a run directory, a checkpoint, a plugin, a stack to export,
    a rendering this machine cannot do. The command prints each line of the message as one line and exits
    with 2."""


class Diverged(RuntimeError):
    """A non-finite loss, action or observation; the run's last checkpoint is left as it was. `layer`
    names the layer that met it (None: the environment's observation). The command exits with 1."""

    def __init__(self, message: str, layer: str | None = None) -> None:
        super().__init__(message)
        self.layer = layer
