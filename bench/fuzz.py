"""Fuzz the streaming decoders with random and mutated frames between valid ones.

For each decoder a stream is built of segments: valid frames (the ground truth), random
"frames" (random bytes of frame length, half of them starting with a real header) and mutated
valid frames (bit flips, replaced, dropped or inserted bytes, truncation, repeated headers).
The stream is fed in random chunks of 1..300 bytes; then padding and ``flush()`` settle the
tail. Figures:

- ``exceptions``: calls of ``feed``/``flush`` that raised (must be 0).
- ``recovered``: valid frames delivered byte for byte at their own offset, over the valid
  frames that no spurious frame overlaps. A spurious frame is one the decoder found in noise
  (noise can carry a frame with a correct checksum by chance); a valid frame it overlaps is
  "overlapped by noise" and counted separately. Must be 100 %.
"""

from __future__ import annotations

import random
import time
from typing import Callable, Dict, List, Tuple

from bench.decoders import dps_frames, handset_frames, originman_frames, servo_frames


def _dps_host_frames(rng: random.Random, count: int) -> List[bytes]:
    from dps_parachute_ros import protocol as p
    codes = sorted(p.HOST_CODES)
    return [p.host_frame(rng.choice(codes), rng.choice((p.CTRL_SET, p.CTRL_QUERY)),
                         rng.randrange(256)) for _ in range(count)]


def _servo_requests(rng: random.Random, count: int) -> List[bytes]:
    from desheng_servo_ros import protocol as sp
    out = []
    for _ in range(count):
        r = rng.random()
        sid = rng.randrange(1, 13)
        if r < 0.6:
            out.append(sp.encode_read(sid, 0x38, 2))
        elif r < 0.7:
            out.append(sp.encode_ping(sid))
        elif r < 0.85:
            out.append(sp.encode_write(sid, 0x28, bytes((rng.randrange(2),))))
        else:
            targets = [(i, rng.randrange(4096), rng.randrange(1000))
                       for i in range(1, rng.randrange(2, 13))]
            out.append(sp.encode_sync_write_positions(targets))
    return out


class _HandsetFuzzDecoder:
    """The handset decoder, returning only the sound frames it takes.

    A rejected candidate is no frame: the search resumes inside it (H3).
    """

    def __init__(self) -> None:
        from handset_link_ros import protocol as hp
        self._decoder = hp.StreamDecoder()
        self._malformed = hp.Malformed

    def _frames(self, results: list) -> list:
        return [r for r in results if not (isinstance(r, self._malformed) and r.type is None)]

    def feed(self, data: bytes) -> list:
        return self._frames(self._decoder.feed(data))

    def flush(self) -> list:
        return self._frames(self._decoder.flush())


def _decoders() -> Dict[str, Tuple[Callable, Callable, List[bytes]]]:
    from desheng_servo_ros import protocol as sp
    from dps_parachute_ros import protocol as p
    from originman_board_ros import protocol as op
    return {
        'dps_from_module': (lambda: p.StreamDecoder('from_module'), dps_frames,
                            [p.MODULE_HEADER, p.HOST_HEADER]),
        'dps_from_host': (lambda: p.StreamDecoder('from_host'), _dps_host_frames,
                          [p.HOST_HEADER]),
        'servo_reply': (lambda: sp.StreamDecoder('reply'), servo_frames, [sp.REPLY_HEADER]),
        'servo_request': (lambda: sp.StreamDecoder('request'), _servo_requests,
                          [sp.REQUEST_HEADER]),
        'handset': (_HandsetFuzzDecoder, handset_frames, [b'\xaa']),
        'originman_from_board': (op.StreamDecoder, originman_frames, [op.HEADER]),
    }


def _mutate(rng: random.Random, frame: bytes, headers: List[bytes]) -> bytes:
    b = bytearray(frame)
    op = rng.randrange(6)
    if op == 0:
        i = rng.randrange(len(b))
        b[i] ^= 1 << rng.randrange(8)
    elif op == 1:
        i = rng.randrange(len(b))
        b[i] = (b[i] + rng.randrange(1, 256)) & 0xFF
    elif op == 2 and len(b) > 1:
        del b[rng.randrange(len(b))]
    elif op == 3:
        b.insert(rng.randrange(len(b) + 1), rng.randrange(256))
    elif op == 4:
        del b[rng.randrange(1, len(b)):]
    else:
        b[:0] = rng.choice(headers)
    return bytes(b)


