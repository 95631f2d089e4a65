"""A minimal terminal screen model for tests of what the operator sees."""

from __future__ import annotations


def screen(raw: str) -> list[str]:
    """The lines a terminal shows after ``raw``: ``\\r`` returns to column 0, ``\\n`` starts
    a line, ``ESC[2K`` erases the line, other text overwrites from the cursor."""
    lines: list[str] = []
    line: list[str] = []
    col = 0
    i = 0
    while i < len(raw):
        if raw.startswith("\x1b[2K", i):
            line, i = [], i + 4
            continue
        ch = raw[i]
        i += 1
        if ch == "\r":
            col = 0
        elif ch == "\n":
            lines.append("".join(line).rstrip())
            line, col = [], 0
        else:
            line[col:col + 1] = [ch] if col < len(line) else [*[" "] * (col - len(line)), ch]
            col += 1
    if line:
        lines.append("".join(line).rstrip())
    return lines
