"""``minidiff.scoped.set_within``: the one way minidiff's per-thread modes are set."""

import contextvars
import threading

import pytest

from minidiff.scoped import set_within


def test_the_value_holds_within_the_block_and_the_old_one_comes_back_after_an_error():
    mode = contextvars.ContextVar("mode", default="outer")
    with set_within(mode, "a") as given:
        assert given == "a" and mode.get() == "a"
        with pytest.raises(RuntimeError), set_within(mode, "b"):
            assert mode.get() == "b"
            raise RuntimeError
        assert mode.get() == "a"
    assert mode.get() == "outer"


def test_another_thread_does_not_see_the_value():
    mode = contextvars.ContextVar("mode", default=False)
    seen = []
    with set_within(mode, True):
        thread = threading.Thread(target=lambda: seen.append(mode.get()))
        thread.start()
        thread.join()
        assert mode.get() is True
    assert seen == [False]
