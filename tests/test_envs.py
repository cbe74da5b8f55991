"""The pinned versions work together: every environment family imports and steps on one mujoco."""

import os

import gymnasium as gym
import numpy as np
import pytest

import layered.envs as envs


def test_gymnasium_classic_and_mujoco_through_the_registry():
    for env_id in ("Pendulum-v1", "gym:InvertedPendulum-v5"):
        env = envs.make_env(env_id)
        env.reset(seed=0)
        for _ in range(5):
            env.step(env.action_space.sample())
        env.close()


def test_unknown_environments_are_clear_errors():
    with pytest.raises(KeyError, match="did you mean"):
        envs.env_info("Pendulm-v1")
    with pytest.raises(KeyError, match="unknown environment family 'atari'"):
        envs.env_info("atari:Pong")
    with pytest.raises(KeyError, match="Discrete action space"):
        envs.make_env("CartPole-v1")


def test_dm_control_suite_steps():
    from dm_control import suite

    env = suite.load("cartpole", "swingup", task_kwargs={"random": 0})
    spec = env.action_spec()
    ts = env.reset()
    for _ in range(5):
        ts = env.step(np.zeros(spec.shape))
    assert ts.observation


def test_gymnasium_robotics_maze_steps():
    import gymnasium_robotics

    gym.register_envs(gymnasium_robotics)
    env = gym.make("PointMaze_UMaze-v3")
    obs, _ = env.reset(seed=0)
    assert set(obs) == {"observation", "achieved_goal", "desired_goal"}
    env.step(env.action_space.sample())
    env.close()


def test_headless_rendering():
    assert os.environ.get("MUJOCO_GL") in ("egl", "osmesa")
    env = gym.make("InvertedPendulum-v5", render_mode="rgb_array", width=64, height=48)
    env.reset(seed=0)
    frame = env.render()
    env.close()
    assert frame.shape == (48, 64, 3) and frame.any()
