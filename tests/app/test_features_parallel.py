"""``qr-cl features --workers N`` and ``--shard I/N`` with tiny random-weight models: the same
bytes as one process, shards that write every frame exactly once, runs that stop on a worker's
error, a killed worker or Ctrl-C leaving only whole frames, and resumes that redo exactly the
damaged frames."""
from __future__ import annotations

import argparse
import json
import multiprocessing
import os
import signal
import threading
import time
from collections import Counter

import numpy as np
import pytest

from qr_cl.app import cli
from qr_cl.app.features import store, workers
from qr_cl.app.features.shards import Shard, shard_spec
from tests.app.features_helpers import drawn_scene, run_features, write_models

FRAMES = 4
STEMS = [f"view_{i}" for i in range(FRAMES)]


@pytest.fixture(scope="module")
def models(tmp_path_factory):
    return write_models(tmp_path_factory.mktemp("weights"))


def _tree(folder):
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir())}


@pytest.fixture(scope="module")
def reference(models, tmp_path_factory):
    """The files of one unsharded run in this process (--workers 1) on a scene of FRAMES frames."""
    scene, images = drawn_scene(tmp_path_factory.mktemp("reference"), frames=FRAMES)
    assert run_features(scene, images, models) == 0
    return _tree(scene / "language_features")


def _fails(capsys, code, *words):
    err = capsys.readouterr().err.strip().splitlines()[-1].split("\r")[-1]   # after the progress bar
    assert code == 2 and err.startswith("qr-cl: error: "), err
    for word in words:
        assert str(word) in err, (word, err)
    return err


def _written(monkeypatch):
    """The stems the run in this process writes (store.write_frame spied on)."""
    stems = []
    real = store.write_frame

    def spy(folder, stem, ids, features):
        real(folder, stem, ids, features)
        stems.append(stem)
    monkeypatch.setattr(store, "write_frame", spy)
    return stems


def _only_whole_frames(folder):
    """Every id map in place is a whole frame; returns the stems done."""
    done = sorted(p.name[:-len("_s.npy")] for p in folder.glob("*_s.npy"))
    assert all(store.frame_done(folder, stem) for stem in done), done
    assert not multiprocessing.active_children()                    # no worker left running
    return done


def test_workers_write_the_same_bytes(models, reference, tmp_path, monkeypatch, capsys):
    scene, images = drawn_scene(tmp_path, frames=FRAMES)
    setups = []
    real_init = workers.WorkerPool.__init__

    def spy(self, setup, count):
        setups.append((setup, count))
        real_init(self, setup, count)
    monkeypatch.setattr(workers.WorkerPool, "__init__", spy)
    assert run_features(scene, images, models, "--workers", "2") == 0
    assert [(s.threads, count) for s, count in setups] == [(1, 2)]            # --threads 1 in all: 1 each
    assert f"{FRAMES} frames written" in capsys.readouterr().out
    assert _tree(scene / "language_features") == reference


def test_threads_are_shared_by_the_workers():
    assert [workers.worker_threads(total, n) for total, n in [(16, 4), (16, 3), (2, 4), (1, 1), (7, 2)]] \
        == [4, 5, 1, 1, 3]


def test_shards_write_every_frame_exactly_once(models, reference, tmp_path, monkeypatch, capsys):
    scene, images = drawn_scene(tmp_path, frames=FRAMES)
    written = _written(monkeypatch)
    by_shard = {}
    for index in (1, 2, 3):
        before = len(written)
        assert run_features(scene, images, models, "--shard", f"{index}/3") == 0
        by_shard[index] = written[before:]
        out = capsys.readouterr().out
        assert f"shard {index}/3: {len(by_shard[index])} of {FRAMES} frames" in out, out
    assert by_shard == {1: ["view_0", "view_3"], 2: ["view_1"], 3: ["view_2"]}
    assert Counter(written) == Counter(STEMS)
    assert _tree(scene / "language_features") == reference
    assert run_features(scene, images, models, "--shard", "2/3") == 0                 # done: nothing again
    assert len(written) == FRAMES and "1 of 1 frames already written" in capsys.readouterr().out


