"""Black box: every frame, request, decision and state change of one run as JSON lines.

One file per run (``parachute-<UTC time>-<pid>.jsonl``) in a directory that is created when
missing. Callers on any thread only append a record to a queue (a frame as its raw bytes), so
neither the serial reader nor a deploy ever waits for the disk or for JSON; one writer thread
serializes, writes in batches and, on safety events, flushes and fsyncs. The writer is woken by
``sync()`` and ``close()``, by a queue that grows long, and otherwise once per
``FLUSH_PERIOD_S``: not once per record (every thread wake-up costs CPU). ``sync()`` returns
whether everything recorded before it reached the disk.

A logging problem never takes the parachute away (README, "Safety model of deploy"): the
constructor never raises, a directory that cannot be used, a full disk or an I/O error only
make records lost. Lost records are counted, the problem is reported through ``on_problem``
(the driver logs it, throttled, and keeps its diagnostics ERROR) and writing is retried, so the
box recovers by itself when the disk does; the file then says so itself, in a ``blackbox``
record ``{"event": "writing again", "error", "failed_at", "lost", "lost_in_outage"}`` (D18).
``max_bytes`` bounds the directory: the oldest runs are removed first, never a run being
written, by this instance or any other, and runs that hold a deployment only once no routine
run is left (decision D14 in ``docs/protocols.md``):

- the writer holds an exclusive ``flock`` on its open file for the whole run; a pruner (every
  instance prunes the same directory: they all default to it) removes a run only while it holds
  that lock itself, taken without waiting, so a run whose writer is alive is never removed, and
  a run whose writer died (the kernel drops the lock) can be. ``flock`` works between processes
  and between two writers of one process (each opens its own file); on a file system without
  it (some network mounts) nothing is removed.
- a run that holds a deployment (a trigger event, a deploy frame sent, a trigger request
  confirmed, the module reporting TRIGGERED) gets a marker beside it, ``<run>.jsonl.deployed``,
  written by the writer when the first such record is written: the pruner sees it in the
  same directory listing, without opening any run.
- a file removed from under the writer anyway (by hand, by an older driver, a cleaner) is
  noticed at the next flush or ``sync()``: the problem is reported (sticky for the run:
  ``status().file_removed``, diagnostics ERROR, preflight FAIL), its records are counted lost
  and a new file is started, beginning with the run's first record (the ``start`` record) and a
  ``blackbox`` record ``{"event": "file removed", "path", "lost"}``.

No ROS here.
"""

from __future__ import annotations

from dataclasses import dataclass
from collections import deque
import errno
import fcntl
import json
import os
import threading
import time
from typing import Any, Callable, List, Optional

FLUSH_PERIOD_S = 1.0
"""Unsynced records reach the OS at least this often (fsync only on safety events)."""
BATCH_BYTES = 1 << 16
"""A batch this large is written at once."""
REOPEN_PERIOD_S = 5.0
"""A black-box file that could not be created is tried again this often."""
BUDGET_CHECK_BYTES = 1 << 18
"""The size bound is checked again after this much was written (and at start)."""
WAKE_RECORDS = 512
"""The writer is woken before its period when this many records wait."""
DEPLOYED_SUFFIX = '.deployed'
"""Marker beside a run that holds a deployment: ``<run>.jsonl.deployed`` (pruned last)."""


@dataclass(frozen=True)
class BlackBoxStatus:
    """What the diagnostics show about the black box."""

    path: str
    directory: str
    writing: bool               # the last write (and fsync) succeeded
    error: str                  # the last write error, '' when writing
    open_failed: bool           # no file could be created in the directory (yet)
    records: int                # records written
    lost: int                   # records that never reached the file
    run_bytes: int              # size of this run's file
    total_bytes: int            # size of every run in the directory, at the last check
    max_bytes: Optional[int]
    removed_runs: int           # old runs removed to stay within max_bytes
    over_budget: bool           # this run alone is larger than max_bytes
    file_removed: str = ''      # sticky: an earlier file of this run that was removed under us


class _Sync:
    __slots__ = ('event', 'ok')

    def __init__(self) -> None:
        self.event = threading.Event()
        self.ok = False


_CLOSE = object()
_TICK = object()


