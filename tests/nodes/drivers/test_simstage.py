"""The in-process sim stage (nodes/drivers/simstage.py) as a RotationStage, on a virtual clock: where it is
during a move, when it settles, limits, faults and their reset, homing, close. (test_stage.py runs the shared
contract against every backend in real time.)"""

from __future__ import annotations

import math

import pytest
from hypothesis import given
from hypothesis import strategies as st
from polarstripe.nodes.drivers import simstage, stage
from polarstripe.nodes.drivers.errors import DriverTimeout, DriverValueError, StageFault
from polarstripe.nodes.drivers.simstage import SimStage


class Clock:
    """``time`` for simstage.py and stage.py: ``monotonic`` reads the virtual clock, ``sleep`` advances it."""

    def __init__(self, t: float = 1000.0):
        self.t = t

    def monotonic(self) -> float:
        return self.t

    def sleep(self, s: float) -> None:
        self.t += s


@pytest.fixture
def clock(monkeypatch):
    c = Clock()
    monkeypatch.setattr(simstage, "time", c)
    monkeypatch.setattr(stage, "time", c)
    return c


def test_before_the_first_move_it_stands_at_start_but_is_not_settled(clock):
    s = SimStage(start_deg=12.5)
    assert s.angle == 12.5 and s.target is None and not s.settled and s.fault is None


def test_a_move_is_linear_at_the_speed_then_settles_after_settle_s(clock):
    s = SimStage(deg_per_s=100.0, settle_s=0.05, start_deg=0.0)
    s.move_to(50.0)  # 0.5 s of travel
    assert s.angle == 0.0 and not s.settled
    clock.t += 0.2
    assert s.angle == pytest.approx(20.0) and not s.settled
    clock.t += 0.3
    assert s.angle == pytest.approx(50.0) and not s.settled  # arrived, still settling
    clock.t += 0.049
    assert not s.settled
    clock.t += 0.002
    assert s.settled and s.angle == 50.0


def test_a_new_move_starts_from_where_the_stage_is(clock):
    s = SimStage(deg_per_s=90.0, settle_s=0.0)
    s.move_to(90.0)
    clock.t += 0.5  # at 45°
    s.move_to(0.0)
    assert s.angle == pytest.approx(45.0)
    clock.t += 0.25
    assert s.angle == pytest.approx(22.5)
    assert s.wait_settled(timeout=1.0) == 0.0


def test_wait_settled_takes_the_travel_and_settle_time(clock):
    s = SimStage(deg_per_s=180.0, settle_s=0.01, start_deg=-90.0)
    s.move_to(90.0)
    t0 = clock.t
    assert s.wait_settled(timeout=5.0, poll_s=0.001) == 90.0
    assert clock.t - t0 == pytest.approx(1.01, abs=0.002)


@pytest.mark.parametrize("bad", [360.5, -361.0, math.nan, -math.inf])
def test_default_limits_are_one_turn_each_way(clock, bad):
    s = SimStage()
    s.move_to(360.0)
    s.move_to(-360.0)
    with pytest.raises(DriverValueError, match=r"sim stage: target angle_deg=.* limits \[-360.0, 360.0\]"):
        s.move_to(bad)
    assert s.target == -360.0


def test_limits_must_be_ordered():
    with pytest.raises(DriverValueError, match="sim stage: software limits min_deg=10 must be below"):
        SimStage(min_deg=10, max_deg=10)


def test_never_settling_times_out_latches_a_fault_and_reset_ends_the_hunting(clock):
    s = SimStage(deg_per_s=100.0, settle_s=0.0)
    s.inject_never_settle()
    s.move_to(30.0)
    assert s.angle == pytest.approx(30.05)  # hunting beside the target
    with pytest.raises(DriverTimeout, match=r"target 30.0° not reached within 2 s \(last reading 30.05"):
        s.wait_settled(timeout=2.0)
    assert s.fault.startswith("target 30.0° not reached") and s.angle is None and not s.settled
    s.reset_fault()
    assert s.fault is None and s.target == 30.0
    assert s.wait_settled(timeout=0.1) == 30.0


def test_faults_are_latched_as_text_joined_once_each(clock):
    s = SimStage()
    s.move_to(10.0)
    clock.t += 1.0
    s.inject_fault("EMCY 0x8611")
    s.inject_fault("heartbeat lost")
    s.inject_fault("EMCY 0x8611")
    assert s.fault == "EMCY 0x8611; heartbeat lost"
    assert s.angle is None and not s.settled
    with pytest.raises(StageFault, match="sim stage: EMCY 0x8611; heartbeat lost"):
        s.move_to(20.0)
    with pytest.raises(StageFault, match="EMCY"):
        s.home()
    with pytest.raises(StageFault, match="EMCY"):
        s.wait_settled(timeout=1.0)
    s.reset_fault()
    clock.t += 1.0
    assert s.fault is None and s.settled and s.angle == 10.0


def test_a_reset_during_a_move_stops_where_the_stage_is(clock):
    s = SimStage(deg_per_s=100.0, settle_s=0.0)
    s.move_to(80.0)
    clock.t += 0.3
    s.inject_fault("EMCY 0x8611")
    clock.t += 0.2  # the model moves on while faulted: 50° at the reset
    s.reset_fault()
    assert s.target == pytest.approx(50.0)  # a new set-point at the present position: nothing jumps
    clock.t += 1.0
    assert s.angle == pytest.approx(50.0) and s.settled


def test_home_goes_to_zero_and_waits(clock):
    s = SimStage(deg_per_s=50.0, settle_s=0.02, start_deg=25.0)
    t0 = clock.t
    s.home(timeout=5.0)
    assert s.target == 0.0 and s.settled and s.angle == 0.0
    assert clock.t - t0 == pytest.approx(0.52, abs=0.01)


def test_home_that_cannot_settle_times_out(clock):
    s = SimStage()
    s.inject_never_settle()
    with pytest.raises(DriverTimeout, match="target 0.0° not reached within 0.5 s"):
        s.home(timeout=0.5)


def test_close_is_idempotent_and_final(clock):
    s = SimStage()
    s.move_to(5.0)
    with s:
        pass
    s.close()
    assert s.angle is None and not s.settled
    for call in (lambda: s.move_to(1.0), s.reset_fault, s.home):
        with pytest.raises(StageFault, match="sim stage: closed"):
            call()


@given(
    start=st.floats(-300, 300), target=st.floats(-300, 300), speed=st.floats(1.0, 1000.0),
    frac=st.floats(0.0, 0.999), settle=st.floats(0.0, 0.5),
)
def test_motion_model_properties(start, target, speed, frac, settle):
    c = Clock()
    old = simstage.time
    simstage.time = c  # (hypothesis runs many examples per fixture: patch by hand)
    try:
        s = SimStage(deg_per_s=speed, settle_s=settle, start_deg=start)
        s.move_to(target)
        duration = abs(target - start) / speed
        c.t += frac * duration
        a = s.angle
        assert min(start, target) - 1e-9 <= a <= max(start, target) + 1e-9
        assert a == pytest.approx(start + (target - start) * frac, abs=1e-6)
        if duration > 0:
            assert not s.settled
        c.t += (1 - frac) * duration + settle + 1e-9
        assert s.settled and s.angle == target
    finally:
        simstage.time = old
