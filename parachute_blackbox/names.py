"""The black box's vocabulary: limits, lanes, bands, command and setting names, rules."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, Dict, TYPE_CHECKING

from dps_parachute_ros import protocol as p

if TYPE_CHECKING:
    from parachute_blackbox.analysis import FlightAnalysis


MAX_BUCKETS = 2000
"""Time buckets per series or band at most; the timeline is a few thousand pixels wide."""
FIRST_BUCKET_S = 0.02
"""Bucket width to begin with: a short run keeps its 10-20 Hz status stream point by point."""
KEEP_EVENTS = 300
"""Events kept per lane at the start and again at the end of the flight."""
MAX_DEPLOYMENTS = 100
"""Deployments described one by one; more are counted."""
MAX_ZOOMS = 6
"""Deployments that get a full-resolution close-up of the seconds around them."""
ZOOM_BEFORE_S = 4.0
ZOOM_AFTER_S = 4.0
ZOOM_MAX_SAMPLES = 4000
REPLY_TIMEOUT_S = 1.0
"""P12: a reply later than this after its request is lost; the driver has given up by then.
The driver's ``request_timeout_s`` in its start record replaces it for that run."""
REPLY_MARGIN_S = 0.2
"""A request with no reply this long after the timeout since its last frame left is
unanswered: a margin for records of the reply that other threads' records overtook in the
queue."""
REQUEST_STALE_S = 2.0
"""A trigger request still undecided this long after it came gets no decision any more (the
module waits 1 s, P10; the driver decides within its defer timeout or at its stop)."""
DEPLOYMENT_WINDOW_S = 10.0
"""Triggered flags, acknowledgements and trigger events this close belong to one deployment."""
REBOOT_SAME_S = 0.2
"""Unsolicited heartbeat frames this close are one power-up (two, 50 ms apart, P5)."""
REBOOT_RECORD_DELAY_S = 5.0
"""The driver's reboot record belongs to the heartbeat frame before it if it came at most this
long after it (the driver records it once it handled the frame: later on a loaded host)."""
RECORD_GAP_S = 2.0
"""No record at all for this long while online and streaming: the black box lost records."""
MAX_RECORDS_KEPT = 64
"""Distinct trigger records (module history) kept."""

LANES = ('calls', 'request', 'deploy', 'module', 'settings', 'link', 'blackbox', 'other')
LANE_TITLES = {
    'calls': 'service calls', 'request': 'trigger requests', 'deploy': 'deployment',
    'module': 'module (reboots)', 'settings': 'settings', 'link': 'link',
    'blackbox': 'black box', 'other': 'unknown records',
}
BANDS = ('port', 'online', 'streaming', 'armed', 'triggered', 'blackbox')
LINK_COUNTERS = ('checksum_errors', 'bytes_discarded', 'timeouts', 'reconnects', 'frames_in',
                 'frames_out')
"""The cumulative counters of a ``link`` record (the driver's decoder and serial link)."""
SETTING_NAMES = {
    p.CMD_ATTITUDE_THRESHOLD: ('attitude_threshold_deg', 'attitude threshold', '°', 1.0),
    p.CMD_FREEFALL_THRESHOLD: ('freefall_threshold_g', 'free-fall threshold', ' g', 0.1),
    p.CMD_FREEFALL_TIME: ('freefall_time_s', 'free-fall time', ' s', 0.01),
    p.CMD_LIGHT_THRESHOLD: ('light_threshold_v', 'light threshold', ' V', 0.1),
}
"""Setting command code -> (key, name, unit, raw step)."""
SETTING_REPLIES = {p.AttitudeThreshold: p.CMD_ATTITUDE_THRESHOLD,
                   p.FreefallThreshold: p.CMD_FREEFALL_THRESHOLD,
                   p.FreefallTime: p.CMD_FREEFALL_TIME,
                   p.LightThreshold: p.CMD_LIGHT_THRESHOLD}
COMMAND_NAMES = {
    p.CMD_HEARTBEAT: 'heartbeat', p.CMD_ARM: 'arm/lock', p.CMD_DEPLOY: 'deploy',
    p.CMD_SHUTDOWN: 'shutdown', p.CMD_STREAMING: 'streaming', p.CMD_LIGHT_LEVEL: 'light level',
    p.CMD_LIGHT_THRESHOLD: 'light threshold', p.CMD_ATTITUDE_TRIGGER: 'attitude trigger',
    p.CMD_FREEFALL_TRIGGER: 'free-fall trigger', p.CMD_ATTITUDE_THRESHOLD: 'attitude threshold',
    p.CMD_FREEFALL_THRESHOLD: 'free-fall threshold', p.CMD_FREEFALL_TIME: 'free-fall time',
    p.CMD_BOOT_COUNT: 'boot count', p.CMD_BAUD_RATE: 'baud rate', p.CMD_SENSOR_ZERO: 'zero sensor',
    p.CMD_ARMED: 'armed?', p.CMD_TRIGGERED: 'triggered?', p.CMD_STATUS: 'status',
    p.CMD_CHARGING: 'charging?', p.CMD_CELL_VOLTAGE: 'cell voltage',
    p.CMD_TRIGGER_RECORDS: 'trigger records', p.CMD_TRIGGER_REQUEST: 'trigger confirmation',
}
SOURCE_BITS = ((p.SOURCE_SERIAL, 'serial'), (p.SOURCE_ATTITUDE, 'attitude'),
               (p.SOURCE_PWM, 'PWM'), (p.SOURCE_FREEFALL, 'free fall'))
VIA_NAMES = {'deploy_ack': 'the deploy acknowledgement', 'status': 'the status (triggered flag)',
             'record': 'a new trigger record'}
"""``trigger_event.via``: how the driver learned of the deployment."""
COMMON_FIELDS = frozenset({'t', 'mono', 'kind'})


def source_text(source: int) -> str:
    """Name trigger-source bits: 'free fall', 'attitude+PWM', 'unknown'."""
    names = [name for bit, name in SOURCE_BITS if source & bit]
    return '+'.join(names) if names else 'unknown'


def short(value: Any, limit: int = 100) -> str:
    """Render a field value in one short line."""
    if isinstance(value, float):
        text = f'{value:.4g}'
    elif isinstance(value, (dict, list)):
        text = ', '.join(f'{k}={short(v, 30)}' for k, v in value.items()) \
            if isinstance(value, dict) else ', '.join(short(v, 30) for v in value)
    else:
        text = str(value)
    return text if len(text) <= limit else text[:limit - 1] + '…'


def describe_fields(record: Dict[str, Any], skip: frozenset = COMMON_FIELDS) -> str:
    """Return ``key=value, ...`` of a record's fields, bounded in length."""
    return short(', '.join(f'{k}={short(v, 40)}' for k, v in record.items() if k not in skip),
                 160)


def record_text(record: p.TriggerRecord) -> str:
    """Describe a trigger record in one line."""
    return (f'source {source_text(record.source)}, boot #{record.boot_count}, '
            f'{record.uptime_s} s after power-up, thresholds {record.attitude_threshold_deg}° / '
            f'{record.freefall_threshold_g:.1f} g / {record.freefall_time_s:.2f} s, cell '
            f'{record.cell_voltage_v:.2f} V, {"charging" if record.charging else "on battery"}')


# ---------------------------------------------------------------------------------------------
# The rules
# ---------------------------------------------------------------------------------------------

Handler = Callable[['FlightAnalysis', Dict[str, Any], float], None]


@dataclass(frozen=True)
class Rule:
    """What one record kind means: its known fields and the handler that reads it."""

    kind: str
    fields: frozenset
    handler: Handler
