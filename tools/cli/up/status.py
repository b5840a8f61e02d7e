"""`aero up`'s status table: one row per service (state, health, restarts, message), printed
every --status-interval while the stack runs. Reads Child records; starts and stops nothing."""
from __future__ import annotations

import shutil
import textwrap

from ..topic import LEVEL_NAMES as LEVELS

MESSAGE_COL = 13 + 1 + 10 + 1 + 6 + 1 + 8 + 2


def format_table(children, width: int | None = None) -> str:
    """One row per service; the message wraps on word boundaries under its column (at most three
    lines, then "..."), so a URL or a number is never cut."""
    width = width or shutil.get_terminal_size((120, 24)).columns
    msg_width = max(30, width - MESSAGE_COL - 1)
    rows = [f"{'SERVICE':<13} {'STATE':<10} {'HEALTH':<6} {'RESTARTS':>8}  MESSAGE"]
    for c in children:
        lvl = LEVELS.get(c.health.get("level"), "-") if c.alive else "-"
        if c.alive:
            msg = c.health.get("message", "")
        elif c.last_exit is not None:
            msg = f"exit {c.last_exit}" + (f": {c.last_error}" if c.last_error else "")
        else:
            msg = ""
        lines = textwrap.wrap(msg, msg_width, break_long_words=False, break_on_hyphens=False,
                              max_lines=3, placeholder=" ...") or [""]
        rows.append(f"{c.name:<13} {c.status():<10} {lvl:<6} {c.restarts:>8}  {lines[0]}")
        rows += [" " * MESSAGE_COL + line for line in lines[1:]]
    return "\n".join(rows)

