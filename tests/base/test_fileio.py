import multiprocessing as mp

import pytest

from s3k.base.fileio import atomic_path, atomic_write_json, file_lock


def test_atomic_write_replaces_and_leaves_no_temporary(tmp_path):
    target = tmp_path / "a.json"
    atomic_write_json({"x": 1}, target)
    atomic_write_json({"x": 2}, target)
    assert target.read_text() == '{\n  "x": 2\n}\n'
    assert [p.name for p in tmp_path.iterdir()] == ["a.json"]


def test_failed_write_keeps_the_old_file(tmp_path):
    target = tmp_path / "a.txt"
    target.write_text("old")
    with pytest.raises(RuntimeError), atomic_path(target) as tmp:
        tmp.write_text("half")
        raise RuntimeError("killed")
    assert target.read_text() == "old"
    assert [p.name for p in tmp_path.iterdir()] == ["a.txt"]


def _try_lock(path, queue):
    with file_lock(path, blocking=False) as mine:
        queue.put(mine)


def test_lock_is_exclusive_across_processes_and_freed_on_exit(tmp_path):
    lock = tmp_path / "run.lock"
    ctx = mp.get_context("spawn")
    queue = ctx.Queue()
    with file_lock(lock) as mine:
        assert mine
        p = ctx.Process(target=_try_lock, args=(lock, queue))
        p.start()
        p.join()
        assert queue.get() is False
    p = ctx.Process(target=_try_lock, args=(lock, queue))
    p.start()
    p.join()
    assert queue.get() is True
