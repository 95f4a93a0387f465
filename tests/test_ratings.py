"""Reading all_data.csv: rater averaging and one clear error per kind of bad input."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from fedlgr.core.data.columns import DESCRIPTOR_COLUMNS, FEATURE_COLUMNS, LABEL_COLUMNS
from fedlgr.errors import DataError
from fedlgr.shell.cli import main
from fedlgr.shell.data.ratings import read_ratings
from tests.support.data import HEADER, rating_row, write_dataset, write_rows

L1 = [1, 2, 3, 4, 5, 1, 2, 3]


def _good_rows():
    return [
        HEADER,
        rating_row(250, True, L1),
        rating_row(250, True, [3, 2, 3, 4, 5, 3, 2, 5]),
        rating_row(251, False, [5] * 8),
        rating_row(250, True, [2, 2, 3, 4, 5, 2, 2, 4]),
    ]


def test_ratings_are_averaged_per_stamp(tmp_path):
    rows = _good_rows()
    rows[4][3] = "0.5000001"  # descriptors agree up to rounding: the first row's is kept
    table = read_ratings(write_rows(tmp_path / "all_data.csv", rows))
    assert table.stamps.tolist() == [250, 251]
    assert table.n_ratings.tolist() == [3, 1]
    np.testing.assert_allclose(table.targets[0], [2, 2, 3, 4, 5, 2, 2, 4])
    np.testing.assert_allclose(table.targets[1], [5] * 8)
    assert table.circle.tolist() == [True, False]
    assert table.values[DESCRIPTOR_COLUMNS[0]][0] == pytest.approx(0.5, abs=1e-7)
    assert table.features.shape == (2, 29)
    np.testing.assert_allclose(table.features[1, -2:], [0, 1])  # the mode flags come last
    assert FEATURE_COLUMNS[-2:] == ("Using circle", "Using arrow")


def test_reads_a_folder_and_tolerates_a_byte_order_mark(tmp_path):
    path = write_rows(tmp_path / "all_data.csv", _good_rows())
    path.write_bytes(b"\xef\xbb\xbf" + path.read_bytes())
    assert len(read_ratings(tmp_path)) == 2


def _mutate(rows, row, column, value):
    rows[row][HEADER.index(column)] = value
    return rows


BAD_INPUTS = {
    "missing column": (
        lambda r: [[v for j, v in enumerate(x) if j != HEADER.index("Carry drinks")] for x in r],
        ["missing column 'Carry drinks'"],
    ),
    "extra column": (
        lambda r: [[*x, "Notes" if i == 0 else "x"] for i, x in enumerate(r)],
        ["unexpected column 'Notes'"],
    ),
    "non-numeric value": (
        lambda r: _mutate(r, 2, "Group radius", "wide"),
        ["row 2 (line 3)", "'Group radius'", "non-numeric value 'wide'"],
    ),
    "empty label": (
        lambda r: _mutate(r, 1, "Carry warm food", ""),
        ["row 1 (line 2)", "'Carry warm food'", "NaN label"],
    ),
    "nan label": (
        lambda r: _mutate(r, 3, "Mopping the floor", "nan"),
        ["row 3 (line 4)", "'Mopping the floor'", "NaN label"],
    ),
    "likert above 5": (
        lambda r: _mutate(r, 2, "Vacuum cleaning", "6"),
        ["row 2 (line 3)", "'Vacuum cleaning'", "Likert value 6 outside 1..5"],
    ),
    "likert below 1": (
        lambda r: _mutate(r, 4, LABEL_COLUMNS[-1], "0"),
        ["row 4 (line 5)", repr(LABEL_COLUMNS[-1]), "Likert value 0 outside 1..5"],
    ),
    "stamp rows disagree": (
        lambda r: _mutate(_mutate(r, 2, "Using circle", "0"), 2, "Using arrow", "1"),
        ["stamp 250", "'Using circle'", "rows [1, 2, 4] disagree"],
    ),
    "both modes": (
        lambda r: _mutate(r, 3, "Using circle", "1"),
        ["row 3 (line 4)", "'Using circle'/'Using arrow'", "exactly one must be 1"],
    ),
    "mode flag not 0/1": (
        lambda r: _mutate(r, 3, "Using arrow", "2"),
        ["row 3 (line 4)", "'Using arrow'", "mode flag 2 is not 0 or 1"],
    ),
    "short row": (
        lambda r: [*r[:2], r[2][:-1], *r[3:]],
        ["row 2 (line 3)", "37 fields, the header has 38"],
    ),
    "fractional stamp": (
        lambda r: _mutate(r, 3, "Stamp", "251.5"),
        ["row 3 (line 4)", "'Stamp'", "stamp '251.5' is not an integer"],
    ),
    "stamp beyond int64": (
        lambda r: _mutate(r, 3, "Stamp", "9223372036854775808"),
        ["row 3 (line 4)", "'Stamp'", "stamp '9223372036854775808' is outside the 64-bit"],
    ),
    "stamp far beyond int64": (
        lambda r: _mutate(r, 2, "Stamp", "1e400"),
        ["row 2 (line 3)", "'Stamp'", "stamp '1e400' is outside the 64-bit integer range"],
    ),
    "stamp not a number": (
        lambda r: _mutate(r, 1, "Stamp", "inf"),
        ["row 1 (line 2)", "'Stamp'", "stamp 'inf' is not an integer"],
    ),
    "infinite descriptor": (
        lambda r: _mutate(r, 2, "Group radius", "inf"),
        ["row 2 (line 3)", "'Group radius'", "infinite value 'inf'"],
    ),
    "negative infinite descriptor": (
        lambda r: _mutate(r, 4, "Distance to closest child", "-Infinity"),
        ["row 4 (line 5)", "'Distance to closest child'", "infinite value '-Infinity'"],
    ),
    "absurd descriptor": (
        lambda r: _mutate(r, 1, "Music playing?", "-2.5e7"),
        ["row 1 (line 2)", "'Music playing?'", "value -2.5e7 is beyond +-1e+06"],
    ),
}


def test_stamps_are_read_exactly_beyond_float_precision(tmp_path):
    """float64 holds integers exactly only up to 2**53: 2**53 and 2**53 + 1 are two scenes."""
    big = 2**53
    rows = [HEADER, rating_row(big, True, L1), rating_row(big + 1, False, [5] * 8)]
    rows.append(rating_row(2**63 - 1, True, [4] * 8))
    rows.append(rating_row(-(2**63), True, [3] * 8))
    table = read_ratings(write_rows(tmp_path / "all_data.csv", rows))
    assert table.stamps.tolist() == [-(2**63), big, big + 1, 2**63 - 1]
    assert table.n_ratings.tolist() == [1, 1, 1, 1]
    np.testing.assert_allclose(table.targets[:, 0], [3, 1, 5, 4])


def test_descriptors_up_to_the_bound_and_integral_stamp_text_are_accepted(tmp_path):
    rows = _mutate(_mutate(_good_rows(), 3, "Group radius", "-1e6"), 3, "Stamp", "2.51e2")
    table = read_ratings(write_rows(tmp_path / "all_data.csv", rows))
    assert table.stamps.tolist() == [250, 251]
    assert table.values["Group radius"][1] == -1e6


@pytest.mark.parametrize("case", BAD_INPUTS)
def test_bad_input_names_file_row_and_column(tmp_path, case):
    mutate, expected = BAD_INPUTS[case]
    path = write_rows(tmp_path / "all_data.csv", mutate(_good_rows()))
    with pytest.raises(DataError) as err:
        read_ratings(path)
    message = str(err.value)
    assert str(path) in message
    for part in expected:
        assert part in message


@pytest.mark.parametrize("case", BAD_INPUTS)
def test_cli_prints_bad_input_as_one_line(tmp_path, case, capsys):
    mutate, expected = BAD_INPUTS[case]
    write_rows(tmp_path / "all_data.csv", mutate(_good_rows()))
    assert main(["data", "check", str(tmp_path), "--modality", "features"]) == 1
    out, err = capsys.readouterr()
    assert out == ""
    assert err.count("\n") == 1 and err.startswith("fedlgr: error: ")
    assert all(part in err for part in expected)


def test_all_problems_are_reported_at_once(tmp_path):
    rows = _mutate(_mutate(_good_rows(), 1, "Vacuum cleaning", "9"), 3, "Carry drinks", "x")
    with pytest.raises(
        DataError, match=r"2 problems: row 1 .*'Vacuum cleaning'.*row 3 .*'Carry drinks'"
    ):
        read_ratings(write_rows(tmp_path / "all_data.csv", rows))


@pytest.mark.parametrize(
    ("content", "expected"),
    [(None, "file not found"), ([], "file is empty"), ([HEADER], "no data rows")],
)
def test_missing_or_empty_file(tmp_path, content, expected):
    path = tmp_path / "all_data.csv"
    if content is not None:
        write_rows(path, content)
    with pytest.raises(DataError, match=expected) as err:
        read_ratings(path)
    assert str(path) in str(err.value)


@pytest.mark.slow
def test_command_line_error_is_one_line_without_traceback(tmp_path):
    """A real process: exit status and stderr as a user sees them."""
    write_rows(tmp_path / "all_data.csv", BAD_INPUTS["likert above 5"][0](_good_rows()))
    done = subprocess.run(
        [sys.executable, "-m", "fedlgr", "data", "check", str(tmp_path), "--modality", "features"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 1
    assert "Traceback" not in done.stderr
    assert done.stderr.strip().splitlines() == [
        f"fedlgr: error: {tmp_path / 'all_data.csv'}: row 2 (line 3), column 'Vacuum cleaning': "
        "Likert value 6 outside 1..5"
    ]


def test_two_scenes_under_one_stamp_are_refused(tmp_path):
    """A bad input of issue 20 (points 8 and 9)."""
    labels = [3, 3, 3, 3, 3, 3, 3, 3]
    folder = write_dataset(
        tmp_path,
        [
            rating_row(250, True, labels, descriptor=0.5),
            rating_row(251, True, labels, descriptor=0.5),
            rating_row(250, True, [4] * 8, descriptor=0.7),  # another scene's descriptors
            rating_row(251, True, [4] * 8, descriptor=0.5),  # another rater: averaged
        ],
    )
    with pytest.raises(DataError) as caught:
        read_ratings(folder)
    message = str(caught.value)
    assert "\n" not in message
    assert message.startswith(f"{folder / 'all_data.csv'}: stamp 250, columns 'Number of people'")
    assert "and 26 more: its rows [1, 3] disagree" in message
    assert "descriptors must be the same in all its rows" in message
    assert "251" not in message.split("(")[0]
