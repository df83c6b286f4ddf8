"""Reading black-box files: JSON lines, streamed with bounded memory, whatever state they are in.

A black box (``blackbox.py``) may be cut short by a crash or a full disk (a partial last line, a
tail of zero bytes), hold lines from another version of the driver, or be hundreds of megabytes
long. ``FlightFiles`` puts the files of one flight in order (by their first record) and yields
their records one at a time, each with one time in seconds since the epoch; every file gets a
``FileInfo`` that says how many lines it had, which could not be read (a bounded sample), where
it ends and whether it ends cleanly. No ROS here.

Time base: a record carries ``t`` (wall clock) and ``mono`` (monotonic). Within one file the
time of a record is its ``mono`` plus the file's ``t - mono`` at its first record, so a wall
clock stepped by NTP during the run does not reorder anything; a record that lacks ``mono``
(a hand-made or damaged line) uses ``t``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
import json
import math
import os
import time
from typing import Any, Callable, Dict, Iterator, List, Optional, Tuple

MAX_LINE_BYTES = 1 << 20
"""A line longer than this is no record (the writer's longest lines are a few hundred bytes)."""
BAD_LINE_SAMPLES = 12
"""Unreadable lines described one by one per file; the rest are counted."""
HEAD_SCAN_LINES = 2000
"""Lines read from the start of a file to find its first timed record (to order the files)."""
CLOCK_STEP_S = 1.0
"""A wall clock that moves this far against the monotonic clock has been stepped."""
BACKWARD_LIMIT_S = 1.0
"""Records are queued from several threads, so a little disorder is normal; more is damage."""
FORWARD_LIMIT_S = 30 * 86400.0
"""A record this far after the one before it has a damaged time (a module may be unplugged
for hours with nothing recorded, not for a month)."""

Progress = Callable[[int], None]
"""Called with the number of bytes read so far, over all files."""


@dataclass
class BadLine:
    """One line that is not a record: where it is and why."""

    line: int
    offset: int
    reason: str
    excerpt: str


@dataclass
class FileInfo:
    """What reading one file found out about it."""

    path: str
    size: int
    index: int = 0
    lines: int = 0
    records: int = 0
    bad_lines: int = 0
    bad_samples: List[BadLine] = field(default_factory=list)
    untimed: int = 0
    bad_times: int = 0
    first_time: Optional[float] = None
    last_time: Optional[float] = None
    starts: int = 0
    stops: int = 0
    ended_with_stop: bool = False
    clock_offset: Optional[float] = None
    clock_steps: int = 0
    clock_step_max_s: float = 0.0
    tail: Optional[BadLine] = None
    tail_lines: int = 0
    last_good_line: int = 0
    last_good_offset: int = 0
    no_final_newline: bool = False
    error: str = ''
    done: bool = False

    @property
    def name(self) -> str:
        """Return the file name without its directory."""
        return os.path.basename(self.path)

    @property
    def truncated(self) -> bool:
        """Whether the file ends in a line that is not a complete record."""
        return self.tail is not None

    @property
    def clean_end(self) -> bool:
        """Whether the driver closed the file (a ``stop`` record) and nothing follows it."""
        return self.ended_with_stop and not self.truncated and not self.error

    def ending(self) -> str:
        """Say in one sentence how the file ends."""
        if self.error:
            return f'could not be read to its end: {self.error}'
        if self.tail is not None:
            more = f' ({self.tail_lines} unreadable lines)' if self.tail_lines > 1 else ''
            return (f'TRUNCATED: the last complete record is line {self.last_good_line} '
                    f'(byte {self.last_good_offset}); from line {self.tail.line} '
                    f'(byte {self.tail.offset}) on the file holds no complete record{more}: '
                    f'{self.tail.reason}')
        if not self.ended_with_stop:
            return (f'ends at line {self.last_good_line} without a stop record: the driver did '
                    'not close it (killed, crashed or the power went)')
        return f'ends cleanly with the stop record (line {self.last_good_line})'


def _excerpt(raw: bytes, limit: int = 60) -> str:
    body = raw.rstrip(b'\n')
    if body and body.strip(b'\x00') == b'':
        return f'{len(body)} zero bytes'
    text = body[:limit].decode('utf-8', 'backslashreplace').replace('\x00', '\\0')
    return text + ('…' if len(body) > limit else '')


def record_time(record: Dict[str, Any], offset: Optional[float]) -> Optional[float]:
    """Return a record's time on the file's time base (s since the epoch), None if it has none."""
    mono = record.get('mono')
    if offset is not None and isinstance(mono, (int, float)) and not isinstance(mono, bool) \
            and math.isfinite(mono):
        return mono + offset
    t = record.get('t')
    if isinstance(t, (int, float)) and not isinstance(t, bool) and math.isfinite(t):
        return float(t)
    return None


def _number(value: Any) -> Optional[float]:
    if isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value):
        return float(value)
    return None


