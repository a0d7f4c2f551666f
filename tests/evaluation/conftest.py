"""The real logs' Betaflight headers, decoded once per module for the header and tune tests."""

from __future__ import annotations

import pytest

from tests.evaluation.test_blackbox_header import CS110, GECKO, _headers


@pytest.fixture(scope="module")
def gecko() -> dict:
    return _headers(GECKO)


@pytest.fixture(scope="module")
def cs110() -> dict:
    return _headers(CS110)
