"""The child-process base: ready, one error type with the child's message,
quit, timeout, messages to the parent; a new child process is one small class."""
from __future__ import annotations

import os
import time

import numpy as np
import pytest

from bonesim.runtime.child import BASE_STATUS, ERROR_BYTES, ChildProcess, record_dtype
from bonesim.errors import BonesimError, ProcessFailed
from tests.bonesim.fakes import wait_for

#: A start-up timeout the tests' children never need [s].
PATIENT_S = 60.0


class Counter(ChildProcess):
    """A new kind of child process in one small class: it counts up by
    ``step`` until asked to quit, publishes the count in its status and
    each count in a ring, and sends its total to the parent at the end."""

    NAME = "bonesim-test-counter"
    STATUS = (("count", np.int64), ("step", np.int64))
    RINGS = ("ui",)                             # any declared ring will do

    def __init__(self, step: int = 1, fail: str = "", hang: bool = False):
        self.step, self.fail, self.hang = step, fail, hang
        super().__init__()

    def child_args(self) -> dict:
        return {"step": self.step, "fail": self.fail, "hang": self.hang}

    @classmethod
    def run(cls, child, step, fail, hang) -> None:
        if fail:
            raise BonesimError(fail, path="counter.toml", field="step")
        if hang:
            while not child.quit:               # never ready; still quits when told
                time.sleep(0.01)
            return
        child.status["step"] = step
        child.ready()
        ui = child.rings["ui"]
        while not child.quit:
            child.status["count"] += step
            ui.append(t_s=[float(child.status["count"])], name=[b"count"], value=[b""])
            time.sleep(0.001)
        child.send({"total": int(child.status["count"])})


class Crasher(ChildProcess):
    NAME = "bonesim-test-crasher"

    @classmethod
    def run(cls, child) -> None:
        {}["missing"]                           # a programming error, not a user error


class Vanisher(ChildProcess):
    NAME = "bonesim-test-vanisher"

    @classmethod
    def run(cls, child) -> None:
        os._exit(7)                             # no error report at all


def test_a_new_child_is_one_small_class_ready_status_ring_quit_and_messages():
    with Counter(step=3) as c:
        assert c.status["ready"] and c.running and c.pid is not None
        assert c.status["step"] == 3
        assert wait_for(lambda: c.status["count"] > 30)
        assert wait_for(lambda: c.rings["ui"].count > 10)
        seen = c.rings["ui"].read(0, 10)["t_s"]
        np.testing.assert_array_equal(seen, 3.0 * np.arange(1, 11))
        c.stop()
        assert not c.running and c.status["done"] and not c.status["failed"]
        assert c.messages == [{"total": int(c.status["count"])}]
        c.stop()                                 # idempotent
        final = int(c.status["count"])
    c.close()                                    # so is close
    # the final status stays readable once the shared memory is freed
    assert c.status["done"] and int(c.status["count"]) == final


def test_a_start_up_error_reaches_the_parent_as_one_error_type_with_the_message():
    c = Counter(fail="step must be positive")
    with pytest.raises(ProcessFailed) as e:
        c.start(PATIENT_S)
    assert isinstance(e.value, BonesimError)
    assert e.value.process == "bonesim-test-counter"
    assert str(e.value) == ("bonesim-test-counter: counter.toml [step]: "
                            "step must be positive")
    assert not c.running                       # stopped, memory freed
    c.close()


def test_a_crash_names_the_exception_and_a_silent_death_its_exit_code():
    with pytest.raises(ProcessFailed, match=r"bonesim-test-crasher: KeyError: 'missing'"):
        Crasher().start(PATIENT_S)
    with pytest.raises(ProcessFailed,
                       match=r"bonesim-test-vanisher: exited during start-up \(exit code 7\)"):
        Vanisher().start(PATIENT_S)


def test_a_child_that_is_never_ready_times_out_and_is_stopped():
    c = Counter(hang=True)
    with pytest.raises(ProcessFailed, match="did not start within 0.5 s"):
        c.start(0.5)
    assert not c.running
    h = Counter(hang=True).launch()
    try:
        with pytest.raises(RuntimeError, match="already started"):
            h.launch()
    finally:
        h.close()                                # a child that is not ready still quits
    assert not h.running


def test_launch_then_wait_ready_lets_the_parent_work_meanwhile():
    c = Counter().launch()
    try:
        assert not c.status["ready"]            # still spawning
        c.wait_ready(PATIENT_S)
        assert c.status["ready"]
    finally:
        c.close()


def test_status_fields_are_named_and_checked():
    dt = record_dtype(BASE_STATUS, [("t_s", np.float64), ("pos_mm", np.float64, (3,))])
    assert dt.names[:4] == ("ready", "done", "failed", "error")
    assert dt.fields["error"][0].itemsize == ERROR_BYTES
    assert dt.fields["pos_mm"][0].shape == (3,)
    with pytest.raises(ValueError, match="'ready' is declared twice"):
        record_dtype(BASE_STATUS, [("ready", np.uint8)])
    c = Counter()
    try:
        assert c.status["count"] == 0 and c.error == ""      # zeroed, strings too
        assert not c.running and c.wait() and c.receive() is None
    finally:
        c.close()
