"""The CSV logs: every row on disk once written, and a size a stopped run can cut the file back to."""

import pytest

from layered.errors import BadInput
from layered.logs import CsvLog


def test_rows_are_on_disk_as_written_and_truncate_returns_to_a_recorded_size(tmp_path):
    log = CsvLog(tmp_path / "episodes.csv", ["phase", "step", "return"])
    log.start()
    log.write({"phase": 0, "step": 5, "return": 1.5})
    assert (tmp_path / "episodes.csv").read_bytes() == b"phase,step,return\r\n0,5,1.5\r\n"  # read while still open
    mark = log.size()
    assert mark == len("phase,step,return\r\n0,5,1.5\r\n")
    log.write({"phase": 0, "step": 9})  # a missing column stays empty
    assert (tmp_path / "episodes.csv").read_bytes().endswith(b"0,9,\r\n")
    log.truncate(mark)
    log.write({"phase": 1, "step": 2, "return": -3.0})
    log.close()
    assert (tmp_path / "episodes.csv").read_bytes() == b"phase,step,return\r\n0,5,1.5\r\n1,2,-3.0\r\n"
    with pytest.raises(BadInput, match="shorter than the 10000 bytes its checkpoint recorded: the rows"):
        log.truncate(10_000)


def test_a_column_outside_the_header_is_refused_and_nothing_is_written(tmp_path):
    log = CsvLog(tmp_path / "m.csv", ["step"])
    log.start()
    with pytest.raises(AssertionError, match=r"columns \['loss'\]"):
        log.write({"step": 1, "loss": 0.5})
    log.close()
    assert (tmp_path / "m.csv").read_bytes() == b"step\r\n"


def test_a_log_reopened_after_close_appends(tmp_path):
    log = CsvLog(tmp_path / "m.csv", ["step"])
    log.start()
    log.write({"step": 1})
    log.close()
    again = CsvLog(tmp_path / "m.csv", ["step"])  # as a resumed run holds it
    again.write({"step": 2})
    again.close()
    assert (tmp_path / "m.csv").read_bytes() == b"step\r\n1\r\n2\r\n"


def test_a_file_begun_under_fewer_columns_goes_on_under_its_own_header(tmp_path):
    path = tmp_path / "metrics.csv"
    old = CsvLog(path, ["step", "return"])  # as an earlier version wrote it, before a measure was added
    old.start()
    old.write({"step": 1, "return": 2.0})
    mark = old.size()
    old.write({"step": 2, "return": 3.0})  # after its last checkpoint
    old.close()
    resumed = CsvLog(path, ["step", "return", "at_bounds"])
    resumed.truncate(mark)
    resumed.write({"step": 2, "return": 4.0, "at_bounds": 0.5})  # the new column left out, nothing shifted
    with pytest.raises(AssertionError, match=r"columns \['loss'\]"):
        resumed.write({"step": 3, "loss": 0.5})
    resumed.close()
    assert path.read_bytes() == b"step,return\r\n1,2.0\r\n2,4.0\r\n"


def test_a_file_with_a_column_this_run_does_not_write_is_refused_in_one_line(tmp_path):
    from layered.errors import BadInput

    path = tmp_path / "metrics.csv"
    path.write_bytes(b"step,gone\r\n1,2\r\n")
    with pytest.raises(BadInput, match=r"columns \['gone'\] are not among those this run writes"):
        CsvLog(path, ["step", "return"]).truncate(len(b"step,gone\r\n1,2\r\n"))
