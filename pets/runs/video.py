"""MP4 videos of real episodes: one frame per env step, rendered by MuJoCo (:class:`envs.render.Renderer`),
encoded by imageio with its ffmpeg plugin (imageio-ffmpeg ships an ffmpeg binary; the ``viz`` extra).

Used by ``run_pets.py --video EVERY`` (config key ``video_every``: ``RUN/videos/trial-NNNN.mp4``) and
``pets.openloop --video DIR`` (``DIR/episode-N.mp4``). Frames are 320x240 (multiples of 16, so ffmpeg never
resizes them) at the env's real time rate, ``1 / dt`` frames per second, without shadows and reflections
(with Mesa's software renderer they take most of a frame's time: HalfCheetah ~63 ms a frame with them, ~9 ms
without, on this project's 2-core CPUs).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from pets.errors import ConfigError

WIDTH, HEIGHT = 320, 240
VIDEO_DIR = "videos"


def require_video() -> None:
    """ConfigError (one line) unless imageio and imageio-ffmpeg are installed."""
    try:
        import imageio  # noqa: F401
        import imageio_ffmpeg  # noqa: F401
    except ImportError as err:
        raise ConfigError(
            f"videos need imageio and imageio-ffmpeg ({err}); install them with: pip install -e '.[viz]'"
        ) from None


def trial_video_path(run_dir: Path, trial: int) -> Path:
    """Where a run's video of trial ``trial`` goes: ``RUN/videos/trial-NNNN.mp4``."""
    return Path(run_dir) / VIDEO_DIR / f"trial-{trial:04d}.mp4"


def frames_per_second(spec: Any) -> int:
    """The env's real time rate (at least 1)."""
    return max(1, round(1.0 / spec.dt))


def write_mp4(path: str | Path, frames: list[np.ndarray] | np.ndarray, fps: int) -> Path:
    """Encode ``frames`` (each (H, W, 3) uint8) as an H.264 MP4 at ``path``, atomically (temporary file in the
    same directory, then ``os.replace``)."""
    import imageio.v2 as imageio

    path = Path(path)
    if len(frames) == 0:
        raise ValueError(f"{path}: no frames to write")
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}.{os.getpid()}.tmp.mp4")
    try:
        imageio.mimwrite(tmp, list(frames), fps=fps, codec="libx264", macro_block_size=16, ffmpeg_log_level="error")
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    return path


class EpisodeRecorder:
    """Frames of a live env: ``start()``, ``capture()`` after every step, ``save(path)`` at the end."""

    def __init__(self, spec: Any, env: Any, width: int = WIDTH, height: int = HEIGHT) -> None:
        from envs.render import Renderer

        inner = env.unwrapped
        if not (hasattr(inner, "model") and hasattr(inner, "data")):  # what MuJoCo's renderer draws from
            raise ConfigError(  # first: installing imageio would not help
                f"videos are rendered by MuJoCo; {spec.name} ({spec.gym_id}) is not a MuJoCo env: drop --video"
            )
        require_video()
        self.spec, self.env = spec, env
        # RenderingUnavailable without GL; no shadows and reflections: ~9 instead of ~63 ms a frame in software
        self.renderer = Renderer(spec, width, height, model=env.unwrapped.model, effects=False)
        self.frames: list[np.ndarray] = []
        self.recording = False

    def start(self) -> None:
        self.frames, self.recording = [], True

    def capture(self) -> None:
        """One frame of the env's current state (when recording)."""
        if self.recording:
            self.frames.append(self.renderer.frame_of(self.env.unwrapped.data))

    def save(self, path: str | Path) -> int:
        """Write the frames so far as an MP4 and stop recording; returns the number of frames."""
        write_mp4(path, self.frames, frames_per_second(self.spec))
        count, self.frames, self.recording = len(self.frames), [], False
        return count

    def close(self) -> None:
        self.renderer.close()
