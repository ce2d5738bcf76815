"""Text progress for a sweep: its per-scenario events as lines (a notebook's ``print``).

The sweep's ``progress`` callback receives a dict per committed scenario (the command draws
its bar from them); every other stage's receives a line of text. :func:`progress_lines`
turns the one into the other (review BW, F5: ``progress=print`` printed raw dicts).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

__all__ = ["progress_lines"]


def progress_lines(
    write: Callable[[str], Any], *, every: int | None = None
) -> Callable[[dict], None]:
    """A sweep ``progress`` callback that writes lines of text.

    Parameters
    ----------
    write : callable
        Called with each line (``print``, a logger's ``info``).
    every : int, optional
        Write every ``every``-th solved scenario (a failed one and the last always); by
        default about every 5 % of the scenarios pending at the start.

    Returns
    -------
    callable
        To pass as ``progress`` to :func:`calib.gravity_sweep`.

    Examples
    --------
    >>> lines = []
    >>> cb = progress_lines(lines.append, every=2)
    >>> cb({"start": True, "done": 0, "total": 3})
    >>> for k in (1, 2, 3):
    ...     cb({"done": k, "total": 3, "index": k, "ok": True, "newton_iterations": 4,
    ...         "wall_s": 0.5, "worker": "w", "message": ""})
    >>> lines
    ['sweep: 3 scenarios to solve', '2/3: scenario 2 solved, 4 Newton iterations, 0.5 s', \
'3/3: scenario 3 solved, 4 Newton iterations, 0.5 s']
    """
    if every is not None and every < 1:
        raise ValueError(f"every must be a positive number of scenarios, got {every!r}")
    step = [every or 1]

    def progress(ev: dict) -> None:
        if ev.get("start"):
            step[0] = every or max(1, round(ev["total"] / 20))
            write(f"sweep: {ev['total']} scenarios to solve")
            return
        done, total = ev["done"], ev["total"]
        if not ev["ok"]:
            write(f"{done}/{total}: scenario {ev['index']} FAILED: {ev.get('message', '')}")
        elif done % step[0] == 0 or done == total:
            write(
                f"{done}/{total}: scenario {ev['index']} solved, "
                f"{ev.get('newton_iterations')} Newton iterations, {ev.get('wall_s', 0.0):.1f} s"
            )

    return progress
