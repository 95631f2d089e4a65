"""A minimal terminal screen model for tests of what the operator sees."""

from __future__ import annotations

import re

#: a control sequence (ESC [ parameters final byte): SGR colours and resets (``ESC[0m``, written
#: by colorama's exit handler where a library imports it), cursor moves, erases
_CSI = re.compile(r"\x1b\[([0-9;?]*)([@-~])")


def screen(raw: str) -> list[str]:
    """The lines a terminal shows after ``raw``: ``\\r`` returns to column 0, ``\\n`` starts
    a line, ``ESC[2K`` erases the line, other control sequences show nothing (colours: a
    terminal draws none of their bytes), other text overwrites from the cursor."""
    lines: list[str] = []
    line: list[str] = []
    col = 0
    i = 0
    while i < len(raw):
        csi = _CSI.match(raw, i) if raw[i] == "\x1b" else None
        if csi is not None:
            if csi.group(2) == "K" and csi.group(1) == "2":
                line = []
            i = csi.end()
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
