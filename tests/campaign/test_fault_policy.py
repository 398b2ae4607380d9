"""The fault policy: pause or abort on instrument errors, record again on lost frames, auto-resume."""

import pytest

from labrunner.procedure import Faults
from labrunner.runner.fault_policy import AutoResume, FaultPolicy


@pytest.mark.parametrize("policy, hard, in_safe_stop, action", [
    ("pause", False, False, "pause"),
    ("abort", False, False, "abort"),
    ("pause", True, False, "abort"),  # refused by a limit: retrying cannot help, go to the safe stop
    ("pause", False, True, "fail"),
    ("abort", True, True, "fail"),
])
def test_instrument_errors(policy, hard, in_safe_stop, action):
    assert FaultPolicy(Faults(policy=policy)).on_instrument_error(hard=hard, in_safe_stop=in_safe_stop) == action


def test_lost_frames_are_recorded_again_up_to_max_rerecords():
    policy = FaultPolicy(Faults(max_dropped_frames=2, max_rerecords=2))
    assert policy.on_record(dropped=2, attempts=1) == "keep"
    assert [policy.on_record(dropped=3, attempts=a) for a in (1, 2, 3)] == ["record_again", "record_again", "give_up"]


def test_auto_resume_only_after_fault_pauses_and_at_most_max_times():
    auto = AutoResume(delay_s=900.0, max_resumes=2)
    assert not auto.due()  # an operator's pause is not resumed
    for n in (1, 2):
        auto.fault_paused()
        assert auto.due() and auto.take() == n and not auto.due()
    auto.fault_paused()
    assert not auto.due() and auto.resumes == 2
    never = AutoResume(delay_s=None)
    never.fault_paused()
    assert not never.due()
