"""A combiner plugin: residual-clip whose lower layers cannot make corrections smaller than 5%
of the action half-range (the largest action), in training as well as at evaluation."""

import numpy as np

from layered.combiners import COMBINERS, ResidualClip


@COMBINERS.register("residual-deadband")
class ResidualDeadband(ResidualClip):
    """Like residual-clip, but small corrections from the layers below never reach the actuator."""

    deadband = 0.05  # fraction of the action half-range

    def admit(self, above, contribution, low, high):
        contribution = super().admit(above, contribution, low, high)  # the evaluation threshold
        small = np.abs(contribution) < self.deadband * (high - low) / 2
        return np.where(small, 0.0, contribution).astype(contribution.dtype)
