"""Shared test setup: plugin autoload off, caches in a temporary folder, one thread."""

from __future__ import annotations

import os

import pytest

# Third-party plugins installed in the environment must not change what tests see.
os.environ.setdefault("UEVAVD_DISABLE_PLUGIN_AUTOLOAD", "1")


@pytest.fixture(autouse=True, scope="session")
def _isolated_cache(tmp_path_factory):
    os.environ["UEVAVD_CACHE"] = str(tmp_path_factory.mktemp("uevavd-cache"))
    yield


@pytest.fixture(autouse=True, scope="session")
def _threads():
    try:
        import torch

        # the cores shared among pytest-xdist's workers (addopts runs -n auto): oversubscribed
        # torch threads wait on each other and run many times slower
        workers = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
        torch.set_num_threads(max(1, min(2, (os.cpu_count() or 1) // workers)))
    except ImportError:  # pragma: no cover
        pass
    yield
