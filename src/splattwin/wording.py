"""Small helpers for the words of messages: English ordinals and plurals."""

from __future__ import annotations


def ordinal(n: int) -> str:
    """`n` as an English ordinal: 1st, 2nd, 3rd, 4th, ... 11th, 12th, 13th (teens take -th), 21st, 22nd, 101st."""
    n = int(n)
    if abs(n) % 100 in (11, 12, 13):
        return f"{n}th"
    return f"{n}{ {1: 'st', 2: 'nd', 3: 'rd'}.get(abs(n) % 10, 'th')}"


def plural(n: int, noun: str, many: str | None = None) -> str:
    """"1 view", "0 views", "2 views" (many: the plural when it is not noun + "s")."""
    return f"{n} {noun if n == 1 else (many or noun + 's')}"
