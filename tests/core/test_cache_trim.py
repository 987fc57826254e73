"""A cache folder trimmed to its size: the least recently used entries go first, the new one stays."""

from __future__ import annotations

import os

from qube_koopman.core.files import trim_cache


def _entry(folder, name: str, size: int, used: float):
    path = folder / name
    path.write_bytes(b"x" * size)
    os.utime(path, (used, used))
    return path


def test_the_least_recently_used_entries_go_until_the_folder_fits(tmp_path):
    old = _entry(tmp_path, "probes-a.npz", 400, 1000.0)
    middle = _entry(tmp_path, "probes-b.npz", 400, 2000.0)
    recent = _entry(tmp_path, "probes-c.npz", 400, 3000.0)
    other = _entry(tmp_path, "notes.txt", 5000, 0.0)  # not the cache's: never counted or deleted
    assert trim_cache(tmp_path, "probes-*.npz", 1000) == [old]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["notes.txt", "probes-b.npz", "probes-c.npz"]
    assert trim_cache(tmp_path, "probes-*.npz", 800) == []  # fits: nothing more
    assert trim_cache(tmp_path, "probes-*.npz", 100, keep=middle) == [recent]
    assert middle.exists() and other.exists()


def test_the_entry_kept_stays_even_when_it_alone_is_too_large(tmp_path):
    big = _entry(tmp_path, "probes-a.npz", 2000, 1000.0)  # the oldest, but just written
    small = _entry(tmp_path, "probes-b.npz", 10, 2000.0)
    assert trim_cache(tmp_path, "probes-*.npz", 500, keep=big) == [small]
    assert big.exists()
