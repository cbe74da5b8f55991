"""`layered eval --video`: an MP4 per episode, with the layer strip under every frame, for each
environment family."""

import os

import imageio.v2 as imageio
import numpy as np
import pytest

import layered.envs  # noqa: F401  (chooses MuJoCo's GL backend: `disable` where no GL library is installed)
from layered import load_recipe
from layered.learner_set import build_learners
from layered.orders import phases_of
from layered.video import COLOURS, write_videos

RECIPES = {  # recipe, episodes (dm_control renders in software here, 30 ms a frame over 1000 steps)
    "classic control": ("pendulum/tla-c.toml", 2),
    "MuJoCo": ("inverted-pendulum/tla-c.toml", 2),
    "dm_control": ("dmc-cartpole-balance/tla-c.toml", 1),
}


# dm_control's video (a minute of software rendering on a CPU) on request; its frames render in test_envs
@pytest.mark.parametrize("family", [pytest.param(f, marks=pytest.mark.slow) if f == "dm_control" else f
                                    for f in RECIPES])
def test_video_per_episode_with_the_layer_strip(family, tmp_path):
    path, episodes = RECIPES[family]
    if family != "classic control" and os.environ.get("MUJOCO_GL") == "disable":
        pytest.skip("no OpenGL library (EGL or OSMesa) on this machine for MuJoCo to render with")
    recipe = load_recipe(path, ["learner.hidden=[16, 16]"])
    learners = build_learners(recipe)
    active = list(phases_of(recipe)[-1].active)
    written = write_videos(recipe, learners, active, tmp_path, episodes=episodes, seed=3, threshold=0.0)
    assert [p.name for p, _ in written] == [f"threshold-0.0-episode-{k}.mp4" for k in range(episodes)]
    at_recipe = write_videos(recipe, learners, active, tmp_path, episodes=1, seed=3)  # (beside them, not over them)
    assert [p.name for p, _ in at_recipe] == ["episode-0.mp4"] and written[0][0].exists()
    reader = imageio.get_reader(written[0][0])
    frames = [f for f in reader]
    reader.close()
    assert len(frames) > 1 and frames[0].shape[1] >= 480
    strip = frames[-1][-60:].reshape(-1, 3).astype(int)  # the strip's layer rows and action row
    fast = np.array(COLOURS[1])  # the second layer's colour: its label, and its blocks where it acted
    assert np.any(np.abs(strip - fast).sum(axis=1) < 40)