def build_stream(rng: random.Random, make_frames: Callable, headers: List[bytes],
                 segments: int) -> Tuple[bytes, List[Tuple[int, bytes]]]:
    """Return (stream, [(offset, valid frame)]) with `segments` frames of all three kinds."""
    valid = make_frames(rng, segments // 3 + 1)
    templates = make_frames(rng, max(16, segments // 50))
    out = bytearray()
    truth: List[Tuple[int, bytes]] = []
    vi = 0
    for _ in range(segments):
        kind = rng.randrange(3)
        if kind == 0 and vi < len(valid):
            truth.append((len(out), valid[vi]))
            out += valid[vi]
            vi += 1
        elif kind == 1:
            n = rng.randrange(4, 24)
            noise = rng.randbytes(n)
            if rng.random() < 0.5:
                noise = rng.choice(headers) + noise
            out += noise
        else:
            out += _mutate(rng, rng.choice(templates), headers)
    return bytes(out), truth


def fuzz_one(name: str, segments: int, seed: int = 7) -> Dict[str, float]:
    """Fuzz one decoder with `segments` frames; return its figures."""
    make_decoder, make_frames, headers = _decoders()[name]
    rng = random.Random(f'{seed}-{name}')
    stream, truth = build_stream(rng, make_frames, headers, segments)
    stream += bytes(300)  # lets every pending false candidate complete and fail
    decoder = make_decoder()
    decoded: List[bytes] = []
    exceptions = 0
    pos = 0
    t0 = time.perf_counter()
    while pos < len(stream):
        n = rng.randrange(1, 301)
        try:
            decoded += [f.raw for f in decoder.feed(stream[pos:pos + n])]
        except Exception:  # noqa: BLE001 - counting them is the point
            exceptions += 1
        pos += n
    if hasattr(decoder, 'flush'):
        try:
            decoded += [f.raw for f in decoder.flush()]
        except Exception:  # noqa: BLE001
            exceptions += 1
    elapsed = time.perf_counter() - t0
    truth_at = {offset: raw for offset, raw in truth}
    starts = [offset for offset, _ in truth]
    recovered = set()
    overlapped = set()
    spurious = 0
    cursor = 0
    import bisect
    for raw in decoded:
        at = stream.find(raw, cursor)
        if at < 0:  # cannot happen: a decoder returns bytes of its input
            exceptions += 1
            continue
        if truth_at.get(at) == raw:
            recovered.add(at)
        else:
            spurious += 1
            end = at + len(raw)
            i = bisect.bisect_left(starts, at)
            if i > 0 and starts[i - 1] + len(truth_at[starts[i - 1]]) > at:
                overlapped.add(starts[i - 1])
            while i < len(starts) and starts[i] < end:
                overlapped.add(starts[i])
                i += 1
        cursor = at + len(raw)
    clean = [o for o in starts if o not in overlapped]
    recovered_clean = sum(1 for o in clean if o in recovered)
    return {
        'frames': segments,
        'valid': len(truth),
        'bytes': len(stream),
        'exceptions': exceptions,
        'spurious': spurious,
        'overlapped': len(overlapped),
        'recovered': recovered_clean,
        'recovered_pct': 100.0 * recovered_clean / len(clean) if clean else 100.0,
        'seconds': elapsed,
    }


def run(segments: int = 1_000_000, seed: int = 7) -> Dict[str, object]:
    """Fuzz every decoder; return per-decoder results and the summary figures."""
    results = {name: fuzz_one(name, segments, seed) for name in _decoders()}
    return {
        'per_decoder': results,
        'fuzz_frames': sum(r['frames'] for r in results.values()),
        'fuzz_exceptions': sum(r['exceptions'] for r in results.values()),
        'fuzz_recovered_pct': min(r['recovered_pct'] for r in results.values()),
        'fuzz_overlapped': sum(r['overlapped'] for r in results.values()),
    }


if __name__ == '__main__':
    import sys
    summary = run(int(sys.argv[1]) if len(sys.argv) > 1 else 1_000_000)
    for name, r in summary['per_decoder'].items():
        print(name, r)
    print({k: v for k, v in summary.items() if k != 'per_decoder'})
