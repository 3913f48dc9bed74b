"""Headless offscreen rendering of MuJoCo scenes (EGL or OSMesa), chosen at first use.

MuJoCo picks its OpenGL platform when ``mujoco`` is imported, from ``MUJOCO_GL``; left unset
on Linux it means GLFW, which needs a display. This module does not depend on that choice:
it creates its own context from ``MUJOCO_GL`` if that names ``egl`` or ``osmesa``, and
otherwise probes, in a subprocess (PyOpenGL's platform cannot change inside a process), EGL
then OSMesa, and uses the first that works. On Debian/Ubuntu, OSMesa comes with the package
``libosmesa6`` and EGL with ``libegl1`` plus a driver (``libegl-mesa0`` or a GPU's).
"""

from __future__ import annotations

import importlib
import os
import subprocess
import sys
import weakref
from functools import lru_cache
from typing import Any

import mujoco
import numpy as np
from numpy.typing import NDArray

__all__ = ["OffscreenRenderer", "RenderUnavailableError", "gl_backend"]

_BACKENDS = ("egl", "osmesa")
_PROBE = (
    "import os, sys; os.environ['MUJOCO_GL'] = sys.argv[1]; "
    "import importlib; m = importlib.import_module('mujoco.' + sys.argv[1]); "
    "c = m.GLContext(16, 16); c.make_current(); c.free()"
)


class RenderUnavailableError(RuntimeError):
    """No headless OpenGL backend could be loaded."""


@lru_cache(maxsize=1)
def gl_backend() -> str | None:
    """The headless GL backend to use (``"egl"`` or ``"osmesa"``), or None if none loads."""
    requested = os.environ.get("MUJOCO_GL", "").strip().lower()
    candidates = (requested,) if requested in _BACKENDS else _BACKENDS
    for name in candidates:
        try:
            probe = subprocess.run(
                [sys.executable, "-c", _PROBE, name],
                capture_output=True,
                timeout=60,
                check=False,
            )
        except (OSError, subprocess.TimeoutExpired):
            continue
        if probe.returncode == 0:
            return name
    return None


def _unavailable_reason() -> str:
    return (
        "no headless OpenGL backend loads (tried MUJOCO_GL=egl and osmesa); on Debian/Ubuntu "
        "install libosmesa6 (software rendering) or libegl1 with a driver such as libegl-mesa0"
    )


def _context(width: int, height: int) -> Any:
    name = gl_backend()
    if name is None:
        raise RenderUnavailableError(_unavailable_reason())
    os.environ.setdefault("PYOPENGL_PLATFORM", name)
    try:
        module = importlib.import_module(f"mujoco.{name}")
        ctx = module.GLContext(width, height)
    except Exception as exc:  # PyOpenGL may already be bound to another platform
        raise RenderUnavailableError(f"cannot create a {name} GL context: {exc}") from exc
    ctx.make_current()
    return ctx


class OffscreenRenderer:
    """Render RGB frames of ``model`` from a named camera, without a display.

    Parameters
    ----------
    model:
        The compiled model; its ``vis.global_.offwidth/offheight`` must be at least the size.
    width, height:
        Frame size in pixels.
    camera:
        Name of a camera of the model (or None: the free camera).
    shadows, reflections:
        Render shadows and mirror reflections (both cost most of the time of a small frame
        under OSMesa; the edge camera turns them off).

    Raises
    ------
    RenderUnavailableError
        When no GL backend loads (see :func:`gl_backend`).
    """

    def __init__(
        self,
        model: mujoco.MjModel,
        width: int = 480,
        height: int = 360,
        camera: str | None = None,
        *,
        shadows: bool = True,
        reflections: bool = True,
    ) -> None:
        if width > model.vis.global_.offwidth or height > model.vis.global_.offheight:
            raise ValueError(
                f"render size {width}x{height} exceeds the model's offscreen buffer "
                f"{model.vis.global_.offwidth}x{model.vis.global_.offheight}"
            )
        self.width, self.height = int(width), int(height)
        self._ctx = _context(self.width, self.height)
        self._scene = mujoco.MjvScene(model, maxgeom=1000)
        self._scene.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = bool(shadows)
        self._scene.flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = bool(reflections)
        self._option = mujoco.MjvOption()
        self._camera = mujoco.MjvCamera()
        if camera is None:
            mujoco.mjv_defaultFreeCamera(model, self._camera)
        else:
            cam_id = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, camera)
            if cam_id < 0:
                raise ValueError(f"camera {camera!r} not in the model")
            self._camera.type = mujoco.mjtCamera.mjCAMERA_FIXED
            self._camera.fixedcamid = cam_id
        self._mjr = mujoco.MjrContext(model, mujoco.mjtFontScale.mjFONTSCALE_100)
        mujoco.mjr_setBuffer(mujoco.mjtFramebuffer.mjFB_OFFSCREEN, self._mjr)
        self._rect = mujoco.MjrRect(0, 0, self.width, self.height)
        self._rgb = np.zeros((self.height, self.width, 3), dtype=np.uint8)
        self._model = model
        # Free the GL resources on close(), garbage collection or interpreter exit (before
        # the EGL display is terminated, which would make the context's own __del__ fail).
        self._finalizer = weakref.finalize(self, _release, self._mjr, self._ctx)

    def render(self, data: mujoco.MjData) -> NDArray[np.uint8]:
        """An (height, width, 3) uint8 frame of the current state of ``data``."""
        self._ctx.make_current()
        mujoco.mjv_updateScene(
            self._model,
            data,
            self._option,
            None,
            self._camera,
            mujoco.mjtCatBit.mjCAT_ALL,
            self._scene,
        )
        mujoco.mjr_render(self._rect, self._scene, self._mjr)
        mujoco.mjr_readPixels(self._rgb, None, self._rect, self._mjr)
        return np.flipud(self._rgb).copy()

    def close(self) -> None:
        """Free the GL resources."""
        self._finalizer()


def _release(mjr: mujoco.MjrContext, ctx: Any) -> None:
    try:
        ctx.make_current()
        mjr.free()
        ctx.free()
    except Exception:  # the GL platform may already be gone at interpreter exit
        pass
    # mujoco's GLContext frees again in __del__ unless told it is done.
    for attr in ("_context", "_buffer"):
        if hasattr(ctx, attr):
            setattr(ctx, attr, None)
