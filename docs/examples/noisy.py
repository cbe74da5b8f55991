"""An environment family plugin: any other id with Gaussian noise on its observations, named
`noisy:<id>`, e.g. `noisy:Pendulum-v1` or `noisy:dmc:cartpole-swingup`."""

import gymnasium as gym
import numpy as np

from layered.envs import FAMILIES, EnvFamily, env_info, make_env


class ObservationNoise(gym.ObservationWrapper):
    """Adds N(0, std^2) to every observation, drawn from the env's own seeded generator."""

    def __init__(self, env, std):
        super().__init__(env)
        self.std = std

    def observation(self, observation):
        noise = self.np_random.normal(0.0, self.std, size=np.shape(observation))
        return (observation + noise).astype(self.observation_space.dtype)


@FAMILIES.register("noisy")
class NoisyFamily(EnvFamily):
    """The environment `name` of any family, observed with noise of std 0.05."""

    example = "noisy:Pendulum-v1"

    def make(self, name, render_mode=None):
        return ObservationNoise(make_env(name, render_mode=render_mode), std=0.05)

    def info(self, name):
        return env_info(name)
