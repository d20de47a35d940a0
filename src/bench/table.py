"""One line of a benchmark's fixed-width result table."""

from __future__ import annotations

from collections.abc import Sequence


def format_line(cells: Sequence[str], widths: Sequence[int]) -> str:
    """Name left-aligned, numbers right-aligned, the note last and unpadded."""
    name, *numbers, note = cells
    padded = [name.ljust(widths[0])] + [c.rjust(w) for c, w in zip(numbers, widths[1:-1], strict=True)]
    return "  ".join([*padded, note]).rstrip()
