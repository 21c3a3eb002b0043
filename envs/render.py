"""Rendering the catalogue envs with MuJoCo's own renderer: the headless GL backend, observations back to
``qpos``, and a camera per env.

- :func:`select_gl_backend` picks ``MUJOCO_GL`` when it is unset and there is no display: ``egl`` (Mesa's
  software EGL renders without a GPU; Debian: ``apt-get install -y libegl1 libgl1 libgl1-mesa-dri``), else
  ``osmesa`` (``libosmesa6``). It must run before ``mujoco`` is imported (MuJoCo picks its GL context class on
  import); ``import envs`` runs it.
- :func:`qpos_from_obs`: the layout's groups, in layout order, are the ``qpos`` coordinates of every catalogue
  env (angles from cos/sin pairs by ``atan2``, quaternions normalised); appended entries (Ant's main-body x,
  Humanoid's mass-centre x) come after ``nq`` and are dropped. The observations here include the root x (and
  y) (``exclude_current_positions_from_observation=False``), so no coordinate is missing.
- :class:`Renderer`: RGB frames of a ``qpos`` or of an env's live state, with the camera of :data:`CAMERAS`
  (a side view of the planar envs, a view from above of Reacher) whose look-at point follows a given root.
"""

from __future__ import annotations

import ctypes.util
import os
import sys
import warnings
from collections.abc import MutableMapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from envs.spec import EnvSpec

#: The one-line system install of the headless GL backend (Debian/Ubuntu), as the README and .ci/run give it.
APT_INSTALL = "apt-get install -y libegl1 libgl1 libgl1-mesa-dri"


def select_gl_backend(environ: MutableMapping[str, str] | None = None) -> str | None:
    """Set ``MUJOCO_GL`` for headless rendering when it is unset and there is no display; returns its value.

    Linux without ``DISPLAY``/``WAYLAND_DISPLAY``: ``egl`` when a libEGL is installed, else ``osmesa`` when a
    libOSMesa is, else nothing (rendering then fails with MuJoCo's own error; simulation is unaffected). A value
    the user set is never changed. Call before ``mujoco`` is imported.
    """
    environ = os.environ if environ is None else environ
    if environ.get("MUJOCO_GL"):
        return environ["MUJOCO_GL"]
    if not sys.platform.startswith("linux") or environ.get("DISPLAY") or environ.get("WAYLAND_DISPLAY"):
        return None
    for backend, library in (("egl", "EGL"), ("osmesa", "OSMesa")):
        if ctypes.util.find_library(library):
            environ["MUJOCO_GL"] = backend
            return backend
    return None


def qpos_from_obs(spec: EnvSpec, obs: np.ndarray, nq: int) -> np.ndarray:
    """The MuJoCo ``qpos`` ``(..., nq)`` of observations ``(..., obs_dim)``: the layout's groups in order, each by
    its kind's conversion (``envs.layout.KIND_QPOS``: ``SO2_cossin`` -> ``atan2(sin, cos)``, ``SO3_quat``
    normalised), the first ``nq`` coordinates."""
    obs = np.asarray(obs, dtype=np.float64)
    if obs.shape[-1] != spec.obs_dim:
        raise ValueError(f"{spec.name}: observations must end in obs_dim={spec.obs_dim}, got {obs.shape}")
    from envs.layout import KIND_QPOS

    parts = []
    for group in spec.layout.groups:  # each kind's conversion (envs.layout.KIND_QPOS), else the entries themselves
        entries = obs[..., list(group.indices)]
        parts.append(KIND_QPOS[group.kind](entries) if group.kind in KIND_QPOS else entries)
    qpos = np.concatenate(parts, axis=-1)
    if qpos.shape[-1] < nq:
        raise ValueError(f"{spec.name}: the layout gives {qpos.shape[-1]} coordinates, the model has nq={nq}")
    return qpos[..., :nq]


class RenderingUnavailable(RuntimeError):
    """MuJoCo could not open an offscreen GL context; the message says what to install."""


def gl_failure(err: BaseException, what: str = "cannot render offscreen") -> str:
    """The one-line message of MuJoCo's GL failing: ``what`` failed, with which ``MUJOCO_GL`` and error, and the
    headless backend to use instead with its install."""
    reason = " ".join(str(err).split())[:200]
    return (
        f"MuJoCo {what} (MUJOCO_GL={os.environ.get('MUJOCO_GL', 'unset')}: {type(err).__name__}: {reason}); "
        "without a display use MUJOCO_GL=egl (or leave it unset) with the headless GL libraries installed "
        f"(Debian/Ubuntu: {APT_INSTALL})"
    )


@dataclass(frozen=True)
class Camera:
    """A free camera: distance, elevation and azimuth (degrees), a look-at point, and ``track``: the world axes
    (0 x, 1 y, 2 z) along which the look-at point follows the root body (MuJoCo body 1): ``lookat + root``."""

    distance: float
    elevation: float
    azimuth: float = 90.0
    lookat: tuple[float, float, float] = (0.0, 0.0, 0.0)
    track: tuple[int, ...] = ()


