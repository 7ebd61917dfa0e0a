"""How wide the command-line tools' rich output is when it goes to a file or a pipe.

On a terminal rich fits tables and lines to the window. Piped or logged, it knows no
window and assumes 80 columns, which breaks progress lines mid-list and cuts table
cells with an ellipsis (a denial reason loses its end). :func:`for_logs` makes a console
that is not a terminal wide and stops it wrapping lines: a log keeps whole lines.
"""

from __future__ import annotations

from rich.console import Console

#: wide enough for every table the tools print (a table is only as wide as its cells)
LOG_WIDTH = 240


def for_logs(console: Console) -> Console:
    """``console``, wide and not wrapping when it writes to no terminal; as it was on a
    terminal. ``$COLUMNS`` is not asked: a terminal's width exported into a pipe's
    environment (pytest exports 80) is no log's."""
    if console.is_terminal:
        return console
    console.width = LOG_WIDTH
    console.soft_wrap = True
    return console


__all__ = ["LOG_WIDTH", "for_logs"]
