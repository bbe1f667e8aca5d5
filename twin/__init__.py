"""VRScroll twin: device spec, MuJoCo model and simulation, MorphPatch approximation."""

import ctypes.util
import os
import sys

__version__ = "0.1.0"

# MuJoCo chooses its OpenGL back end when first imported, VTK its render window when first drawing: on Linux
# without a display both take the off-screen EGL one (nothing to do with a display, or where the user chose)
if sys.platform.startswith("linux") and not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
    os.environ.setdefault("MUJOCO_GL", "egl")
    os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")

# MuJoCo's OpenGL back ends on Linux (mujoco/rendering/classic/gl_context.py reads MUJOCO_GL when mujoco is first
# imported: any other value, or osmesa without its library, raises there, before any command could say why)
GL_BACKENDS = ("egl", "osmesa", "glfw", "glx")
_GL_OFF = ("", "disable", "disabled", "off", "false", "0", "enable", "enabled", "on", "true", "1")


def gl_problem() -> str | None:
    """Why the MUJOCO_GL the user set cannot work here (one line naming the choices), or None."""
    chosen = os.environ.get("MUJOCO_GL", "").lower().strip()
    choices = f"unset it, or choose one of {', '.join(GL_BACKENDS)} (egl renders without a display: libegl1)"
    if chosen in _GL_OFF + GL_BACKENDS and not sys.platform.startswith("linux"):
        return None
    if chosen not in _GL_OFF + GL_BACKENDS:
        return f"MUJOCO_GL={chosen} is not one of MuJoCo's OpenGL back ends: {choices}"
    if chosen == "osmesa" and ctypes.util.find_library("OSMesa") is None:
        return f"MUJOCO_GL=osmesa but OSMesa's library is not installed (Debian: libosmesa6): {choices}"
    return None