#: The camera of each env (azimuth 90: looking along +y, the planar envs' x to the right).
CAMERAS: dict[str, Camera] = {
    "invertedpendulum": Camera(2.2, -10.0, lookat=(0.0, 0.0, 0.3)),
    "inverteddoublependulum": Camera(3.2, -10.0, lookat=(0.0, 0.0, 0.6)),
    "reacher": Camera(0.75, -90.0, lookat=(0.0, 0.0, 0.0)),
    "hopper": Camera(3.2, -10.0, lookat=(0.0, 0.0, 0.9), track=(0,)),
    "walker2d": Camera(3.6, -10.0, lookat=(0.0, 0.0, 0.9), track=(0,)),
    "halfcheetah": Camera(3.6, -10.0, track=(0, 2)),  # follows the torso's height too: the cheetah flips
    "ant": Camera(3.5, -25.0, lookat=(0.0, 0.0, 0.4), track=(0, 1)),
    "humanoid": Camera(4.0, -10.0, lookat=(0.0, 0.0, 1.0), track=(0, 1)),
}


class Renderer:
    """Offscreen RGB frames ``(height, width, 3)`` uint8 of one MuJoCo env: a catalogue env with its :data:`CAMERAS`
    camera, your own with MuJoCo's default free camera (fixed, on the whole model).

    ``frame(qpos, root)`` renders a state given by ``qpos`` (velocities are irrelevant to a picture);
    ``frame_of(data)`` renders a live ``MjData`` (an env's ``unwrapped.data``). ``root`` (x, y, z): the root
    position the camera follows (default: the rendered state's own root body, see :meth:`root`).
    ``model``: render this ``MjModel`` (an env's live one) instead of a fresh one; ``effects=False`` drops
    shadows and reflections (videos: a frame every step).
    """

    def __init__(
        self, spec: EnvSpec, width: int = 320, height: int = 240, model: Any = None, effects: bool = True
    ) -> None:
        import mujoco

        if width < 16 or height < 16:
            raise ValueError(f"frames must be at least 16x16 pixels, got {width}x{height}")
        if model is None:  # a model of its own; an env's live model (``env.unwrapped.model``) for its frames
            env = spec.make()
            model = env.unwrapped.model
            env.close()
        self.model = model
        self.model.vis.global_.offwidth = max(self.model.vis.global_.offwidth, width)
        self.model.vis.global_.offheight = max(self.model.vis.global_.offheight, height)
        self.data = mujoco.MjData(self.model)
        self.spec, self.width, self.height = spec, width, height
        self.config = CAMERAS.get(spec.name)  # None: your own env (videos), MuJoCo's default free camera
        try:
            with warnings.catch_warnings():  # glfw warns before it fails without a display: the error says it all
                warnings.simplefilter("ignore")
                self._renderer = mujoco.Renderer(self.model, height, width)
        except Exception as err:  # ImportError, RuntimeError, mujoco.FatalError: no usable GL context
            raise RenderingUnavailable(gl_failure(err)) from None
        if not effects:  # shadows and reflections: most of a frame's time on a software renderer (~7x here)
            self._renderer.scene.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = 0
            self._renderer.scene.flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = 0
        self.camera = mujoco.MjvCamera()
        mujoco.mjv_defaultFreeCamera(self.model, self.camera)  # the whole model, from its extent
        if self.config is not None:
            self.camera.distance, self.camera.elevation = self.config.distance, self.config.elevation
            self.camera.azimuth = self.config.azimuth

    def root(self, qpos: np.ndarray) -> np.ndarray:
        """The world position (x, y, z) of the root body (MuJoCo body 1) at ``qpos``."""
        import mujoco

        self.data.qpos[:] = qpos
        mujoco.mj_kinematics(self.model, self.data)
        return self.data.xpos[1].copy()

    def frame(self, qpos: np.ndarray, root: np.ndarray | None = None) -> np.ndarray:
        """The frame of the state ``qpos`` (nq,), the camera tracking ``root`` (default: this state's root)."""
        import mujoco

        self.data.qpos[:] = qpos
        self.data.qvel[:] = 0.0
        mujoco.mj_forward(self.model, self.data)
        return self.frame_of(self.data, root)

    def frame_of(self, data: Any, root: np.ndarray | None = None) -> np.ndarray:
        """The frame of a live ``MjData`` of this env's model."""
        if self.config is not None:
            lookat = np.array(self.config.lookat, dtype=np.float64)
            axes = list(self.config.track)
            lookat[axes] += (data.xpos[1] if root is None else np.asarray(root))[axes]
            self.camera.lookat[:] = lookat
        self._renderer.update_scene(data, self.camera)
        return self._renderer.render().copy()

    def close(self) -> None:
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None

    def __enter__(self) -> Renderer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
