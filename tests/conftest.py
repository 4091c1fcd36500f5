"""Shared test fixtures."""

import pytest
import torch


@pytest.fixture
def one_torch_thread():
    """Run a test with one torch intra-op thread and restore the setting afterwards.

    The simulators' tensors are tiny: on a shared 2-core machine a second thread only adds contention
    (a 6×6 matmul took 25 ms with two contended threads, 20 µs with one).
    """
    old = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(old)


@pytest.fixture
def ray_env():
    """The environment of a Ray driver run in its own process: a private, short Ray temp folder (RAY_TMPDIR: Ray's
    socket paths must stay under the 107 bytes AF_UNIX allows, and pytest's tmp_path is too deep), no RAY_ADDRESS
    (a local cluster, never another run's), one thread per process."""
    import os
    import shutil
    import tempfile

    folder = tempfile.mkdtemp(prefix="rt", dir="/tmp")
    env = {k: v for k, v in os.environ.items() if k != "RAY_ADDRESS"}
    # a loaded 2-core machine: Ray runs its workers at nice 15, so beside a busy process on their core they starve
    # (measured: a table's prepare task made no progress in 4 min beside a sysid run); they may take over Ray's 60 s
    # to register; an experiment beside the suite may fill the memory past the OOM monitor's 95 % (these are small)
    env.update(OMP_NUM_THREADS="1", RAY_TMPDIR=folder, RAY_USAGE_STATS_ENABLED="0", RAY_worker_niceness="0",
               RAY_worker_register_timeout_seconds="300", RAY_memory_monitor_refresh_ms="0")
    yield env
    shutil.rmtree(folder, ignore_errors=True)
