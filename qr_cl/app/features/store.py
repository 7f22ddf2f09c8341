"""Where ``qr-cl features`` writes, atomically, and what it resumes from.

Each frame's ``<stem>_f.npy`` then ``<stem>_s.npy`` are written to a temporary file in
``language_features/`` and renamed into place, so a frame's files are whole or absent; a frame
counts as done when both exist. ``language_features/features.json`` records the models (name
and sha256 of each weights file) and settings; a resumed run with other ones refuses to mix them
into the same folder.
"""
from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path

import numpy as np

from .errors import FeaturesError

RECORD = "features.json"


def frame_files(folder: Path, stem: str) -> tuple[Path, Path]:
    """(``<stem>_s.npy``, ``<stem>_f.npy``) in ``folder``."""
    return folder / f"{stem}_s.npy", folder / f"{stem}_f.npy"


def frame_done(folder: Path, stem: str) -> bool:
    """Whether both of a frame's files are in place."""
    return all(p.is_file() for p in frame_files(folder, stem))


def write_atomic(path: Path, write) -> None:
    """Call ``write(file object)`` on a temporary file beside ``path``, flush it to disk, then
    rename it to ``path`` (a crash leaves the old file or none, never a partial one)."""
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as fh:
            write(fh)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def write_frame(folder: Path, stem: str, ids: np.ndarray, features: np.ndarray) -> None:
    """Write a frame's features then its id map (the id map last: it marks the frame done)."""
    s_path, f_path = frame_files(folder, stem)
    write_atomic(f_path, lambda fh: np.save(fh, features))
    write_atomic(s_path, lambda fh: np.save(fh, ids))


def check_record(folder: Path, record: dict, stems: list[str], overwrite: bool) -> list[str]:
    """Write ``record`` to ``folder``/features.json and return the stems still to do. Frames
    already done are kept when the folder's record equals ``record`` (FeaturesError naming the
    record when it differs, unless ``overwrite``, which redoes every frame)."""
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / RECORD
    done = [s for s in stems if frame_done(folder, s)]
    if done and not overwrite:
        try:
            old = json.loads(path.read_text())
        except (OSError, json.JSONDecodeError):
            old = None
        if old != record:
            diff = sorted(k for k in record if old is None or old.get(k) != record[k]) or ["record"]
            raise FeaturesError(f"{path}: {len(done)} frames were made with other {', '.join(diff)} (or without a "
                                f"record); pass --overwrite to redo them, or another scene folder")
    write_atomic(path, lambda fh: fh.write(json.dumps(record, indent=1).encode()))
    return stems if overwrite else [s for s in stems if s not in done]
