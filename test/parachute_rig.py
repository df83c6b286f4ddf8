"""What the parachute tests share: the host frames a virtual module received, the black box."""

from __future__ import annotations

import json
from pathlib import Path
import threading
from typing import List, Optional

from dps_parachute_ros import protocol as p


class Wire:
    """Every host frame the virtual module received, with its time (a tap on the runner)."""

    def __init__(self, runner, on_frame=None) -> None:
        self.frames: list = []
        self._lock = threading.Lock()
        self._decoder = p.StreamDecoder('from_host')
        self._on_frame = on_frame
        runner.add_tap(self._tap)

    def _tap(self, direction: str, data: bytes, t: float) -> None:
        if direction == 'rx':
            for frame in self._decoder.feed(data):
                with self._lock:
                    self.frames.append((t, frame.raw))
                if self._on_frame is not None:
                    self._on_frame(frame.raw)

    def mark(self) -> int:
        """Return a position to look from (`since`)."""
        with self._lock:
            return len(self.frames)

    def since(self, mark: int, code: Optional[int] = None) -> List[bytes]:
        """Host frames received since `mark`, only those of command `code` if given."""
        with self._lock:
            return [raw for _, raw in self.frames[mark:] if code is None or raw[2] == code]


def blackbox_records(directory: Path, pattern: str = 'parachute-*.jsonl') -> List[dict]:
    """Every complete record of the black-box files in `directory`, oldest file first."""
    records = []
    for path in sorted(Path(directory).glob(pattern)):
        for line in path.read_text().splitlines():
            try:
                records.append(json.loads(line))
            except ValueError:
                pass  # a line cut short by a kill
    return records
