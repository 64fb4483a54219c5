"""Small helpers for what the station and the report say: counts with the right plural, and signed
numbers that never read "-0.00"."""

from __future__ import annotations


def plural(n: int, word: str, many: str | None = None) -> str:
    """'1 capture', '2 captures' ('many' for an irregular plural)."""
    return f"{n} {word if n == 1 else (many or word + 's')}"


def signed(value: float, digits: int = 2) -> str:
    """'+1.25', '-0.40', and '+0.00' for a change that rounds to nothing (never '-0.00')."""
    text = f"{value:+.{digits}f}"
    return "+" + text[1:] if float(text) == 0.0 else text
