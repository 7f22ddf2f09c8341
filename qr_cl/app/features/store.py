"""Where ``qr-cl features`` writes, atomically, and what it resumes from.

Each frame's ``<stem>_f.npy`` then ``<stem>_s.npy`` are written to a temporary file
``.<name>.<random>.tmp`` in ``language_features/`` and renamed into place, so a frame's files are
whole or absent; a frame counts as done when both are in place and whole (:func:`frame_done`). A
run first removes the temporary files a killed writer left of its frames
(:func:`remove_stale_temporaries`). ``language_features/features.json`` records the models (name
and sha256 of each weights file) and settings; a resumed run, or a shard (:mod:`.shards`), with
other ones refuses to mix them into the same folder, and a run stops when another one replaces
the record while it runs (:func:`check_record_kept`).
"""
from __future__ import annotations

import json
import os
import tempfile
import time
from pathlib import Path

import numpy as np

from .errors import FeaturesError

RECORD = "features.json"
#: Age in seconds past which any temporary file in the folder is a killed writer's, whatever it
#: was writing (a frame's file takes seconds): younger ones of other frames may be another
#: shard's writes in progress.
STALE_SECONDS = 3600


def frame_files(folder: Path, stem: str) -> tuple[Path, Path]:
    """(``<stem>_s.npy``, ``<stem>_f.npy``) in ``folder``."""
    return folder / f"{stem}_s.npy", folder / f"{stem}_f.npy"


def frame_written(folder: Path, stem: str) -> bool:
    """Whether both of a frame's files are in place (whole or not)."""
    return all(p.is_file() for p in frame_files(folder, stem))


def frame_done(folder: Path, stem: str) -> bool:
    """Whether a frame's files are both in place and whole: ``.npy`` files whose header and data
    are all there (read memory-mapped: the features' rows are never read), a [4, H, W] id map and
    [M, E] features with a row for every id. Anything else (a file cut short by a crash of
    something other than :func:`write_atomic`, or features and id map of different runs) means
    the frame is redone."""
    s_path, f_path = frame_files(folder, stem)
    try:
        ids = np.load(s_path, mmap_mode="r")
        rows = np.load(f_path, mmap_mode="r")
    except (OSError, ValueError, EOFError):
        return False
    if ids.ndim != 3 or len(ids) != 4 or rows.ndim != 2:
        return False
    return ids.size == 0 or bool(ids.max() < len(rows))


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


def remove_stale_temporaries(folder: Path, stems: list[str]) -> int:
    """Remove the temporary files a killed :func:`write_atomic` left in ``folder``: those of the
    frames ``stems`` (this run's, which no other run writes) and any older than
    :data:`STALE_SECONDS`. Returns how many were removed."""
    mine = {p.name for stem in stems for p in frame_files(folder, stem)}
    now, removed = time.time(), 0
    for tmp in folder.glob(".*.tmp"):
        target = tmp.name[1:-len(".tmp")].rpartition(".")[0]          # .<name>.<random>.tmp
        try:
            if target in mine or now - tmp.stat().st_mtime > STALE_SECONDS:
                tmp.unlink()
                removed += 1
        except FileNotFoundError:                                      # its writer renamed it meanwhile
            pass
    return removed


def _read_record(path: Path) -> dict | None:
    try:
        return json.loads(path.read_text())
    except (OSError, json.JSONDecodeError):
        return None


def _differs(old: dict | None, record: dict) -> str:
    return ", ".join(sorted(k for k in record if old is None or old.get(k) != record[k]) or ["record"])


def check_record(folder: Path, record: dict, stems: list[str], overwrite: bool,
                 scene_stems: list[str] | None = None) -> list[str]:
    """Write ``record`` to ``folder``/features.json (unless it is there already) and return the
    stems of ``stems`` still to do. Frames already written, of any of ``scene_stems`` (default
    ``stems``; a shard passes the whole scene's), are kept when the folder's record equals
    ``record`` (FeaturesError naming the record when it differs, unless ``overwrite``, which
    redoes every frame of ``stems``). Shards starting at once with the same record each find it
    or write the same bytes, atomically."""
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / RECORD
    old = _read_record(path)
    if old != record:
        written = [s for s in (stems if scene_stems is None else scene_stems) if frame_written(folder, s)]
        if written and not overwrite:
            raise FeaturesError(f"{path}: {len(written)} frames were made with other {_differs(old, record)} (or "
                                f"without a record); pass --overwrite to redo them, or another scene folder")
        write_atomic(path, lambda fh: fh.write(json.dumps(record, indent=1).encode()))
    return stems if overwrite else [s for s in stems if not frame_done(folder, s)]


def check_record_kept(folder: Path, record: dict) -> None:
    """FeaturesError naming ``folder``/features.json when it no longer equals ``record``: another
    run (a shard with other models or settings) replaced it while this one wrote frames."""
    path = folder / RECORD
    old = _read_record(path)
    if old != record:
        raise FeaturesError(f"{path}: another run wrote other {_differs(old, record)} into this folder while this "
                            f"one ran; its frames and this run's are mixed: pass the same options to every shard, "
                            f"and --overwrite to redo them")
