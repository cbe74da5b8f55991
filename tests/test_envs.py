"""Environment families: one id scheme, the pinned versions stepping on one mujoco, the adapters' contracts."""

import os

import numpy as np
import pytest
from conftest import stack_recipe
from gymnasium.utils.env_checker import check_env
from pettingzoo.test import api_test

import layered.envs as envs
from layered import make_aec_env

ONE_PER_FAMILY = list(dict.fromkeys([
    "Pendulum-v1", "gym:InvertedPendulum-v5", "dmc:cartpole-swingup", "robotics:PointMaze_UMaze-v3",
    "robotics:AntMaze_UMaze-v5", "robotics:FetchReach-v4",
    *(envs.FAMILIES.get(family).example for family in envs.FAMILIES.names()),  # (every registered family's example)
]))


@pytest.mark.parametrize("env_id", ONE_PER_FAMILY)
def test_every_family_steps_and_passes_the_gymnasium_checker(env_id):
    env = envs.make_env(env_id)
    check_env(env, skip_render_check=True)
    obs, _ = env.reset(seed=0)
    assert obs.shape == env.observation_space.shape
    for _ in range(5):
        env.step(env.action_space.sample())
    env.close()


@pytest.mark.parametrize("env_id", ["dmc:walker-walk", "robotics:PointMaze_UMazeDense-v3"])
def test_stacks_on_other_families_pass_the_pettingzoo_checker(env_id):
    env = make_aec_env(stack_recipe([2, 1], ["gate", "residual-clip"], env=env_id), seed=0)
    api_test(env, num_cycles=100)
    env.close()


def test_dm_control_adapter_matches_the_suites_own_specs():
    from dm_control import suite

    native = suite.load("walker", "walk", task_kwargs={"random": 0})
    env = envs.make_env("dmc:walker-walk")
    size = sum(int(np.prod(s.shape)) for s in native.observation_spec().values())
    spec = native.action_spec()
    assert env.observation_space.shape == (size,)
    assert np.array_equal(env.action_space.low, spec.minimum) and np.array_equal(env.action_space.high, spec.maximum)
    assert env.unwrapped.dt == pytest.approx(native.control_timestep()) == envs.control_timestep("dmc:walker-walk")
    first, _ = env.reset(seed=0)
    again, _ = env.reset(seed=0)
    other, _ = env.reset(seed=1)
    assert np.array_equal(first, again) and not np.array_equal(first, other)


def test_dm_control_time_limit_is_truncation():
    env = envs.make_env("dmc:cartpole-balance")
    env.reset(seed=0)
    steps, terminated, truncated = 0, False, False
    while not (terminated or truncated):
        _, reward, terminated, truncated, _ = env.step(np.zeros(1, np.float32))
        assert 0.0 <= reward <= 1.0
        steps += 1
    assert (steps, terminated, truncated) == (1000, False, True)


def test_dm_control_constants_are_the_tasks_own_time_limit_and_range():
    """Every suite task runs 1000 steps paying [0, 1] a step, but the regulators', which run until they settle."""
    from dm_control import suite

    for domain, task in suite.ALL_TASKS:
        limit = suite.load(domain, task)._step_limit
        info = envs.env_info(f"dmc:{domain}-{task}")
        assert (info.episode_steps, info.return_range) == ((1000, (0.0, 1000.0)) if limit == 1000 else (None, None))
    assert envs.env_info("dmc:lqr-lqr_2_1").episode_steps is None


def test_goal_conditioned_observations_are_flattened_in_sorted_key_order():
    env = envs.make_env("robotics:PointMaze_UMaze-v3")
    flat, _ = env.reset(seed=0)
    inner = env.unwrapped
    goal = inner.goal
    assert flat.shape == (8,)  # achieved_goal (2), desired_goal (2), observation (4)
    assert np.allclose(flat[2:4], goal)


def test_unknown_environments_are_clear_errors():
    with pytest.raises(KeyError, match="did you mean Pendulum-v1"):
        envs.env_info("Pendulm-v1")
    with pytest.raises(KeyError, match="unknown environment family 'atari'"):
        envs.env_info("atari:Pong")
    assert "action space is Discrete" in envs.env_spaces("CartPole-v1").problem()
    with pytest.raises(KeyError, match="did you mean cartpole-swingup"):
        envs.env_info("dmc:cartpole-swingupp")


@pytest.mark.parametrize("env_id", ["gym:InvertedPendulum-v5", "dmc:cartpole-swingup", "robotics:PointMaze_UMaze-v3"])
def test_headless_rendering(env_id):
    if os.environ.get("MUJOCO_GL") == "disable":
        pytest.skip("no OpenGL library (EGL or OSMesa) on this machine")
    env = envs.make_env(env_id, render_mode="rgb_array")
    env.reset(seed=0)
    frame = env.render()
    env.close()
    assert frame.ndim == 3 and frame.shape[2] == 3 and frame.any()


def test_without_an_opengl_library_mujoco_steps_and_rendering_is_refused_in_one_line():
    """A machine with no display and neither EGL nor OSMesa: nothing GL is loaded to step Hopper, and
    asking it to render names what to install."""
    import subprocess
    import sys

    script = (
        "import ctypes.util, os; ctypes.util.find_library = lambda name: None; "
        "os.environ.pop('DISPLAY', None); os.environ.pop('MUJOCO_GL', None)\n"
        "from layered.envs import RenderingUnavailable, make_env\n"
        "env = make_env('Hopper-v5'); env.reset(seed=0); env.step(env.action_space.sample()); env.close()\n"
        "print(os.environ['MUJOCO_GL'])\n"
        "try:\n    make_env('dmc:cartpole-swingup', render_mode='rgb_array')\n"
        "except RenderingUnavailable as e:\n    print(e)\n"
    )
    env = {k: v for k, v in os.environ.items() if k not in ("MUJOCO_GL", "DISPLAY")}
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=env, check=True)
    backend, message = done.stdout.strip().splitlines()
    assert backend == "disable" and "apt install libegl1" in message


@pytest.mark.parametrize("env_id, parallel", [
    ("Pendulum-v1", False),  # classic control steps in Python
    ("Hopper-v5", True),  # MuJoCo's step lets go of Python's lock
    ("HalfCheetah-v5", True),
    ("dmc:cartpole-balance", False),  # not measured faster in threads (cartpole was slower)
    ("robotics:PointMaze_UMaze-v3", False),
])
def test_which_environments_step_their_rows_in_parallel_threads(env_id, parallel):
    assert envs.env_spaces(env_id).parallel is parallel
