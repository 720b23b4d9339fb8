"""Headless MuJoCo camera rendering that works from any thread.

An EGL (or OSMesa) context is current in one thread at a time, and the edge loop steps each robot
in its own thread, not the one that built it: a renderer made in `__init__` fails there with
EGL_BAD_ACCESS. `CameraRenderer` makes one `mujoco.Renderer` per thread on first use. Shadows and
multisampling are turned off on the model first: at 128x128 they cost far more than they show.
"""

from __future__ import annotations

import os

os.environ.setdefault("MUJOCO_GL", "egl")

import threading

import mujoco
import numpy as np


class CameraRenderer:
    def __init__(self, model: mujoco.MjModel, height: int, width: int) -> None:
        model.vis.quality.shadowsize = 0
        model.vis.quality.offsamples = 0
        model.vis.global_.offwidth = max(model.vis.global_.offwidth, width)
        model.vis.global_.offheight = max(model.vis.global_.offheight, height)
        self.model, self.height, self.width = model, height, width
        self._local = threading.local()
        self._made: list[mujoco.Renderer] = []
        self._lock = threading.Lock()

    def render(self, data: mujoco.MjData, camera: int | str) -> np.ndarray:
        """An (height, width, 3) uint8 frame from `camera`, a copy the caller may keep."""
        renderer = getattr(self._local, "renderer", None)
        if renderer is None:
            renderer = mujoco.Renderer(self.model, self.height, self.width)
            self._local.renderer = renderer
            with self._lock:
                self._made.append(renderer)
        renderer.update_scene(data, camera=camera)
        return renderer.render().copy()

    def close(self) -> None:
        with self._lock:
            made, self._made = self._made, []
        for renderer in made:
            try:
                renderer.close()
            except Exception:  # a context current in a thread that has ended: the process frees it
                pass
