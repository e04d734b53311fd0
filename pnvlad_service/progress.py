"""Progress bars: tqdm's bar on a terminal, plain lines in a log.

tqdm redraws its bar with carriage returns; written to a file or a pipe (a CI log, ``2> log``,
systemd's journal) that is one endless line of frames. :class:`tqdm` here is tqdm's own class
with two changes, so that it is a drop-in for ``from tqdm import tqdm``:

- where its stream is not a terminal it writes the same figures without the bar, one line at the
  start, one every :data:`LOG_INTERVAL_S` seconds and one at the end (with ``leave``);
- ``disable=None`` (tqdm's "hide it where the stream is not a terminal") shows it, as lines
  there: a command's ``--progress`` means the same in a terminal and in a log.
"""

from __future__ import annotations

import re
import sys
from typing import Any, TextIO

from tqdm import tqdm as _tqdm

#: Seconds between two progress lines where the stream is not a terminal.
LOG_INTERVAL_S = 30.0


def is_terminal(stream: Any) -> bool:
    """Whether ``stream`` is an interactive terminal (False for a closed or odd stream)."""
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError, OSError):
        return False


class _Lines:
    """A stream for tqdm that writes each redraw (``\\r`` + frame) as a line of its own and
    drops the blank ones (its padding and the clearing of a bar that does not stay)."""

    def __init__(self, stream: TextIO) -> None:
        self.stream = stream
        self.encoding = getattr(stream, "encoding", None) or "utf-8"

    def write(self, text: str) -> None:
        for frame in re.split(r"[\r\n]", text):
            if frame.strip():
                self.stream.write(frame.rstrip() + "\n")

    def flush(self) -> None:
        self.stream.flush()


class tqdm(_tqdm):  # lower case: the name of the class it stands in for
    """``tqdm.tqdm`` (same arguments and methods) that writes plain lines off a terminal."""

    def __init__(
        self, iterable: Any = None, *args: Any, file: Any = None, disable: bool | None = False,
        **kwargs: Any,
    ) -> None:  # fmt: skip
        stream = sys.stderr if file is None else file
        self._log = not is_terminal(stream)
        if self._log:
            stream = _Lines(stream)
            # ncols 0: tqdm's figures without the bar; one line every LOG_INTERVAL_S at most.
            kwargs |= {"ncols": 0, "dynamic_ncols": False}
            kwargs |= {"mininterval": LOG_INTERVAL_S, "maxinterval": LOG_INTERVAL_S}
        super().__init__(iterable, *args, file=stream, disable=bool(disable), **kwargs)

    def set_postfix(self, ordered_dict: Any = None, refresh: bool = True, **kwargs: Any) -> None:
        """tqdm's, but in a log the postfix waits for the next line: a refresh would write one
        line an update (a training loop sets its loss every step)."""
        super().set_postfix(ordered_dict, refresh=refresh and not self._log, **kwargs)

    def set_description(self, desc: str | None = None, refresh: bool = True) -> None:
        """As :meth:`set_postfix`: in a log the description waits for the next line."""
        super().set_description(desc, refresh=refresh and not self._log)
