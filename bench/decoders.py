"""Throughput of the streaming decoders on a mixed stream with 10 % garbage.

The stream is what a driver reads: the module's / the servos' / the OriginMan board's / the
handset's frames (a realistic mix of lengths) with random noise bursts in between amounting to
10 % of the bytes. It is fed in chunks of ``chunk`` bytes (the driver reads whatever the port
holds; 64 bytes is a few milliseconds of a 115200 baud line). Throughput is stream bytes /
CPU-bound wall time of the ``feed`` calls; the ratio is against a 1 Mbit/s 8N1 wire (100 000
bytes/s).
"""

from __future__ import annotations

import random
import time
from typing import Callable, Dict, List, Tuple

WIRE_1M_BYTES_S = 1_000_000 / 10


def dps_frames(rng: random.Random, count: int) -> List[bytes]:
    """Return `count` frames a parachute module sends, in a realistic mix."""
    from dps_parachute_ros import protocol as p
    frames = []
    codes = sorted(p.MODULE_CODES - {p.CMD_STATUS, p.CMD_TRIGGER_RECORDS})
    for _ in range(count):
        r = rng.random()
        if r < 0.6:
            frames.append(p.encode_status_frame(rng.randrange(91), rng.randrange(30),
                                                rng.random() < 0.1, rng.random() < 0.5))
        elif r < 0.85:
            frames.append(p.module_frame(rng.choice(codes), rng.randrange(256)))
        elif r < 0.9:
            frames.append(p.module_frame(p.CMD_TRIGGER_RECORDS, rng.randrange(256)))
        elif r < 0.95:
            frames.append(p.encode_trigger_record(
                rng.randrange(256), rng.randrange(65536), rng.choice((1, 2, 4, 8)),
                rng.randrange(10, 91), rng.randrange(1, 10), rng.randrange(1, 256),
                rng.random() < 0.5, rng.random() < 0.5, rng.randrange(256),
                rng.randrange(256)))
        else:
            frames.append(p.encode_trigger_request(rng.choice((p.MODULE_HEADER,
                                                               p.HOST_HEADER))))
    return frames


def servo_frames(rng: random.Random, count: int) -> List[bytes]:
    """Return `count` servo replies: mostly position reads, some telemetry and status."""
    from desheng_servo_ros import protocol as sp
    frames = []
    for _ in range(count):
        r = rng.random()
        sid = rng.randrange(1, 13)
        status = 0 if rng.random() < 0.95 else rng.choice((0x01, 0x04, 0x20))
        if r < 0.7:
            params = rng.randrange(4096).to_bytes(2, 'big')
        elif r < 0.9:
            params = bytes(rng.randrange(256) for _ in range(rng.choice((4, 8, 10))))
        elif r < 0.97:
            params = b''
        else:
            params = bytes(rng.randrange(256) for _ in range(rng.randrange(1, 65)))
        frames.append(sp.encode_reply(sid, status, params))
    return frames


def originman_frames(rng: random.Random, count: int) -> List[bytes]:
    """Return `count` frames an OriginMan board sends: mostly IMU, servo replies, the rest."""
    from originman_board_ros import protocol as p
    frames = []
    subs = sorted(p.BUS_READ_FORMATS)
    for _ in range(count):
        r = rng.random()
        if r < 0.6:
            frames.append(p.encode_imu_report([rng.uniform(-2, 2) for _ in range(3)],
                                              [rng.uniform(-500, 500) for _ in range(3)]))
        elif r < 0.85:
            sub = rng.choice(subs) if rng.random() < 0.3 else p.BusSub.READ_POSITION
            sid = rng.randrange(1, 13)
            if rng.random() < 0.05:
                frames.append(p.encode_bus_reply(sid, sub, None, p.BUS_FAILURE))
            elif sub in (p.BusSub.READ_ANGLE_LIMITS, p.BusSub.READ_VOLTAGE_LIMITS):
                frames.append(p.encode_bus_reply(sid, sub, (rng.randrange(1000),
                                                            rng.randrange(1000, 14000))))
            elif sub == p.BusSub.READ_OFFSET:
                frames.append(p.encode_bus_reply(sid, sub, rng.randrange(-125, 126)))
            else:
                frames.append(p.encode_bus_reply(sid, sub, rng.randrange(256)))
        elif r < 0.9:
            frames.append(p.encode_sbus_report([rng.randrange(2048) for _ in range(16)]))
        elif r < 0.95:
            frames.append(p.encode_battery_report(rng.randrange(6000, 8500)))
        elif r < 0.98:
            frames.append(p.encode_key_report(rng.choice(p.KEY_IDS), rng.choice(list(p.KeyEvent))))
        else:
            frames.append(p.encode_pwm_pulse_reply(rng.randrange(1, 5), rng.randrange(500, 2501)))
    return frames


