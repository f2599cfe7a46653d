"""Default OpenGL backend for MuJoCo rendering, chosen before dm_control is imported.

dm_control picks its rendering backend once, when ``dm_control._render`` is first imported, from the
``MUJOCO_GL`` environment variable. When the variable is unset it tries GLFW first; on a machine
without a display GLFW then prints ``X11: The DISPLAY environment variable is missing`` (a
``GLFWError`` warning) on every import, although physics never needs OpenGL.

Policy, applied only when ``MUJOCO_GL`` is unset and dm_control's backend has not been chosen yet:

* A display is available (``DISPLAY`` or ``WAYLAND_DISPLAY`` set): leave ``MUJOCO_GL`` unset, so
  dm_control picks GLFW exactly as it would without dvfb.
* Headless, ``PYOPENGL_PLATFORM`` set to ``egl`` or ``osmesa``: that platform (dm_control refuses a
  backend that disagrees with it).
* Headless with an EGL library: ``egl``. It renders off-screen (GPU driver or Mesa's software
  renderer), prints nothing, and keeps ``physics.render()`` working for videos and plots.
* Headless without a usable EGL: ``disable``. Physics works; rendering raises a clear RuntimeError.
  (dm_control's backends fail at import when they cannot be set up, e.g. no EGL display can be
  opened, so a failed default is re-tried as ``disable`` instead of breaking ``import dvfb.envs``.)

A value the user sets is never overridden, so rendering with any backend (``osmesa``, ``egl``,
``glfw``) keeps working when ``MUJOCO_GL`` is set before ``dvfb.envs`` (or dm_control) is imported.
"""

from __future__ import annotations

import ctypes.util
import os
import sys

MUJOCO_GL = "MUJOCO_GL"
_PYOPENGL_PLATFORM = "PYOPENGL_PLATFORM"


def _headless() -> bool:
    return not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


def configure_default_mujoco_gl() -> str | None:
    """Set ``MUJOCO_GL`` if it is unset and the backend is still undecided; return the value used.

    Returns the backend name this function chose, or None when it left the environment alone.
    """
    if MUJOCO_GL in os.environ or "dm_control._render" in sys.modules or not _headless():
        return None
    pyopengl_platform = os.environ.get(_PYOPENGL_PLATFORM)
    if pyopengl_platform in ("egl", "osmesa"):
        backend = pyopengl_platform  # the user already chose PyOpenGL's platform; follow it
    else:
        backend = "egl" if ctypes.util.find_library("EGL") else "disable"
    pyopengl_platform_was_set = pyopengl_platform is not None
    os.environ[MUJOCO_GL] = backend
    if backend != "disable":
        try:
            import dm_control._render  # noqa: F401  (chooses the backend now)
        except Exception:  # noqa: BLE001  (ImportError, or PyOpenGL errors for a missing library)
            # The backend could not be set up (e.g. no EGL display): fall back to physics-only.
            for module_name in [m for m in sys.modules if m.startswith("dm_control._render")]:
                del sys.modules[module_name]
            if not pyopengl_platform_was_set:
                os.environ.pop(_PYOPENGL_PLATFORM, None)
            backend = "disable"
            os.environ[MUJOCO_GL] = backend
    return backend
