"""The live worker's lag policy (mapping.live.lag_policy): when it skips ahead, and what it still starts at a stop.
The real process behind the car and stopped by SIGTERM: test_worker_lag.py."""

from mapping.live.lag_policy import expected_window_s, stop_deadline, window_fits, windows_to_skip


def test_skips_to_the_newest_ended_window_only_when_too_far_behind():
    # 20 m windows centred every 10 m: window k ends at 10 k + 10 m
    assert windows_to_skip(1, 40.0, 10, 10, max_behind_m=25) == 0  # window 1 ended 20 m behind
    assert windows_to_skip(1, 50.0, 10, 10, max_behind_m=25) == 3  # 30 m behind: 1-3 skipped, 4 (ended at 50) next
    assert windows_to_skip(1, 55.0, 10, 10, max_behind_m=25) == 3
    assert windows_to_skip(1, 10_000.0, 10, 10, max_behind_m=None) == 0  # no limit: never


def test_a_stop_starts_only_windows_that_end_before_its_timeout_less_the_reserve():
    deadline = stop_deadline(100.0, stop_timeout_s=60.0, reserve_s=20.0)
    assert deadline == 140.0
    assert window_fits(130.0, deadline, 10.0) and not window_fits(130.5, deadline, 10.0)
    assert stop_deadline(100.0, None, 20.0) is None and window_fits(1e9, None, 1e9)
    assert stop_deadline(100.0, 10.0, 20.0) == 100.0  # a reserve longer than the timeout: no window starts
    assert expected_window_s([], 3.0) == 3.0 and expected_window_s([2.0, 7.5, 4.0], 3.0) == 7.5