def test_a_shard_with_other_settings_refuses(models, tmp_path, monkeypatch, capsys):
    scene, images = drawn_scene(tmp_path, frames=2)
    assert run_features(scene, images, models, "--shard", "1/2") == 0
    _fails(capsys, run_features(scene, images, models, "--shard", "2/2", "--points-per-side", "3"),
           store.RECORD, "1 frames were made with other masks", "--overwrite")
    assert not (scene / "language_features" / "view_1_s.npy").exists()


def test_a_run_stops_when_another_replaces_the_record(models, tmp_path, monkeypatch, capsys):
    scene, images = drawn_scene(tmp_path, frames=2)
    record = scene / "language_features" / store.RECORD
    real = store.write_frame

    def other_shard_starts(folder, stem, ids, features):      # a shard with other settings starts meanwhile
        real(folder, stem, ids, features)
        mixed = json.loads(record.read_text())
        mixed["masks"]["points_per_side"] = 3
        store.write_atomic(record, lambda fh: fh.write(json.dumps(mixed).encode()))
    monkeypatch.setattr(store, "write_frame", other_shard_starts)
    _fails(capsys, run_features(scene, images, models), record, "another run wrote other masks", "--overwrite")
    assert not (scene / "language_features" / "view_1_s.npy").exists()       # stopped after one frame


