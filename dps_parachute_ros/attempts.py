"""Deploy frames without a successful acknowledgement, kept across runs of the driver (P11, D6).

The module counts unsuccessful attempts until its next power-up; three in a row put it into
protection. The driver stops at two, and a respawned driver must not start again from zero:
the count and the module's boot count it belongs to are written to a small JSON file beside the
black box (``parachute-attempts-<port>.json``; the black box prunes only its ``.jsonl`` runs)
before each deploy frame leaves and whenever the count changes. A new run takes it back when it
reads the same boot count from the module (the same power-up). Written with a rename, not
fsynced: it survives a crash of the driver, which is what it is for.
"""

from __future__ import annotations

from dataclasses import dataclass
import json
import os
import re
from typing import Optional


@dataclass(frozen=True)
class Attempts:
    """Unsuccessful deploy frames in one power-up of the module at one port."""

    port: str
    boot_count: Optional[int]
    """None: that run never read it (all its frames were sent since the last read, and count)."""
    failed: int
    unacked: int
    since_read: int = 0
    """Of them, sent since the boot count was last read: they may have gone to a later boot."""


class AttemptsFile:
    """The file of one port's count; errors are returned as text, never raised."""

    def __init__(self, directory: str, port: str) -> None:
        self.port = port
        slug = re.sub(r'[^A-Za-z0-9]+', '_', port).strip('_') or 'port'
        self.path = os.path.join(os.path.expanduser(directory),
                                 f'parachute-attempts-{slug}.json')

    def save(self, boot_count: Optional[int], failed: int, unacked: int,
             since_read: int = 0) -> str:
        """Write the count; return '' or what went wrong.

        No boot count (never read): kept all the same. A frame of this run may have gone to the
        power-up the next run finds (P11); it counts them as sent since the last read.
        """
        data = dict(port=self.port, boot_count=boot_count, failed=failed, unacked=unacked,
                    since_read=since_read)
        tmp = f'{self.path}.{os.getpid()}.tmp'
        try:
            os.makedirs(os.path.dirname(self.path), exist_ok=True)
            with open(tmp, 'w') as out:
                json.dump(data, out)
            os.replace(tmp, self.path)
        except OSError as exc:
            return f'cannot write {self.path}: {exc.strerror or exc}'
        return ''

    def load(self) -> Optional[Attempts]:
        """Return the count written by an earlier run for this port, or None."""
        try:
            with open(self.path) as src:
                data = json.load(src)
            boot = data['boot_count']
            attempts = Attempts(str(data['port']), None if boot is None else int(boot),
                                int(data['failed']), int(data['unacked']),
                                int(data.get('since_read', 0)))
        except (OSError, ValueError, KeyError, TypeError):
            return None
        return attempts if attempts.port == self.port else None
