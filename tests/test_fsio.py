"""Background reading (slscan.fsio.Prefetched): order, errors, waiting and cancelling; output locks."""

from __future__ import annotations

import os
import threading

import pytest

from slscan.errors import SlscanError
from slscan.fsio import Prefetched


def test_values_come_back_by_key_in_the_order_read():
    order = []

    def read(key):
        order.append(key)
        return key * 2

    with Prefetched(read, ["c", "a", "b", "a"]) as values:
        assert list(values) == ["c", "a", "b"] and len(values) == 3
        assert values["b"] == "bb" and values["c"] == "cc"
        assert dict(values.items()) == {"c": "cc", "a": "aa", "b": "bb"}
    assert order == ["c", "a", "b"]  # one read per key, in the order given


def test_membership_does_not_wait_and_errors_surface_at_their_key():
    gate = threading.Event()

    def read(key):
        if key == "slow":
            gate.wait(10)
        if key == "bad":
            raise SlscanError("bad.png: not a readable image")
        return key

    with Prefetched(read, ["slow", "bad", "ok"]) as values:
        assert "bad" in values and "missing" not in values  # answered while "slow" blocks
        gate.set()
        assert values["slow"] == "slow" and values["ok"] == "ok"
        with pytest.raises(SlscanError, match="bad.png"):
            values["bad"]
        with pytest.raises(KeyError):
            values["missing"]


def test_leaving_the_block_cancels_reads_not_started():
    started = []
    gate, first = threading.Event(), threading.Event()

    def read(key):
        started.append(key)
        first.set()
        gate.wait(10)
        return key

    values = Prefetched(read, list(range(20)))
    assert first.wait(10)  # a read is under way (on a busy machine the thread may start late)
    timer = threading.Timer(0.2, gate.set)
    timer.start()
    values.close()  # waits for the read under way, drops the others
    timer.join()
    assert 1 <= len(started) < 20
    # the shared reading thread is free again for the next caller
    with Prefetched(lambda k: -k, [1, 2]) as again:
        assert again[2] == -2


# --- output locks -----------------------------------------------------------------------


def _dead_pid() -> int:
    """The id of a process that has exited (and been reaped)."""
    import subprocess
    import sys

    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


def test_a_second_writer_of_an_output_is_refused_and_the_lock_goes_away(tmp_path):
    import json
    import socket
    import subprocess
    import sys

    from slscan.fsio import lock_path, output_lock

    out = tmp_path / "deep" / "out"
    other = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(30)"])
    try:
        lock_path(out).parent.mkdir(parents=True)
        lock_path(out).write_text(json.dumps({"pid": other.pid, "host": socket.gethostname(),
                                              "started": "then", "command": "slscan decode s --out out"}))
        with pytest.raises(SlscanError, match=rf"out: another slscan is writing it \(process {other.pid} on "
                                              r".*slscan decode s --out out\).*remove .*\.out\.lock"):
            with output_lock(out):
                pass
        assert lock_path(out).is_file()  # the live writer's lock is left alone
    finally:
        other.kill()
        other.wait()
    with output_lock(out, command="slscan x") as lock:  # its writer is dead now: taken over
        held = json.loads(lock.read_text())
        assert held["pid"] == os.getpid() and held["command"] == "slscan x"
        with output_lock(out):  # nested in this process: shared
            pass
        assert lock.is_file()
    assert not lock_path(out).exists()


@pytest.mark.parametrize("owner", ["dead", "empty-new", "another-host"])
def test_stale_locks_are_taken_over_on_this_host_only(tmp_path, owner):
    import json
    import socket

    from slscan.fsio import lock_path, output_lock

    lock = lock_path(tmp_path / "out")
    if owner == "empty-new":  # its writer may be between creating and filling it
        lock.write_text("")
    else:
        host = socket.gethostname() + ("-elsewhere" if owner == "another-host" else "")
        lock.write_text(json.dumps({"pid": _dead_pid(), "host": host, "started": "then"}))
    if owner == "dead":
        with output_lock(tmp_path / "out"):
            pass
        assert not lock.exists()
    else:  # another host's process cannot be seen from here
        with pytest.raises(SlscanError, match="another slscan is writing it"):
            with output_lock(tmp_path / "out"):
                pass
        assert lock.exists()


def test_a_lock_makes_missing_folders_and_removes_them(tmp_path):
    from slscan.fsio import output_lock

    with pytest.raises(SlscanError, match="refused"):
        with output_lock(tmp_path / "a" / "b" / "out"):
            assert (tmp_path / "a" / "b").is_dir()
            raise SlscanError("refused")
    assert not (tmp_path / "a").exists()