def _lines(handle, start_offset: int = 0) -> Iterator[Tuple[int, bytes, bool]]:
    """Yield ``(offset, line, complete)``; an over-long line is yielded cut, never whole."""
    offset = start_offset
    while True:
        raw = handle.readline(MAX_LINE_BYTES)
        if not raw:
            return
        if raw.endswith(b'\n') or len(raw) < MAX_LINE_BYTES:
            yield offset, raw, True
            offset += len(raw)
            continue
        # Over-long: skip to the next newline in bounded reads, report it as one bad line.
        length = len(raw)
        while True:
            more = handle.readline(MAX_LINE_BYTES)
            length += len(more)
            if not more or more.endswith(b'\n'):
                break
        yield offset, raw[:80], False
        offset += length


def _parse(raw: bytes) -> Tuple[Optional[Dict[str, Any]], str]:
    try:
        value = json.loads(raw)
    except (ValueError, RecursionError) as exc:
        # ValueError covers JSONDecodeError and UnicodeDecodeError.
        if raw.strip(b'\x00\n\r ') == b'':
            return None, 'zero bytes (a crash or a full disk leaves these)'
        return None, f'not JSON ({str(exc).split(":")[0]})'
    if not isinstance(value, dict):
        return None, f'JSON {type(value).__name__}, not a record'
    return value, ''


def is_record(value: Optional[Dict[str, Any]]) -> bool:
    """Whether a parsed line is a black-box record (the writer gives each a kind and a t)."""
    return (value is not None and isinstance(value.get('kind'), str)
            and _number(value.get('t')) is not None)


def not_a_blackbox(path: str) -> str:
    """Say why ``path`` is no black-box file ('' when it holds at least one record).

    A directory, a missing path, a device, an empty file, binary data, text that is not JSON
    lines, or JSON lines none of which is a record. The whole file is read if need be (in
    bounded pieces): one record anywhere makes it a black box, however damaged the rest.
    """
    if os.path.isdir(path):
        return 'is a directory'
    if not os.path.exists(path):
        return 'no such file or directory'
    if not os.path.isfile(path):
        return 'is not a regular file'
    lines = json_lines = binary = zeros = 0
    try:
        with open(path, 'rb') as handle:
            for _, raw, complete in _lines(handle):
                lines += 1
                if not complete:
                    binary += 1
                    continue
                record, reason = _parse(raw)
                if is_record(record):
                    return ''
                if record is not None or reason.startswith('JSON '):
                    json_lines += 1
                elif raw.strip(b'\0\n') == b'':
                    zeros += 1
                elif b'\0' in raw or _binary(raw):
                    binary += 1
    except OSError as exc:
        return f'cannot be read: {exc.strerror or exc}'
    if lines == 0:
        return 'is empty: not a black-box file (it holds no record)'
    if zeros == lines:
        return ('holds only zero bytes: no record reached the disk (a crash or a full disk '
                'leaves these)')
    if binary:
        return 'is binary data, not a black-box file (it holds no record of the driver)'
    if json_lines:
        return ('holds JSON but no black-box record (each has a "kind" and a "t"): not a '
                'black-box file')
    return 'is text but not JSON lines: not a black-box file (it holds no record)'


def _binary(raw: bytes) -> bool:
    try:
        text = raw.decode('utf-8')
    except UnicodeDecodeError:
        return True
    return any(ord(c) < 32 and c not in '\t\r\n' for c in text)


def first_time(path: str) -> Optional[float]:
    """Return the time of the first timed record of a file (None if none near its start)."""
    offset = None
    try:
        with open(path, 'rb') as handle:
            for n, (_, raw, complete) in enumerate(_lines(handle)):
                if n >= HEAD_SCAN_LINES:
                    break
                record, _ = _parse(raw) if complete else (None, '')
                if record is None:
                    continue
                t, mono = _number(record.get('t')), _number(record.get('mono'))
                if offset is None and t is not None and mono is not None:
                    offset = t - mono
                when = record_time(record, offset)
                if when is not None:
                    return when
    except OSError:
        return None
    return None


