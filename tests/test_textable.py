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


def test_a_rule_wider_than_the_terminal_is_cut_not_wrapped_into_lines_of_dashes():
    from harness.textable import fit_text, text_table

    table = text_table(["#", "evidence"], [["1", "word " * 60]], align="ll")
    out = fit_text(table, 100).splitlines()
    assert all(len(line) <= 100 for line in out)
    rules = [line for line in out if line and set(line) <= set("- ")]
    assert len(rules) == 1 and len(rules[0]) == 100
    assert sum("word" in line for line in out) >= 3  # the long cell still wraps
