"""Fixtures of the simulator tests: a per-session mechanics cache so tests never touch ~/.cache."""

from __future__ import annotations

import pytest


@pytest.fixture(scope="session", autouse=True)
def mechanics_cache_dir(tmp_path_factory):
    """Point ``USDEFORM_CACHE_DIR`` at a fresh directory for the whole test session."""
    path = tmp_path_factory.mktemp("usdeform-cache")
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("USDEFORM_CACHE_DIR", str(path))
        yield path
