"""Trajectory data sets (``.npz``) for the offline experiments: the file format, reading and writing.

File format (written by ``python -m pets.collect``; every array is float64 unless said):

- ``obs`` (n, T + 1, obs_dim): observations, ``obs[i, 0]`` is the reset observation of episode i;
- ``act`` (n, T, act_dim): the actions as they were passed to ``env.step``;
- ``rew`` (n, T): the env's rewards;
- ``terminated`` (n, T) bool: the env's ``terminated`` flag (True at most at the last real step);
- ``lengths`` (n,) int64: the number of real steps of each episode (1 <= lengths <= T);
- ``env`` (0-d unicode array): the canonical env name (``envs.get(env).make()`` gives the
  observation convention);
- optional metadata: ``policy`` (0-d string), ``seed`` (0-d int64), ``reset_seeds`` (n,) int64,
  ``sac_resumed_at`` (k,) int64 (the env steps at which a SAC collection went on from its checkpoint).

T is the longest episode. Shorter episodes are padded: ``obs[i, lengths[i] + 1:]``,
``act[i, lengths[i]:]`` and ``rew[i, lengths[i]:]`` are NaN and ``terminated`` is False there,
so that padding can never be mistaken for data. Episode i's real transitions are
``(obs[i, t], act[i, t], obs[i, t + 1])`` for ``t < lengths[i]``.

Files are written byte-for-byte reproducibly (fixed zip timestamps, fixed key order) and
atomically (temporary file + ``os.replace``). Only numpy is imported at module level, so that the
commands fail fast (without importing torch) on bad arguments.
"""

from __future__ import annotations

import io
import zipfile
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from pets.runs.fileio import atomic_write_bytes

REQUIRED_KEYS = ("obs", "act", "rew", "terminated", "lengths", "env")


# --------------------------------------------------------------------------- files
def npz_bytes(arrays: Mapping[str, np.ndarray]) -> bytes:
    """An uncompressed ``.npz`` archive of ``arrays`` (in the given key order) that ``np.load`` reads.

    Unlike ``np.savez`` the zip entries carry a fixed timestamp, so equal arrays give equal bytes.
    Object arrays are refused (they would need pickle to load).
    """
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", compression=zipfile.ZIP_STORED) as zf:
        for key, value in arrays.items():
            arr = np.asarray(value)
            if arr.dtype == object:
                raise ValueError(f"array {key!r} has dtype object; store numbers, bools or strings")
            info = zipfile.ZipInfo(f"{key}.npy", date_time=(1980, 1, 1, 0, 0, 0))
            info.external_attr = 0o644 << 16
            with zf.open(info, "w", force_zip64=True) as f:
                np.lib.format.write_array(f, arr if arr.flags.c_contiguous else arr.copy(order="C"), allow_pickle=False)
    return buf.getvalue()


def save_dataset(path: str | Path, data: Mapping[str, np.ndarray]) -> Path:
    """Validate ``data`` (see the module docstring) and write it atomically to ``path`` (exactly that name)."""
    check_dataset(data)
    path = Path(path)
    if path.parent and not path.parent.exists():
        path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_bytes(path, npz_bytes(data))
    return path


def missing_data_file(path: Path, what: str = "data file") -> str | None:
    """Why ``path`` is no data set file to read (a directory, or nothing there), or None if it is a file."""
    if Path(path).is_file():
        return None
    return f"{what} {path} " + (
        "is a directory; give a data set file (.npz)" if Path(path).is_dir() else "does not exist"
    )


def load_dataset(path: str | Path) -> dict[str, np.ndarray]:
    """Read and validate a data set file; ValueError (one line) if it is missing or malformed."""
    path = Path(path)
    if problem := missing_data_file(path):
        raise ValueError(problem)
    if not zipfile.is_zipfile(path):  # numpy would call any other file "pickled (object) data"
        raise ValueError(f"{path} is not an .npz archive; data sets are written by pets.collect")
    try:
        with np.load(path, allow_pickle=False) as z:
            data = {k: z[k] for k in z.files}
    except Exception as err:  # zipfile.BadZipFile, ValueError (pickled arrays), OSError, ...
        raise ValueError(
            f"{path} is not a readable .npz data set ({type(err).__name__}: "
            f"{str(err).splitlines()[0] if str(err) else ''})"
        ) from None
    check_dataset(data, str(path))
    return data


