import pytest

from harness.textable import text_table


def test_columns_line_up_first_left_rest_right():
    text = text_table(["name", "n"], [["a", 1], ["longer", 1234]])
    assert text.splitlines() == ["name       n", "------  ----", "a          1", "longer  1234"]


def test_explicit_alignment_and_its_length_is_checked():
    assert text_table(["a", "b"], [["x", "yy"]], align="ll").splitlines()[2] == "x  yy"
    with pytest.raises(ValueError, match="3 columns"):
        text_table(["a", "b", "c"], [], align="lr")


def test_no_rows_gives_header_and_rule():
    assert text_table(["col", "x"], []) == "col  x\n---  -"
