"""Which OpenGL backend MuJoCo renders with, chosen without loading one: stepping a MuJoCo environment
needs no GL library, only rendering it does (videos, galleries).

MuJoCo and dm_control read `MUJOCO_GL` when they are imported, and the EGL backend fails at import
where the EGL library is missing. So on a machine without a display the backend is chosen by which
library is installed (EGL, else OSMesa), or rendering is turned off, before either is imported; a
`MUJOCO_GL` the user set is left as it is.
"""

from __future__ import annotations

import ctypes.util
import os

from layered.errors import BadInput

OFF = "disable"  # what MuJoCo and dm_control read as "no rendering backend"
HOW_TO_INSTALL = ("rendering a MuJoCo environment needs an OpenGL library and none was found: install EGL "
                  "(Debian/Ubuntu: apt install libegl1) or OSMesa (apt install libosmesa6), or set MUJOCO_GL")


class RenderingUnavailable(BadInput, RuntimeError):
    """A MuJoCo environment was asked to render on a machine with no OpenGL backend."""


def choose_backend() -> None:
    """Set `MUJOCO_GL` for a machine without a display, unless the user has (and pygame's SDL to render
    off-screen); call before MuJoCo is imported."""
    if "DISPLAY" in os.environ:
        return
    os.environ.setdefault("SDL_VIDEODRIVER", "dummy")
    if "MUJOCO_GL" not in os.environ:
        found = [name for name, library in (("egl", "EGL"), ("osmesa", "OSMesa")) if ctypes.util.find_library(library)]
        os.environ["MUJOCO_GL"] = found[0] if found else OFF


def check_can_render(env_module: str) -> None:
    """Refuse, in one line, to render an environment (named by its class's module) that renders through
    MuJoCo where no backend was found."""
    mujoco_based = any(part in env_module for part in ("mujoco", "robotics", "dm_control"))
    if mujoco_based and os.environ.get("MUJOCO_GL", "").lower() in ("disable", "disabled", "off", "false", "0"):
        raise RenderingUnavailable(HOW_TO_INSTALL)
