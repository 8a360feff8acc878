"""Shared fixtures: the real models of ../shared/data and cached builds."""

from __future__ import annotations

import functools
import os
from pathlib import Path

import pytest

DATA = Path(os.environ.get("PMJAX_DATA", Path(__file__).resolve().parents[1].parent / "shared" / "data"))


def _data_path(name: str) -> str:
    path = DATA / name
    if not path.exists():
        pytest.skip(f"{path} not found (set PMJAX_DATA or put shared/ beside the repository)")
    return str(path)


@functools.lru_cache(maxsize=None)
def _built(name: str, pair_distance: float, metric: str, target_faces: int):
    import pmjax
    from pmjax.builders import BuildOptions, build_pm

    v, f, _, _ = pmjax.load_clean_mesh(_data_path(name))
    options = BuildOptions(pair_distance=pair_distance, metric=metric, target_faces=target_faces)
    return build_pm(v, f, options)


@pytest.fixture(scope="session")
def built():
    """``built(name, pair_distance=0, metric='quadric', target_faces=0)`` -> PMData (cached)."""

    def get(name, pair_distance=0.0, metric="quadric", target_faces=0):
        return _built(name, pair_distance, metric, target_faces)

    return get


@pytest.fixture(scope="session")
def data_path():
    """``data_path(name)``: path of a model in ../shared/data (skips if absent)."""
    return _data_path
