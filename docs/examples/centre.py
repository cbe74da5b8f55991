"""A learner plugin: a layer that always acts at the centre of its action range and never
learns, a do-nothing baseline for the layers above or below it."""

from typing import Literal

import numpy as np

from layered.learners import LEARNERS, Learner, LearnerConfig


class CentreConfig(LearnerConfig):
    """No settings besides the kind."""

    kind: Literal["centre"] = "centre"


@LEARNERS.register("centre")
class Centre(Learner):
    """Acts at the centre of its action box; observing and updating do nothing."""

    Config = CentreConfig

    def act(self, obs, explore):
        return ((self.action_space.low + self.action_space.high) / 2).astype(np.float32)

    def act_macs(self):
        return 0

    def observe(self, transition):
        pass

    def update(self):
        return None

    def state_dict(self):
        return {}

    def load_state_dict(self, state):
        pass
