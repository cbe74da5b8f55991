"""Learners, registered by name; importing this package registers the built-in ones."""

from layered.learners import captured as _captured  # noqa: F401  (registers "td3", "temporl" and "td3-gate")
from layered.learners.base import LEARNERS, Flag, Learner, LearnerConfig, Losses, Whole

__all__ = ["LEARNERS", "Flag", "Learner", "LearnerConfig", "Losses", "Whole"]
