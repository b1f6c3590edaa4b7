"""Background reading (slscan.fsio.Prefetched): order, errors, waiting and cancelling."""

from __future__ import annotations

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
