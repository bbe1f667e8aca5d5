"""VRScroll twin: device spec, MuJoCo model and simulation, MorphPatch approximation."""

import os
import sys

__version__ = "0.1.0"

# MuJoCo chooses its OpenGL back end when first imported, VTK its render window when first drawing: on Linux
# without a display both take the off-screen EGL one (nothing to do with a display, or where the user chose)
if sys.platform.startswith("linux") and not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
    os.environ.setdefault("MUJOCO_GL", "egl")
    os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")
