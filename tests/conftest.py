"""Suite-wide settings.

Under pytest-xdist (``scripts/test.sh`` runs ``-n auto``, one worker per core), a worker's torch keeps its default
thread count where the cores are few (2 threads on a 2-core machine: the native kernels' multi-chunk dispatch and
torch's threaded paths stay tested) and takes its share of the cores, at least 2, where they are many (16 workers
of 16 threads each ran 256 threads on 16 cores).
"""

from __future__ import annotations

import os

import torch


def pytest_configure(config) -> None:
    workers = os.environ.get("PYTEST_XDIST_WORKER_COUNT")
    if workers:
        share = max(2, (os.cpu_count() or 1) // int(workers))
        torch.set_num_threads(min(torch.get_num_threads(), share))
