"""The mapping worker's append-only journal: lines fold into the state, a torn line is skipped and counted
and loses nothing after it, an old single-document journal is converted."""

import json

from mapping.live.odometry import Odometry
from mapping.live.worker_journal import (
    JOURNAL_NAME,
    JournalHeader,
    JournalState,
    WindowEntry,
    append_line,
    header_line,
    progress_line,
    read_journal,
)

HEADER = JournalHeader(2, config_sha256="abc", grid_resolution_m=0.1, cameras=["front"])


def _drive(folder, windows: int) -> tuple[JournalState, Odometry]:
    """A worker's saves: the header, then a line per window while the odometry grows (its tip moves)."""
    append_line(folder, header_line(HEADER))
    state, odometry, saved = JournalState(HEADER), Odometry(), 0
    t = 0
    for k in range(windows):
        for _ in range(7):  # 0.3 s apart: every other message moves the tip instead of adding a knot
            t += 300_000_000
            odometry.add(t, 10.0)
        state.next_window, state.mapped_until_m, state.odometry_last_speed_mps = k + 1, 40.0 * k, 10.0
        window = WindowEntry(k, "done", tiles=[f"{k}_0.npz"], seq={"imu": [3 * k, 3 * k + 2]})
        state.windows.append(window)
        append_line(folder, progress_line(state, odometry.knots_t, odometry.knots_s, saved, window))
        saved = len(odometry.knots_t)
    return state, odometry


def test_lines_fold_into_the_state_the_worker_saved(tmp_path):
    state, odometry = _drive(tmp_path, 4)
    read = read_journal(tmp_path)
    assert read.windows == state.windows and read.next_window == 4 and read.mapped_until_m == 120.0
    assert read.odometry_t == odometry.knots_t and read.odometry_s == odometry.knots_s
    assert read.header == HEADER and read.skipped_lines == 0 and not read.finished
    lines = (tmp_path / JOURNAL_NAME).read_text().splitlines()
    assert len(lines) == 5 and all(len(line) < 400 for line in lines)  # a line per window, not the whole journal


def test_a_torn_line_is_skipped_and_the_next_append_starts_a_fresh_one(tmp_path):
    state, odometry = _drive(tmp_path, 2)
    with open(tmp_path / JOURNAL_NAME, "ab") as f:
        f.write(b'{"window": {"index": 2, "sta')  # power cut mid-write
    torn = read_journal(tmp_path)
    assert torn.skipped_lines == 1 and len(torn.windows) == 2 and torn.odometry_t == odometry.knots_t
    state.finished = True
    append_line(tmp_path, progress_line(state, odometry.knots_t, odometry.knots_s, len(odometry.knots_t)))
    after = read_journal(tmp_path)
    assert after.finished and after.skipped_lines == 1 and after.odometry_t == odometry.knots_t


def test_a_journal_of_the_old_format_is_converted(tmp_path):
    old = dict(header_line(HEADER), version=1,
               windows=[{"index": 0, "status": "done"}, {"index": 1, "status": "failed"}],
               next_window=2, odometry_t=[0, 500_000_000, 900_000_000], odometry_s=[0.0, 5.0, 9.0],
               odometry_last_speed_mps=10.0, mapped_until_m=80.0, origin=[48.1, 11.5, 520.0], finished=False)
    (tmp_path / "journal.json").write_text(json.dumps(old))
    read = read_journal(tmp_path)
    assert [w.to_json() for w in read.windows] == old["windows"]
    for key in ("next_window", "odometry_t", "odometry_s", "mapped_until_m", "origin"):
        assert getattr(read, key) == old[key], key
    assert read.header.config_sha256 == "abc" and read.header.version == 2 and not (tmp_path / "journal.json").exists()
    assert read_journal(tmp_path) == read  # read again from the converted file
    assert read_journal(tmp_path / "nothing-here") is None
