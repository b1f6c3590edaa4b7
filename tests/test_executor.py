"""Per-view work gives the same results inline, in local processes and on a Dask cluster."""

from __future__ import annotations

import operator
import os
import sys
import time

import numpy as np
import pytest

from slscan.decode.pipeline import decode_session
from slscan.decode.rangemap import read_ply
from slscan.errors import SlscanError
from slscan.executor import Executor
from slscan.virtual.device import VirtualCaptureConfig, capture_session


def test_map_keeps_the_order():
    items = list(range(7))
    assert list(Executor(workers=1).map(operator.neg, items)) == [-i for i in items]
    assert list(Executor(workers=2).map(operator.neg, items)) == [-i for i in items]


def _where(item):
    time.sleep(0.05)
    return item, os.getpid()


def _has(name):
    return os.getpid(), name in sys.modules


def _die_in_a_helper(item):
    parent, value = item
    if os.getpid() != parent:
        os._exit(3)
    return value


def _fail_on_three(item):
    if item == 3:
        raise ValueError("item 3")
    return item


def test_helpers_are_kept_and_this_process_takes_part():
    ex = Executor(workers=2)
    first = list(ex.map(_where, range(8)))
    second = list(ex.map(_where, range(8)))
    assert [i for i, _ in first] == list(range(8)) == [i for i, _ in second]
    pids = {pid for _, pid in first}
    assert os.getpid() in pids and len(pids) == 2  # this process and one helper
    assert {pid for _, pid in second} == pids  # the same helper: started once, imports paid once


def test_start_has_the_helpers_import_the_stage_modules():
    ex = Executor(workers=2)
    list(ex.map(_where, range(2)))  # the pool runs already
    assert "wave" not in sys.modules
    ex.start(4, ["wave"])
    loaded = [has for pid, has in ex.map(_has, ["wave"] * 6) if pid != os.getpid()]
    assert loaded and all(loaded)  # the first item always goes to the helper


def test_an_error_in_a_helper_or_here_reaches_the_caller_and_the_pool_goes_on():
    with pytest.raises(ValueError, match="item 3"):
        list(Executor(workers=2).map(_fail_on_three, range(7)))
    with pytest.raises(SlscanError, match="worker process died"):
        list(Executor(workers=2).map(_die_in_a_helper, [(os.getpid(), i) for i in range(6)]))
    assert list(Executor(workers=2).map(operator.neg, range(5))) == [0, -1, -2, -3, -4]


def _read_relative(item):
    time.sleep(0.05)
    return os.getpid(), open(item).read()


def test_helpers_follow_the_callers_working_directory(tmp_path, monkeypatch):
    ex = Executor(workers=2)
    list(ex.map(_where, range(4)))  # the helper starts in this directory
    for name in ("a", "b"):
        (tmp_path / name).mkdir()
        (tmp_path / name / "x.txt").write_text(name)
        monkeypatch.chdir(tmp_path / name)  # a later stage, run from elsewhere, with relative paths
        results = list(ex.map(_read_relative, ["x.txt"] * 6))
        assert {text for _, text in results} == {name}
        assert len({pid for pid, _ in results}) == 2  # the helper read some too


def test_bad_settings_are_refused():
    with pytest.raises(SlscanError, match="at least 1"):
        Executor(workers=0)
    with pytest.raises(SlscanError, match="tcp://HOST"):
        Executor(scheduler="localhost")


@pytest.fixture(scope="module")
def two_views(tmp_path_factory):
    config = VirtualCaptureConfig(views=2, camera_scale=0.25, projector_scale=0.25, levels=7, lit_images=False)
    return capture_session(config, tmp_path_factory.mktemp("ex") / "capture")


def _faces(folder):
    return [read_ply(folder / f"view_00{i}.ply").vertices for i in range(2)]


def test_decode_in_processes_and_on_a_dask_cluster_match_inline(two_views, tmp_path):
    distributed = pytest.importorskip("distributed")
    decode_session(two_views, tmp_path / "inline", executor=Executor(workers=1))
    decode_session(two_views, tmp_path / "procs", executor=Executor(workers=2))
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                  dashboard_address=None) as cluster:
        decode_session(two_views, tmp_path / "dask", executor=Executor(scheduler=cluster.scheduler_address))
    for other in ("procs", "dask"):
        for a, b in zip(_faces(tmp_path / "inline"), _faces(tmp_path / other)):
            np.testing.assert_array_equal(a, b)


def test_an_unreachable_scheduler_is_a_clear_error(two_views, tmp_path):
    pytest.importorskip("distributed")
    with pytest.raises(SlscanError, match="cannot reach the Dask scheduler"):
        decode_session(two_views, tmp_path / "x", executor=Executor(scheduler="tcp://127.0.0.1:9"))
    assert not (tmp_path / "x").exists()


def _pid_and_trim(_item):
    """On a Dask worker: the task's process and its malloc setting (the thresholds are
    not readable back from glibc; the flag says they were set)."""
    import os

    from slscan import executor

    return os.getpid(), executor._MALLOC_TUNED is (sys.platform == "linux")


def test_dask_results_are_released_and_malloc_tuned():
    """The cluster keeps no result once the caller has it (146 views' range maps held 8.9
    GiB in the workers before), and every task runs with the worker's malloc tuned."""
    distributed = pytest.importorskip("distributed")
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=True,
                                  dashboard_address=None) as cluster, \
            distributed.Client(cluster.scheduler_address) as client:
        def held() -> int:
            return client.run_on_scheduler(lambda dask_scheduler: len(dask_scheduler.tasks))

        results = Executor(scheduler=cluster.scheduler_address).map(_pid_and_trim, range(4))
        out = [next(results), next(results)]  # two of four taken: the cluster lets those go
        deadline = time.monotonic() + 10
        while held() > 2 and time.monotonic() < deadline:
            time.sleep(0.1)
        assert held() <= 2
        out += list(results)
        assert all(tuned for _, tuned in out) and len({pid for pid, _ in out}) == 1
