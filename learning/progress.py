"""Progress output: a tqdm bar on a terminal, plain lines in a log file.

tqdm redraws its bar with carriage returns; written to a file or a pipe (``hil demo >
demo.log``, a CI log) that is one ever-growing line of redraws (a 25 KB ``demo.log``).
:func:`progress` picks by ``file.isatty()``: tqdm when a person watches, otherwise
:class:`LineProgress`, which writes one line per 10 % of the work (and the last one).
"""

from __future__ import annotations

import sys
import time
from collections.abc import Iterable, Iterator
from typing import IO, Any


class LineProgress:
    """tqdm's small interface (iterate, ``update``, ``set_postfix``, ``close``) as plain lines.

    One line per ``every_frac`` of ``total`` (or per ``every_n`` items when the total is
    unknown), e.g. ``fit: 20/40 (50%) 3.2 s train_loss=0.0123``.
    """

    def __init__(self, iterable: Iterable[Any] | None = None, *, total: int | None = None, desc: str = "",
                 file: IO[str] | None = None, every_frac: float = 0.1, every_n: int = 100):
        self.iterable = iterable
        if total is None and iterable is not None and hasattr(iterable, "__len__"):
            total = len(iterable)  # type: ignore[arg-type]
        self.total = total
        self.desc = desc
        self.file = file if file is not None else sys.stderr
        self.n = 0
        self._step = max(1, round(total * every_frac)) if total else every_n
        self._next = self._step
        self._postfix = ""
        self._t0 = time.monotonic()
        self._closed = False
        self._last_written = 0

    def __iter__(self) -> Iterator[Any]:
        assert self.iterable is not None
        try:
            for x in self.iterable:
                yield x
                self.update(1)
        finally:
            self.close()

    def __enter__(self) -> LineProgress:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def update(self, n: int = 1) -> None:
        self.n += n
        if self.n >= self._next:
            self._write()
            while self._next <= self.n:
                self._next += self._step

    def set_postfix(self, values: dict[str, Any] | None = None, **kw: Any) -> None:
        items = {**(values or {}), **kw}
        self._postfix = " ".join(f"{k}={v}" for k, v in items.items())

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        if self.n != self._last_written and self.n > 0:
            self._write()

    def _write(self) -> None:
        self._last_written = self.n
        of = f"/{self.total} ({100 * self.n / self.total:.0f}%)" if self.total else ""
        tail = f" {self._postfix}" if self._postfix else ""
        self.file.write(f"{self.desc}: {self.n}{of} {time.monotonic() - self._t0:.1f} s{tail}\n")
        self.file.flush()


def progress(iterable: Iterable[Any] | None = None, *, total: int | None = None, desc: str = "",
             file: IO[str] | None = None) -> Any:
    """A tqdm bar when ``file`` (default stderr) is a terminal, else :class:`LineProgress`."""
    file = file if file is not None else sys.stderr
    isatty = getattr(file, "isatty", None)
    if isatty is not None and isatty():
        from tqdm import tqdm

        return tqdm(iterable, total=total, desc=desc, file=file, leave=False)
    return LineProgress(iterable, total=total, desc=desc, file=file)
