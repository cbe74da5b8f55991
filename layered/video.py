"""Videos of evaluation episodes with a strip under each frame that shows the stack at work.

The strip scrolls with the episode: one row per layer marks the steps at which the layer decided
(a grey tick) and those at which its part of the executed action was non-zero (a coloured block:
above the threshold, or a committed gate), and the last row draws the executed action within its
bounds. The current step is the right edge. Frames are written as they are rendered (MP4, H.264,
through imageio's ffmpeg plugin, which brings its own binary).
"""

from __future__ import annotations

from collections import deque
from collections.abc import Mapping
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw, ImageFont

from layered.agents import make_aec_env
from layered.envs import control_timestep
from layered.evaluate import episode_seeds, run_episode
from layered.learners import Learner
from layered.metrics import StepRecord
from layered.schema import Recipe

WINDOW = 80  # steps shown in the strip
LABEL_WIDTH = 64
ROW = 18  # pixels per layer row
ACTION_ROW = 44
HEADER = 20
COLOURS = [(31, 119, 180), (255, 127, 14), (44, 160, 44), (214, 39, 40), (148, 103, 189), (140, 86, 75)]
ACTION_COLOURS = [(20, 20, 20), (0, 150, 150), (200, 0, 150), (130, 130, 0), (90, 90, 220), (230, 120, 0)]
GREY, LIGHT, WHITE, INK = (150, 150, 150), (235, 235, 235), (255, 255, 255), (30, 30, 30)
MIN_WIDTH = 480  # small renders are scaled up so that the strip stays legible