def check_dataset(data: Mapping[str, Any], name: str = "data set") -> None:
    """Check keys, shapes, dtypes, lengths and the NaN padding convention; ValueError says what is wrong."""
    missing = [k for k in REQUIRED_KEYS if k not in data]
    if missing:
        raise ValueError(f"{name}: missing arrays {missing}; a data set needs {list(REQUIRED_KEYS)}")
    obs, act, rew = (np.asarray(data[k]) for k in ("obs", "act", "rew"))
    term, lengths = np.asarray(data["terminated"]), np.asarray(data["lengths"])
    env = np.asarray(data["env"])
    if env.shape != () or env.dtype.kind != "U":
        raise ValueError(f"{name}: 'env' must be a 0-d string array, got shape {env.shape} dtype {env.dtype}")
    if obs.ndim != 3 or act.ndim != 3 or rew.ndim != 2 or term.ndim != 2 or lengths.ndim != 1:
        raise ValueError(
            f"{name}: expected obs (n, T+1, obs_dim), act (n, T, act_dim), rew (n, T), terminated (n, T), "
            f"lengths (n,); got {obs.shape}, {act.shape}, {rew.shape}, {term.shape}, {lengths.shape}"
        )
    n, t = act.shape[:2]
    if n < 1 or t < 1:
        raise ValueError(f"{name}: needs at least one episode with one step, got act shape {act.shape}")
    if obs.shape[:2] != (n, t + 1) or rew.shape != (n, t) or term.shape != (n, t) or lengths.shape != (n,):
        raise ValueError(
            f"{name}: inconsistent shapes obs {obs.shape}, act {act.shape}, rew {rew.shape}, "
            f"terminated {term.shape}, lengths {lengths.shape} (expected n={n}, T={t})"
        )
    if obs.dtype.kind != "f" or act.dtype.kind != "f" or rew.dtype.kind != "f":
        raise ValueError(f"{name}: obs, act and rew must be float arrays, got {obs.dtype}, {act.dtype}, {rew.dtype}")
    if term.dtype != np.bool_ or lengths.dtype.kind not in "iu":
        raise ValueError(f"{name}: terminated must be bool and lengths integer, got {term.dtype} and {lengths.dtype}")
    if lengths.min() < 1 or lengths.max() > t:
        raise ValueError(f"{name}: lengths must be in [1, T={t}], got min {lengths.min()} max {lengths.max()}")
    steps = np.arange(t)
    real = steps[None, :] < lengths[:, None]  # (n, T)
    real_obs = np.concatenate([np.ones((n, 1), bool), real], axis=1)  # (n, T + 1)
    for key, arr, mask in (("obs", obs, real_obs), ("act", act, real), ("rew", rew, real)):
        if not np.isfinite(arr[mask]).all():
            raise ValueError(f"{name}: non-finite values in the real (unpadded) part of {key!r}")
    if term[~real].any():
        raise ValueError(f"{name}: 'terminated' is True in the padding (beyond lengths)")


def transitions(data: Mapping[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """All real transitions, episode by episode: ``(obs, act, next_obs)`` of shapes (N, .), N = sum(lengths)."""
    lengths = np.asarray(data["lengths"])
    t = np.asarray(data["act"]).shape[1]
    ep, step = np.nonzero(np.arange(t)[None, :] < lengths[:, None])  # row-major: episode order, then time
    obs, act = np.asarray(data["obs"]), np.asarray(data["act"])
    return obs[ep, step], act[ep, step], obs[ep, step + 1]


def env_name(data: Mapping[str, np.ndarray]) -> str:
    """The data set's canonical env name."""
    return str(np.asarray(data["env"])[()])