class FlightFiles:
    """The black-box files of one flight, in the order of their first record."""

    def __init__(self, paths: List[str]) -> None:
        if not paths:
            raise ValueError('no black-box file given')
        infos = []
        for path in paths:
            try:
                size = os.path.getsize(path)
            except OSError as exc:
                raise FileNotFoundError(f'cannot read {path}: {exc.strerror}') from None
            infos.append((first_time(path), path, size))
        # Files without a timed record go last, in the order given.
        infos.sort(key=lambda item: (item[0] is None, item[0] or 0.0))
        self.files = [FileInfo(path=path, size=size, index=i)
                      for i, (_, path, size) in enumerate(infos)]
        self.total_bytes = sum(f.size for f in self.files)
        self.bytes_done = 0

    def records(self, progress: Optional[Progress] = None
                ) -> Iterator[Tuple[FileInfo, int, Optional[float], Dict[str, Any]]]:
        """Yield ``(file, line number, time, record)`` for every readable record, file by file."""
        for info in self.files:
            base = self.bytes_done
            for item in self._file_records(info, progress, base):
                yield item
            self.bytes_done = base + info.size
            if progress is not None:
                progress(self.bytes_done)

    def _file_records(self, info: FileInfo, progress: Optional[Progress], base: int
                      ) -> Iterator[Tuple[FileInfo, int, Optional[float], Dict[str, Any]]]:
        next_progress = time.monotonic() + 0.2
        line_no = 0
        pending_tail: Optional[BadLine] = None
        pending_count = 0
        try:
            with open(info.path, 'rb') as handle:
                for offset, raw, complete in _lines(handle):
                    line_no += 1
                    if (line_no & 0xFFF) == 0 and progress is not None:
                        now = time.monotonic()
                        if now >= next_progress:
                            next_progress = now + 0.2
                            progress(base + offset)
                    if complete:
                        record, reason = _parse(raw)
                    else:
                        record, reason = None, f'a line longer than {MAX_LINE_BYTES} bytes'
                    if record is None:
                        zeros = raw.count(b'\0')
                        if zeros and raw.strip(b'\0\n'):
                            reason = (f'{zeros} zero bytes after {len(raw) - zeros} of text (a '
                                      'crash or a full disk leaves these)')
                        if not raw.endswith(b'\n') and complete:
                            reason = f'partial last line ({len(raw)} bytes, no newline); {reason}'
                        bad = BadLine(line_no, offset, reason, _excerpt(raw))
                        info.bad_lines += 1
                        if len(info.bad_samples) < BAD_LINE_SAMPLES:
                            info.bad_samples.append(bad)
                        if pending_tail is None:
                            pending_tail = bad
                        pending_count += 1
                        continue
                    pending_tail, pending_count = None, 0
                    info.no_final_newline = not raw.endswith(b'\n')
                    info.records += 1
                    info.last_good_line, info.last_good_offset = line_no, offset
                    t, mono = _number(record.get('t')), _number(record.get('mono'))
                    if t is not None and mono is not None:
                        if info.clock_offset is None:
                            info.clock_offset = t - mono
                        else:
                            step = abs(t - mono - info.clock_offset)
                            if step > CLOCK_STEP_S and step > info.clock_step_max_s + CLOCK_STEP_S:
                                info.clock_steps += 1
                                info.clock_step_max_s = step
                    when = record_time(record, info.clock_offset)
                    if when is not None and info.last_time is not None and not (
                            -BACKWARD_LIMIT_S < when - info.last_time < FORWARD_LIMIT_S):
                        info.bad_times += 1  # placed at the time before it, not trusted
                        when = None
                    elif when is not None and info.first_time is None and not (
                            0 < when < 1e11):
                        info.bad_times += 1  # before 1970 or after year 5000: not a time
                        when = None
                    if when is None:
                        info.untimed += 1
                    else:
                        if info.first_time is None:
                            info.first_time = when
                        if info.last_time is None or when > info.last_time:
                            info.last_time = when
                    kind = record.get('kind')
                    info.ended_with_stop = kind == 'stop'
                    if kind == 'start':
                        info.starts += 1
                    elif kind == 'stop':
                        info.stops += 1
                    yield info, line_no, when, record
        except OSError as exc:
            info.error = exc.strerror or str(exc)
        info.lines = line_no
        info.tail = pending_tail
        info.tail_lines = pending_count
        info.done = True