class StripVideo:
    """A watcher that writes every rendered frame, with the strip under it, to one MP4 file."""

    def __init__(self, path: Path, layers: list[str], low: np.ndarray, high: np.ndarray, fps: int) -> None:
        import imageio.v2 as imageio

        self.path, self.layers, self.low, self.high = path, layers, low, high
        self.writer = imageio.get_writer(path, fps=fps, codec="libx264", quality=7, macro_block_size=1,
                                         ffmpeg_log_level="error")
        self.history: deque[tuple[tuple[str, ...], tuple[str, ...], np.ndarray]] = deque(maxlen=WINDOW)
        self.font = ImageFont.load_default(size=12)

    def wants(self, step: int) -> bool:
        return True

    def __call__(self, step: int, frame: np.ndarray, record: StepRecord) -> None:
        self.history.append((record.acted, record.decided, record.action))  # (acted, decided, action)
        image = Image.fromarray(np.ascontiguousarray(frame[..., :3]))
        if image.width < MIN_WIDTH:
            image = image.resize((MIN_WIDTH, round(image.height * MIN_WIDTH / image.width)), Image.Resampling.NEAREST)
        strip = self._strip(step, image.width)
        canvas = Image.new("RGB", (image.width, image.height + strip.height), WHITE)
        canvas.paste(image, (0, 0))
        canvas.paste(strip, (0, image.height))
        even = canvas.crop((0, 0, canvas.width - canvas.width % 2, canvas.height - canvas.height % 2))
        self.writer.append_data(np.asarray(even))

    def _strip(self, step: int, width: int) -> Image.Image:
        height = HEADER + ROW * len(self.layers) + ACTION_ROW
        strip = Image.new("RGB", (width, height), WHITE)
        draw = ImageDraw.Draw(strip)
        executed = self.history[-1][2]
        action = " ".join(f"{a:+.2f}" for a in executed[:4]) + (" ..." if len(executed) > 4 else "")
        draw.text((4, 3), f"step {step}   action {action}", fill=INK, font=self.font)
        self._legend(draw, width)
        cell = (width - LABEL_WIDTH - 4) / WINDOW
        x0 = width - 4 - cell * len(self.history)  # the oldest step shown
        for row, name in enumerate(self.layers):
            top = HEADER + ROW * row
            draw.rectangle((LABEL_WIDTH, top + 1, width - 4, top + ROW - 2), fill=LIGHT)
            draw.text((4, top + 3), name, fill=COLOURS[row % len(COLOURS)], font=self.font)
            for k, (acted, decided, _) in enumerate(self.history):
                left = x0 + k * cell
                if name in acted:
                    draw.rectangle((left, top + 6, left + max(cell - 1, 1), top + ROW - 3),
                                   fill=COLOURS[row % len(COLOURS)])
                if name in decided:
                    draw.line((left, top + 1, left, top + 6), fill=GREY, width=1)
        self._action_row(draw, width, HEADER + ROW * len(self.layers), x0, cell)
        return strip

    def _legend(self, draw: ImageDraw.ImageDraw, width: int) -> None:
        """Right-aligned key: the tick of a decision, the block of a changed action, where now is."""
        right: float = width - 4
        for text, mark in (("now", None), ("changed the action", "block"), ("decided", "tick")):
            right -= draw.textlength(text, font=self.font)
            draw.text((right, 3), text, fill=INK, font=self.font)
            if mark == "block":
                draw.rectangle((right - 12, 7, right - 4, 14), fill=INK)  # (the key, in no layer's colour)
            elif mark == "tick":
                draw.line((right - 6, 4, right - 6, 14), fill=GREY, width=1)
            right -= 22

    def _action_row(self, draw: ImageDraw.ImageDraw, width: int, top: int, x0: float, cell: float) -> None:
        """The executed action per dimension against its bounds (bottom to top), step by step."""
        draw.text((4, top + ACTION_ROW / 2 - 7), "action", fill=INK, font=self.font)
        draw.rectangle((LABEL_WIDTH, top + 2, width - 4, top + ACTION_ROW - 3), outline=GREY)
        draw.line((LABEL_WIDTH, top + ACTION_ROW / 2, width - 4, top + ACTION_ROW / 2), fill=LIGHT)  # mid-range
        span = np.where(self.high > self.low, self.high - self.low, 1.0)
        bottom, scale = top + ACTION_ROW - 4, ACTION_ROW - 8
        for d in range(min(len(self.low), len(ACTION_COLOURS))):  # the first six dimensions
            points = [(x0 + (k + 0.5) * cell, bottom - scale * float((a[d] - self.low[d]) / span[d]))
                      for k, (_, _, a) in enumerate(self.history)]
            if len(points) > 1:
                draw.line(points, fill=ACTION_COLOURS[d], width=2)

    def close(self) -> None:
        self.writer.close()


def write_videos(recipe: Recipe, learners: Mapping[str, Learner], active: list[str], out_dir: Path, episodes: int,
                 seed: int, threshold: float | None = None) -> list[tuple[Path, float]]:
    """One MP4 per evaluation episode (seeded as `layered eval` seeds them), with each episode's return: episode-K.mp4
    at the recipe's thresholds, threshold-T-episode-K.mp4 at another, so that one never replaces the other."""
    env = make_aec_env(recipe, active=active, evaluation=True, threshold=threshold, keep_trace=True,
                       render_mode="rgb_array")
    if np.ndim(env.render()) != 3:
        env.close()
        raise ValueError(f"{recipe.env.id} renders no rgb_array frames, so no video can be made of it")
    low, high = env.stack.low, env.stack.high
    timestep = control_timestep(recipe.env.id)  # (in real time where the environment's step has a duration)
    fps = round(1 / timestep) if timestep else int(env.base.metadata.get("render_fps") or 30)
    written = []
    for k, episode_seed in enumerate(episode_seeds(seed, episodes)):
        name = f"episode-{k}.mp4" if threshold is None else f"threshold-{threshold}-episode-{k}.mp4"
        video = StripVideo(out_dir / name, env.possible_agents, low, high, fps)
        env.watcher = video
        try:
            measures = run_episode(env, learners, episode_seed)
        finally:
            video.close()
        written.append((video.path, measures.ret))
    env.close()
    return written
