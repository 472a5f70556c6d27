"""Suite-wide settings.

Under pytest-xdist (``scripts/test.sh`` runs ``-n auto``, one worker per core), a worker's torch keeps its default
thread count where the cores are few (2 threads on a 2-core machine: the native kernels' multi-chunk dispatch and
torch's threaded paths stay tested) and takes its share of the cores, at least 2, where they are many (16 workers
of 16 threads each ran 256 threads on 16 cores).

Which tests a worker runs, and in what order, changes from run to run, so no test may depend on what ran before it
in its process:

- torch's thread count is put back after each test: the scripts' ``main`` (evaluate.py ``--threads 1``,
  doc_figures.py, the benchmarks), called in-process by their tests, set it for the rest of the process, and every
  later test of that worker ran on one thread (the threaded paths untested, and slower);
- the global random generators (torch's, NumPy's legacy one, :mod:`random`) are seeded before each test from its
  node id: the tests that draw from them (``torch.rand`` without a generator) saw whatever state the tests before
  them had left, a different draw at each run under xdist (one fixed order before).

Where the tests' device is CUDA (``TORCHFACE_TEST_DEVICE``, ``cuda`` unless it names another, as
tests/test_cuda.py reads it), ``CUBLAS_WORKSPACE_CONFIG=:4096:8``, cuBLAS's condition for deterministic products
(tests/test_cuda.py's runs under ``torch.use_deterministic_algorithms(True)``), is set here, before any test runs,
unless the environment sets it. Two tests set it themselves (``monkeypatch.setenv``), after whatever CUDA products
earlier tests had run: torch allocates a stream's cuBLAS workspace at its first product, with the size the variable
gave then, and keeps it (torch's own check of the mode reads the variable at each call, and passed). Under xdist
each worker reads this file before its first test too.
"""

from __future__ import annotations

import os
import random
import zlib

import numpy as np
import pytest
import torch

if os.environ.get("TORCHFACE_TEST_DEVICE", "cuda").split(":")[0] == "cuda":
    os.environ.setdefault("CUBLAS_WORKSPACE_CONFIG", ":4096:8")

#: The worker's torch thread count (set by :func:`pytest_configure`), put back after each test.
_THREADS = torch.get_num_threads()


def pytest_configure(config) -> None:
    global _THREADS
    workers = os.environ.get("PYTEST_XDIST_WORKER_COUNT")
    if workers:
        share = max(2, (os.cpu_count() or 1) // int(workers))
        torch.set_num_threads(min(torch.get_num_threads(), share))
    _THREADS = torch.get_num_threads()


@pytest.hookimpl(tryfirst=True)
def pytest_runtest_setup(item) -> None:
    seed = zlib.crc32(item.nodeid.encode())  # (the same for a test whichever worker runs it, and after whatever)
    torch.manual_seed(seed)
    np.random.seed(seed)
    random.seed(seed)


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_teardown(item, nextitem):
    yield  # (the test's fixtures torn down first: one of them may have set the count)
    if torch.get_num_threads() != _THREADS:
        torch.set_num_threads(_THREADS)