def handset_frames(rng: random.Random, count: int) -> List[bytes]:
    """Return `count` handset frames: mostly sticks, every type and encoding (H5)."""
    from handset_link_ros import protocol as hp
    types = list(hp.SPECS)
    weights = [20, 20, 20, 20, 4, 4, 4]
    out = []
    for type_ in rng.choices(types, weights, k=count):
        spec = hp.SPECS[type_]
        encoding = rng.choice(hp.ENCODINGS)
        if spec.whole or encoding in ('int8', 'int16'):
            lo, hi = int(spec.lo), int(spec.hi)
            if encoding == 'int8':
                lo, hi = max(lo, -128), min(hi, 127)
            value = rng.randint(lo, hi)
        else:
            value = round(rng.uniform(spec.lo, spec.hi), rng.choice((0, 1, 3)))
        if encoding == 'float32':
            value = float(value)
        out.append(hp.encode_command(type_, value, encoding))
    return out


def mixed_stream(frames: List[bytes], rng: random.Random,
                 garbage_fraction: float = 0.10) -> Tuple[bytes, int]:
    """Interleave `frames` with random noise bursts; return (stream, garbage bytes)."""
    total = sum(len(f) for f in frames)
    garbage_total = int(total * garbage_fraction / (1 - garbage_fraction))
    slots = len(frames)
    out = bytearray()
    left = garbage_total
    for i, frame in enumerate(frames):
        out += frame
        remaining_slots = slots - i
        if left and rng.random() < 0.3 or remaining_slots * 8 < left:
            n = min(left, rng.randrange(1, 17))
            out += bytes(rng.randrange(256) for _ in range(n))
            left -= n
    return bytes(out), garbage_total - left


def _throughput(make_decoder: Callable, stream: bytes, chunk: int,
                repeats: int, count_frames: Callable = len) -> Tuple[float, int]:
    best = float('inf')
    frames = 0
    for _ in range(repeats):
        decoder = make_decoder()
        feed = decoder.feed
        count = 0
        t0 = time.perf_counter()
        for i in range(0, len(stream), chunk):
            count += count_frames(feed(stream[i:i + chunk]))
        elapsed = time.perf_counter() - t0
        best = min(best, elapsed)
        frames = count
    return len(stream) / best / 1e6, frames


def run(n_frames: int = 40_000, chunk: int = 64, repeats: int = 3,
        seed: int = 1) -> Dict[str, float]:
    """Measure the four decoders; return figures (MB/s = 10^6 bytes/s, best of `repeats`)."""
    from desheng_servo_ros.protocol import StreamDecoder as ServoDecoder
    from dps_parachute_ros.protocol import StreamDecoder as DpsDecoder
    from handset_link_ros import protocol as hp
    from originman_board_ros.protocol import StreamDecoder as OriginManDecoder

    def sound(results: list) -> int:
        # The handset reports each rejected candidate as a Malformed result: not a frame.
        return sum(1 for r in results if not (isinstance(r, hp.Malformed) and r.type is None))

    rng = random.Random(seed)
    out: Dict[str, float] = {}
    for name, frames, factory, count in (
            ('dps', dps_frames(rng, n_frames), lambda: DpsDecoder('from_module'), len),
            ('servo', servo_frames(rng, n_frames), lambda: ServoDecoder('reply'), len),
            ('originman', originman_frames(rng, n_frames), OriginManDecoder, len),
            ('handset', handset_frames(rng, n_frames), hp.StreamDecoder, sound)):
        stream, garbage = mixed_stream(frames, rng)
        mb_s, decoded = _throughput(factory, stream, chunk, repeats, count)
        out[f'decoder_mb_s_{name}'] = round(mb_s, 2)
        out[f'decoder_x_1mbit_{name}'] = round(mb_s * 1e6 / WIRE_1M_BYTES_S, 1)
        out[f'decoder_garbage_pct_{name}'] = round(100.0 * garbage / len(stream), 1)
        out[f'decoder_frames_found_pct_{name}'] = round(100.0 * decoded / len(frames), 2)
    return out


if __name__ == '__main__':
    for key, value in run().items():
        print(f'{key}={value}')
