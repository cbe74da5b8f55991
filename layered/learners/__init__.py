"""Learners, registered by name; importing this package registers the built-in ones."""

from layered.learners import gate_td3 as _gate_td3  # noqa: F401  (registers "td3-gate")
from layered.learners import td3_captured as _td3  # noqa: F401  (registers "td3")
from layered.learners import temporl as _temporl  # noqa: F401  (registers "temporl")
from layered.learners.base import LEARNERS, Flag, Learner, LearnerConfig, Losses, Whole

__all__ = ["LEARNERS", "Flag", "Learner", "LearnerConfig", "Losses", "Whole"]
