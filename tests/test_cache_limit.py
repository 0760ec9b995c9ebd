"""The on-disk caches (FEM solutions, FEM library entries) stay within $USDEFORM_CACHE_MAX_MB: the least recently
used entries go first, never the one just written, and a bad limit is refused naming the variable."""

import os

import numpy as np
import pytest

from usdeform._files import CACHE_LIMIT_VARIABLE, cache_limit_bytes, mark_used, prune_cache
from usdeform.errors import InputError


def _entry(folder, name: str, kilobytes: int, age_s: float):
    path = folder / f"{name}.npz"
    path.write_bytes(b"\0" * kilobytes * 1024)
    os.utime(path, (1e9 - age_s, 1e9 - age_s))
    return path


def test_the_least_recently_used_entries_go_first_and_never_the_one_just_written(tmp_path, monkeypatch):
    monkeypatch.setenv(CACHE_LIMIT_VARIABLE, str(250 / 1024))  # 250 kB
    oldest = _entry(tmp_path, "oldest", 100, 400)
    used = _entry(tmp_path, "used", 100, 300)
    middle = _entry(tmp_path, "middle", 100, 200)
    written = _entry(tmp_path, "written", 100, 500)  # the entry just written, with the oldest time of all
    other = tmp_path / "notes.txt"
    other.write_bytes(b"\0" * 300 * 1024)  # not a cache entry: never counted nor removed
    mark_used(used)  # read just now
    prune_cache(tmp_path, keep=written)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["notes.txt", "used.npz", "written.npz"]
    assert not oldest.exists() and not middle.exists()


def test_a_cache_within_its_limit_is_left_as_it_is(tmp_path, monkeypatch):
    monkeypatch.delenv(CACHE_LIMIT_VARIABLE, raising=False)
    assert cache_limit_bytes() == 4096 * 1024 * 1024
    entries = [_entry(tmp_path, f"e{i}", 10, i) for i in range(3)]
    prune_cache(tmp_path, keep=entries[0])
    assert all(path.exists() for path in entries)


@pytest.mark.parametrize("text", ["0", "-5", "lots", "inf", "nan"])
def test_a_limit_that_is_no_positive_number_is_refused_naming_the_variable(monkeypatch, text):
    monkeypatch.setenv(CACHE_LIMIT_VARIABLE, text)
    with pytest.raises(InputError, match=f"{CACHE_LIMIT_VARIABLE}: expected a positive number of MB"):
        cache_limit_bytes()


def test_the_fem_library_cache_prunes_after_each_write(tmp_path, monkeypatch):
    from usdeform.gap import library_cache
    from usdeform.gap.library_entries import LibraryEntry

    monkeypatch.setenv("USDEFORM_CACHE_DIR", str(tmp_path))
    monkeypatch.setenv(CACHE_LIMIT_VARIABLE, str(1 / 1024))  # 1 kB: only the newest entry fits
    folder = tmp_path / "library"
    entry = LibraryEntry(np.zeros((4, 8, 8, 2)), np.zeros(4), np.zeros(4), "")
    first, second = folder / "a.npz", folder / "b.npz"
    library_cache._write(first, entry)
    library_cache._write(second, entry)
    assert second.exists() and not first.exists()
