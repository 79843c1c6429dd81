import pytest

from splattwin.wording import ordinal, plural


@pytest.mark.parametrize("n, text", [(1, "1st"), (2, "2nd"), (3, "3rd"), (4, "4th"), (8, "8th"), (10, "10th"),
                                     (11, "11th"), (12, "12th"), (13, "13th"), (14, "14th"), (21, "21st"),
                                     (22, "22nd"), (23, "23rd"), (101, "101st"), (111, "111th"), (112, "112th"),
                                     (0, "0th")])
def test_ordinal(n, text):
    assert ordinal(n) == text


def test_plural():
    assert [plural(n, "held-out view") for n in (0, 1, 2)] == ["0 held-out views", "1 held-out view",
                                                               "2 held-out views"]
    assert plural(1, "child", "children") == "1 child" and plural(3, "child", "children") == "3 children"