def test_shards_writing_the_record_at_once(tmp_path):
    folder, record, errors = tmp_path / "language_features", {"clip": {"model": "m"}, "masks": {"n": 1}}, []

    def start():
        try:
            for _ in range(20):
                assert store.check_record(folder, record, ["a"], False, ["a", "b"]) == ["a"]
                (folder / store.RECORD).unlink(missing_ok=True)      # the next start writes it again
        except BaseException as exc:                                  # noqa: BLE001 - reported below
            errors.append(exc)
    threads = [threading.Thread(target=start) for _ in range(8)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert not errors, errors
    assert not list(folder.glob(".*.tmp"))


def test_the_shards_split_every_frame_into_exactly_one():
    rng = np.random.default_rng(0)
    triples = [(n, frames) for n in range(1, 13) for frames in range(0, 40)]
    triples += [(int(n), int(frames)) for n, frames in zip(rng.integers(1, 64, 100), rng.integers(0, 1000, 100))]
    for count, frames in triples:
        parts = [Shard(index, count).select(range(frames)) for index in range(1, count + 1)]
        assert sorted(p for part in parts for p in part) == list(range(frames)), (count, frames)
        assert {len(part) for part in parts} <= {frames // count, -(-frames // count)}     # even loads
        assert all(part == sorted(part) for part in parts)
    assert Shard().whole and str(shard_spec(" 2/8")) == "2/8"


def test_resume_redoes_exactly_the_damaged_frames(models, reference, tmp_path, monkeypatch):
    scene, images = drawn_scene(tmp_path, frames=FRAMES)
    lang = scene / "language_features"
    lang.mkdir()
    for name, data in reference.items():
        (lang / name).write_bytes(data)
    (lang / "view_0_s.npy").write_bytes(reference["view_0_s.npy"][:-100])        # data cut short
    (lang / "view_1_s.npy").write_bytes(reference["view_1_s.npy"][:40])          # header cut short
    ids = np.load(lang / "view_2_s.npy")
    assert ids.max() >= 0
    np.save(lang / "view_2_f.npy", np.load(lang / "view_2_f.npy")[:int(ids.max())])   # a row short
    (lang / ".view_3_s.npy.k1ll3d_x.tmp").write_bytes(b"half a file")             # a killed write; view_3 whole
    old = lang / ".features.json.0ld_x.tmp"
    old.write_bytes(b"{")
    os.utime(old, (time.time() - 2 * store.STALE_SECONDS,) * 2)
    fresh = lang / ".view_9_f.npy.other_shard.tmp"                                # another run's write in progress
    fresh.write_bytes(b"in progress")
    assert [store.frame_done(lang, stem) for stem in STEMS] == [False, False, False, True]

    written = _written(monkeypatch)
    assert run_features(scene, images, models) == 0
    assert sorted(written) == ["view_0", "view_1", "view_2"]
    assert fresh.exists()
    fresh.unlink()
    assert _tree(lang) == reference                                                # the stale ones are gone


def test_a_killed_worker_stops_the_run(models, reference, tmp_path, monkeypatch, capsys):
    scene, images = drawn_scene(tmp_path, frames=FRAMES)
    lang = scene / "language_features"
    killed = []
    real = workers.WorkerPool.frames

    def kill_a_busy_worker(self, work):
        for item in real(self, work):
            yield item
            if not killed:                                  # after the first frame: the other one, on its frame
                conn, stem = next(iter(self.in_flight.items()))
                pid = self.processes[conn].pid
                os.kill(pid, signal.SIGSTOP)                # (it may just have written it: see below)
                killed.append((stem, store.frame_done(lang, stem)))
                os.kill(pid, signal.SIGKILL)
    monkeypatch.setattr(workers.WorkerPool, "frames", kill_a_busy_worker)
    _fails(capsys, run_features(scene, images, models, "--workers", "2"), "a worker process died on frame",
           "SIGKILL", "run again")
    monkeypatch.undo()
    done = _only_whole_frames(lang)
    (stem, finished), = killed
    assert 1 <= len(done) < FRAMES and (stem in done) == finished

    written = _written(monkeypatch)
    assert run_features(scene, images, models) == 0
    assert sorted(written) == sorted(set(STEMS) - set(done))
    assert _tree(lang) == reference


def test_ctrl_c_stops_the_workers(models, reference, tmp_path, monkeypatch):
    scene, images = drawn_scene(tmp_path, frames=FRAMES)
    lang = scene / "language_features"

    def interrupt(folder, record):
        raise KeyboardInterrupt
    monkeypatch.setattr(store, "check_record_kept", interrupt)         # Ctrl-C once a frame is written
    with pytest.raises(KeyboardInterrupt):
        run_features(scene, images, models, "--workers", "2")
    monkeypatch.undo()
    assert 1 <= len(_only_whole_frames(lang)) < FRAMES
    assert run_features(scene, images, models) == 0
    assert _tree(lang) == reference


def test_a_worker_error_stops_the_run(models, tmp_path, capsys):
    scene, images = drawn_scene(tmp_path, frames=FRAMES)
    (images / "view_1.png").write_bytes(b"not a png")
    _fails(capsys, run_features(scene, images, models, "--workers", "2"), images / "view_1.png", "not a readable image")
    assert "view_1" not in _only_whole_frames(scene / "language_features")


@pytest.mark.parametrize("option, value, expected", [
    ("--shard", "0/4", "expected I/N"), ("--shard", "5/4", "expected I/N"), ("--shard", "x", "expected I/N"),
    ("--shard", "2/", "expected I/N"), ("--shard", "1/0", "expected I/N"), ("--shard", "-1/4", "expected I/N"),
    ("--workers", "0", "expected a positive integer"), ("--workers", "two", "expected a positive integer")])
def test_bad_shard_or_workers_is_one_line(option, value, expected, capsys):
    with pytest.raises(SystemExit) as exit_:
        cli.main(["features", "room", "--images", "i", "--clip-weights", "c", "--sam-weights", "s",
                  f"{option}={value}"])
    err = capsys.readouterr().err
    assert exit_.value.code == 2 and err.count("\n") == 1 and "Traceback" not in err, err
    assert err.startswith(f"qr-cl features: error: argument {option}: {expected}") and value in err, err


def test_shard_spec_is_an_argparse_type():
    assert shard_spec("3/3") == Shard(3, 3)
    with pytest.raises(argparse.ArgumentTypeError):
        shard_spec("4/3")