class BlackBox:
    """A thread-safe JSON-lines recorder with explicit fsync points that never raises."""

    def __init__(self, directory: str, prefix: str = 'parachute',
                 max_bytes: Optional[int] = None, path: Optional[str] = None,
                 on_problem: Optional[Callable[[str, bool], None]] = None,
                 reopen_period_s: float = REOPEN_PERIOD_S) -> None:
        """Open this run's file (or `path`, for tests); `on_problem(text, ok)` hears changes."""
        self.reopen_period_s = reopen_period_s
        self.directory = os.path.abspath(os.path.expanduser(directory))
        self.prefix = prefix
        self.on_problem = on_problem
        self._lock = threading.Lock()   # guards the counters and status fields below
        self._max_bytes = max_bytes
        self._fixed_path = path
        self.path = path or ''
        self._fd: Optional[int] = None
        self._records = 0
        self._lost = 0
        self._run_bytes = 0
        self._total_bytes = 0
        self._removed = 0
        self._error = ''
        self._open_failed = False
        self._writing = True
        self._failed_at = 0.0           # wall time the present outage began
        self._lost_before = 0           # records lost before it
        self.syncs = 0
        self._closed = False
        self._buf: List[bytes] = []
        self._buf_bytes = 0
        self._next_open = 0.0
        self._since_check = 0
        self._first_line = b''          # the run's first record, the head of a replacement file
        self._deployed = False          # this run holds a deployment (its marker is written)
        self._file_removed = ''         # why an earlier file of this run is gone ('' if none)
        self._lost_with_files = 0       # records written to files removed under the writer
        self._gone: set = set()         # paths of this run's files removed under the writer
        self._open()
        self._enforce_budget()
        # Records (dicts), frames (_Frame tuples) and markers, in order; deque appends and pops
        # are atomic, so producers take no lock.
        self._queue: 'deque[Any]' = deque()
        self._wake = threading.Event()
        self._thread = threading.Thread(target=self._run, name='blackbox', daemon=True)
        self._thread.start()

    # -- API (any thread) -------------------------------------------------------------------

    @property
    def records(self) -> int:
        """Records written so far."""
        with self._lock:
            return self._records

    @property
    def last_error(self) -> str:
        """The last write error, '' while writing works."""
        with self._lock:
            return self._error

    def set_max_bytes(self, max_bytes: Optional[int]) -> None:
        """Change the size bound; it is applied by the writer thread at once."""
        with self._lock:
            self._max_bytes = max_bytes
            self._since_check = BUDGET_CHECK_BYTES
        if not self._closed:
            self._put(_TICK, wake=True)

    def status(self) -> BlackBoxStatus:
        """Return the present state, for diagnostics and the preflight check."""
        with self._lock:
            max_bytes = self._max_bytes
            return BlackBoxStatus(
                path=self.path, directory=self.directory, writing=self._writing,
                error=self._error, open_failed=self._open_failed, records=self._records,
                lost=self._lost, run_bytes=self._run_bytes, total_bytes=self._total_bytes,
                max_bytes=max_bytes, removed_runs=self._removed,
                over_budget=max_bytes is not None and self._run_bytes > max_bytes,
                file_removed=self._file_removed)

    def record(self, kind: str, **fields: Any) -> None:
        """Queue one record; ``t`` (wall, s) and ``mono`` (monotonic, s) are added here."""
        if self._closed:
            return
        fields['t'] = time.time()
        fields['mono'] = time.monotonic()
        fields['kind'] = kind
        self._put(fields)

    def frame(self, direction: str, data: bytes, **fields: Any) -> None:
        """Record bytes on the wire (``direction`` 'tx' or 'rx') as hex (made by the writer)."""
        if self._closed:
            return
        self._put((direction, bytes(data), fields, time.time(), time.monotonic()))

    def _put(self, item: Any, wake: bool = False) -> None:
        queue = self._queue
        queue.append(item)
        if wake or len(queue) >= WAKE_RECORDS:
            self._wake.set()

    def sync(self, timeout: Optional[float] = 2.0) -> bool:
        """Flush and fsync everything recorded so far.

        With ``timeout`` None, return at once (the sync happens in the background); else wait
        up to ``timeout`` s and return whether the data is on disk (False when a write or the
        fsync failed, or the time ran out).
        """
        if self._closed:
            return False
        item = _Sync()
        self._put(item, wake=True)
        if timeout is None:
            return True
        return item.event.wait(timeout) and item.ok

    def close(self, timeout: float = 2.0) -> None:
        """Sync and close the file; later records are ignored."""
        if self._closed:
            return
        self._closed = True
        self._put(_CLOSE, wake=True)
        self._thread.join(timeout)

    # -- writer thread ------------------------------------------------------------------------

    def _run(self) -> None:
        last_flush = time.monotonic()
        queue, wake = self._queue, self._wake
        while True:
            wake.wait(min(max(last_flush + FLUSH_PERIOD_S - time.monotonic(), 0.01),
                          FLUSH_PERIOD_S))
            wake.clear()  # before taking the items: a later append sets it again
            while queue:
                item = queue.popleft()
                try:
                    if item is _CLOSE:
                        self._flush()
                        self._fsync()
                        if self._fd is not None:
                            os.close(self._fd)
                            self._fd = None
                        return
                    if isinstance(item, _Sync):
                        self._check_file()
                        item.ok = self._flush() and self._fsync() and self.status().writing
                        item.event.set()
                        last_flush = time.monotonic()
                        continue
                    if item is not _TICK:
                        self._serialize(item)
                    if self._buf_bytes >= BATCH_BYTES:
                        self._flush()
                        last_flush = time.monotonic()
                except Exception as exc:  # noqa: BLE001 - the recorder must outlive any bug
                    self._failed(f'internal error: {exc!r}', 0)
                    if isinstance(item, _Sync):
                        item.event.set()
            try:
                now = time.monotonic()
                if now - last_flush >= FLUSH_PERIOD_S - 0.005:  # the wait's own jitter
                    self._check_file()
                    self._flush()
                    last_flush = now
                with self._lock:
                    due = self._since_check >= BUDGET_CHECK_BYTES
                if due:
                    self._enforce_budget()
            except Exception as exc:  # noqa: BLE001 - the recorder must outlive any bug
                self._failed(f'internal error: {exc!r}', 0)

    def _serialize(self, item: Any) -> None:
        if isinstance(item, tuple):  # a frame: (dir, bytes, fields, t, mono)
            direction, data, extra, t, mono = item
            item = {'dir': direction, 'hex': data.hex(' '), **extra, 't': t, 'mono': mono,
                    'kind': 'frame'}
        line = (json.dumps(item, default=str, separators=(',', ':')) + '\n').encode()
        if not self._first_line:
            self._first_line = line
        self._buf.append(line)
        self._buf_bytes += len(line)
        if not self._deployed and holds_deployment(item):
            self._mark_deployed()

    def _open(self) -> bool:
        """Create this run's file (or open the fixed path); False when it cannot be."""
        self._next_open = time.monotonic() + self.reopen_period_s
        try:
            if self._fixed_path:
                self._fd = os.open(self._fixed_path, os.O_WRONLY | os.O_CREAT | os.O_APPEND,
                                   0o644)
            else:
                os.makedirs(self.directory, exist_ok=True)
                self._fd = self._create_run_file()
                if self._deployed:
                    self._deployed = False
                    self._mark_deployed()
        except OSError as exc:
            with self._lock:
                self._open_failed = True
            where = self._fixed_path or self.directory
            # The reason first: a report or diagnostic that clips a long path keeps it.
            self._failed(f'cannot create a file ({exc.strerror or exc}) in {where!r}', 0)
            return False
        with self._lock:
            self._open_failed = False
        return True

    def _create_run_file(self) -> int:
        stamp = time.strftime('%Y%m%dT%H%M%SZ', time.gmtime())
        for n in range(1000):
            suffix = f'-{n}' if n else ''
            name = f'{self.prefix}-{stamp}-{os.getpid()}{suffix}.jsonl'
            path = os.path.join(self.directory, name)
            if path in self._gone:
                continue  # a new name: the removed file's would say it is still there
            try:
                # O_EXCL: never append to (or clobber) another run's file.
                fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
            except FileExistsError:
                continue
            try:
                # Held for the whole run (released when the fd closes or the process dies):
                # every pruner leaves a locked run alone.
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError:
                pass  # no flock here (or a pruner's lock this instant): pruners keep off too
            self.path = path
            return fd
        raise FileExistsError(17, 'no free black-box file name', self.directory)

    def _flush(self) -> bool:
        """Write the batch; on failure its records are counted lost. Returns success."""
        batch, count = b''.join(self._buf), len(self._buf)
        self._buf, self._buf_bytes = [], 0
        if self._fd is None and (time.monotonic() < self._next_open or not self._open()):
            if count:
                self._failed(self.last_error, count)
            return False
        view = memoryview(batch)
        try:
            while view:
                written = os.write(self._fd, view)
                view = view[written:]
        except OSError as exc:
            self._failed(exc.strerror or str(exc), count)
            return False
        with self._lock:
            self._records += count
            self._run_bytes += len(batch)
            self._since_check += len(batch)
        if count:
            self._recovered()
        return True

    def _fsync(self) -> bool:
        if self._fd is None:
            return False
        try:
            os.fsync(self._fd)
        except OSError as exc:
            if exc.errno != errno.EINVAL:  # EINVAL: a special file, nothing to sync
                self._failed(f'fsync failed: {exc.strerror or exc}', 0)
                return False
        self.syncs += 1
        return True

    def _failed(self, error: str, lost: int) -> None:
        with self._lock:
            if self._writing:
                self._failed_at = time.time()
                self._lost_before = self._lost
            self._lost += lost
            first = self._writing or error != self._error
            self._writing = False
            self._error = error
            text = f'cannot write: {error}; {self._lost} records lost'
        if self.on_problem is not None and (first or lost):
            self.on_problem(text, False)

    def _recovered(self) -> None:
        with self._lock:
            if self._writing:
                return
            self._writing = True
            error, self._error = self._error, ''
            lost, outage = self._lost, self._lost - self._lost_before
            failed_at = self._failed_at
            text = f'writing again to {self.path}; {self._lost} records were lost'
        # The outage's own records are gone: this one tells the file what happened (D18).
        self.record('blackbox', event='writing again', error=error, failed_at=failed_at,
                    lost=lost, lost_in_outage=outage)
        if self.on_problem is not None:
            self.on_problem(text, True)

    def _check_file(self) -> None:
        """Notice this run's file removed (or replaced) under the writer; start a new one."""
        if self._fd is None or self._fixed_path:
            return
        try:
            mine = os.fstat(self._fd)
            there = os.stat(self.path)
            gone = mine.st_nlink == 0 or \
                (there.st_dev, there.st_ino) != (mine.st_dev, mine.st_ino)
        except FileNotFoundError:
            gone = True
        except OSError:
            return  # cannot tell (the directory is unreadable): the writes will say
        if not gone:
            return
        old = self.path
        self._gone.add(old)
        with self._lock:
            lost = self._records - self._lost_with_files
            self._lost_with_files = self._records
            self._lost += lost
            self._run_bytes = 0
            self._file_removed = (f'this run\'s file {old} was removed while it was written '
                                  f'(by hand, a cleaner or an older driver): {lost} records '
                                  'lost with it')
            problem = self._file_removed
        try:
            os.close(self._fd)
        except OSError:
            pass
        self._fd = None
        # The new file begins as the run did (its start record) and says what became of the
        # old one; the records not yet written follow.
        now = time.time()
        note = {'event': 'file removed', 'path': old, 'lost': lost, 't': now,
                'mono': time.monotonic(), 'kind': 'blackbox'}
        head = [self._first_line] if self._first_line else []
        head.append((json.dumps(note, separators=(',', ':')) + '\n').encode())
        self._buf[:0] = head
        self._buf_bytes += sum(len(line) for line in head)
        if self.on_problem is not None:
            self.on_problem(problem, False)
        self._open()  # on failure the next flush counts the batch lost and retries later

    def _mark_deployed(self) -> None:
        """Write the marker that makes pruners keep this run until no routine run is left."""
        self._deployed = True
        if self._fixed_path or not self.path:
            return
        try:
            os.close(os.open(self.path + DEPLOYED_SUFFIX, os.O_WRONLY | os.O_CREAT, 0o644))
        except OSError:
            pass  # then it is pruned as a routine run: the run itself is still written

    def _enforce_budget(self) -> None:
        """Remove the oldest runs until the directory fits in max_bytes.

        Never a run being written (its writer's lock is held: this one's or another
        instance's); runs without a deployment first, oldest first, then those with one.
        """
        with self._lock:
            self._since_check = 0
            max_bytes = self._max_bytes
        if self._fixed_path:
            return
        try:
            names = set(os.listdir(self.directory))
        except OSError:
            return
        runs = []
        for name in names:
            if name.startswith(self.prefix + '-') and name.endswith('.jsonl'):
                path = os.path.join(self.directory, name)
                try:
                    st = os.stat(path)
                except OSError:
                    continue  # removed meanwhile
                runs.append((name + DEPLOYED_SUFFIX in names, st.st_mtime, path, st.st_size))
            elif name.endswith('.jsonl' + DEPLOYED_SUFFIX) and name[:-len(DEPLOYED_SUFFIX)] \
                    not in names and name.startswith(self.prefix + '-'):
                _unlink(os.path.join(self.directory, name))  # its run is gone
        total = sum(size for *_, size in runs)
        removed = 0
        if max_bytes is not None:
            for deployed, _, path, size in sorted(runs):
                if total <= max_bytes:
                    break
                if path == self.path or not _remove_unless_written(path):
                    continue
                if deployed:
                    _unlink(path + DEPLOYED_SUFFIX)
                total -= size
                removed += 1
        with self._lock:
            self._total_bytes = total
            self._removed += removed


def holds_deployment(record: Any) -> bool:
    """Whether a record is evidence of a deployment (its run is pruned last)."""
    if not isinstance(record, dict):
        return False
    kind = record.get('kind')
    if kind == 'trigger_event':
        return True
    if kind == 'state':
        return record.get('triggered') is True
    if kind == 'decision':
        what = record.get('what')
        return what == 'deploy: sending the deploy frame' or (
            what == 'trigger request' and record.get('decision') == 'confirmed')
    return False


def _remove_unless_written(path: str) -> bool:
    """Remove a run unless a writer holds its lock; return whether it was removed."""
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return False
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            return False  # being written (or no flock here: then nothing is removed)
        # Removed while the lock is held: its writer cannot have started meanwhile.
        return _unlink(path)
    finally:
        os.close(fd)


def _unlink(path: str) -> bool:
    try:
        os.unlink(path)
    except OSError:
        return False
    return True
