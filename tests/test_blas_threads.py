"""Numerical work runs on a deliberate thread count (threadpoolctl), restored afterwards."""

from __future__ import annotations

import numpy as np
import pytest
from threadpoolctl import threadpool_info, threadpool_limits

from labrunner.blas_threads import ENV, analysis_threads, configured_threads
from labrunner.errors import UserError


def _blas_threads() -> set[int]:
    return {int(p["num_threads"]) for p in threadpool_info() if p["user_api"] == "blas"}


def test_default_is_one_thread_and_the_caller_setting_comes_back(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv(ENV, raising=False)
    np.ones((4, 4)) @ np.ones((4, 4))  # load numpy's BLAS
    with threadpool_limits(limits=2):
        assert _blas_threads() == {2}
        with analysis_threads() as n:
            assert n == 1
            assert _blas_threads() == {1}
        assert _blas_threads() == {2}


def test_the_environment_sets_it(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv(ENV, "2")
    assert configured_threads() == 2
    with analysis_threads() as n:
        assert n == 2 and _blas_threads() == {2}


@pytest.mark.parametrize("raw", ["0", "two", "-1", "1.5"])
def test_a_bad_setting_is_named(monkeypatch: pytest.MonkeyPatch, raw: str) -> None:
    monkeypatch.setenv(ENV, raw)
    with pytest.raises(UserError, match=ENV):
        configured_threads()
