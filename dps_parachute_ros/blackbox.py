"""Black box: every frame, request, decision and state change of one run as JSON lines.

One file per run (``parachute-<UTC time>-<pid>.jsonl``) in a directory that is created when
missing; old files are kept. Callers on any thread only put a record on a queue, so the serial
reader never waits for the disk; one writer thread serializes, writes (buffered) and, on safety
events, flushes and fsyncs. ``sync()`` returns once everything recorded before it is on disk.
No ROS here.
"""

from __future__ import annotations

import json
import os
import queue
import threading
import time
from typing import Any, Optional

FLUSH_PERIOD_S = 1.0
"""Unsynced records reach the OS at least this often (fsync only on safety events)."""


class BlackBox:
    """A thread-safe JSON-lines recorder with explicit fsync points."""

    def __init__(self, directory: str, prefix: str = 'parachute') -> None:
        self.directory = os.path.abspath(os.path.expanduser(directory))
        os.makedirs(self.directory, exist_ok=True)
        stamp = time.strftime('%Y%m%dT%H%M%SZ', time.gmtime())
        for n in range(1000):
            suffix = f'-{n}' if n else ''
            self.path = os.path.join(self.directory,
                                     f'{prefix}-{stamp}-{os.getpid()}{suffix}.jsonl')
            try:
                # 'x': never append to (or clobber) another run's file.
                self._file = open(self.path, 'x', encoding='utf-8', buffering=1 << 16)
                break
            except FileExistsError:
                continue
        else:
            raise FileExistsError(f'no free black-box file name in {self.directory}')
        self._queue: 'queue.SimpleQueue[Any]' = queue.SimpleQueue()
        self.records = 0
        self.syncs = 0
        self.errors = 0
        self.last_error = ''
        self._closed = False
        self._thread = threading.Thread(target=self._run, name='blackbox', daemon=True)
        self._thread.start()

    def record(self, kind: str, **fields: Any) -> None:
        """Queue one record; ``t`` (wall, s) and ``mono`` (monotonic, s) are added here."""
        if self._closed:
            return
        fields['t'] = time.time()
        fields['mono'] = time.monotonic()
        fields['kind'] = kind
        self._queue.put(fields)

    def frame(self, direction: str, data: bytes, **fields: Any) -> None:
        """Record bytes on the wire (``direction`` 'tx' or 'rx') as hex."""
        self.record('frame', dir=direction, hex=data.hex(' '), **fields)

    def sync(self, timeout: Optional[float] = 2.0) -> bool:
        """Flush and fsync everything recorded so far.

        With ``timeout`` None, return at once (the sync happens in the background); else wait
        up to ``timeout`` s and return whether the data is on disk.
        """
        if self._closed:
            return False
        done = threading.Event()
        self._queue.put(done)
        if timeout is None:
            return True
        return done.wait(timeout)

    def close(self) -> None:
        """Sync and close the file; later records are ignored."""
        if self._closed:
            return
        self.sync(2.0)
        self._closed = True
        self._queue.put(None)
        self._thread.join(2.0)

    def _run(self) -> None:
        last_flush = time.monotonic()
        while True:
            try:
                item = self._queue.get(timeout=FLUSH_PERIOD_S)
            except queue.Empty:
                item = False
            try:
                if item is None:
                    self._file.flush()
                    os.fsync(self._file.fileno())
                    self._file.close()
                    return
                if isinstance(item, threading.Event):
                    self._file.flush()
                    os.fsync(self._file.fileno())
                    self.syncs += 1
                    item.set()
                    last_flush = time.monotonic()
                    continue
                if item is not False:
                    self._file.write(json.dumps(item, default=str, separators=(',', ':')))
                    self._file.write('\n')
                    self.records += 1
                now = time.monotonic()
                if now - last_flush >= FLUSH_PERIOD_S:
                    self._file.flush()
                    last_flush = now
            except (OSError, ValueError) as exc:  # a full disk must not stop the driver
                self.errors += 1
                self.last_error = str(exc)
                if isinstance(item, threading.Event):
                    item.set()
