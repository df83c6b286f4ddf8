"""Shared helpers of the benchmarks: a private ROS domain, node processes, wire taps, figures.

Everything here starts something that must be stopped: every helper is a context manager or
has a ``stop()``, and every wait has a timeout. Temporary files live in one
``tempfile.TemporaryDirectory`` per use and are removed on exit.
"""

from __future__ import annotations

import contextlib
import math
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any, Callable, Dict, Iterator, List, Optional

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

CLK_TCK = os.sysconf('SC_CLK_TCK')
PAGE_SIZE = os.sysconf('SC_PAGE_SIZE')

# ------------------------------------------------------------------------------------------
# A private ROS domain
# ------------------------------------------------------------------------------------------

# wait_for raises process.WaitTimeout, a TimeoutError (what the benchmarks catch).
from uav_serial_common.process import (  # noqa: E402,F401
    claim_domain_id as _claim, die_with_parent, executable_path, wait_for)


def claim_domain_id() -> int:
    """Lock a ROS_DOMAIN_ID no test session or other benchmark holds (uav_serial_common.process).

    Never the one in this process's environment: a test session that started the benchmark
    holds that one.
    """
    current = os.environ.get('ROS_DOMAIN_ID')
    return _claim(exclude=int(current) if current and current.isdigit() else None)


def ros_env() -> Dict[str, str]:
    """Return the environment for node processes: private domain, localhost discovery."""
    env = dict(os.environ)
    env['ROS_DOMAIN_ID'] = str(claim_domain_id())
    env['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    env.pop('ROS_LOCALHOST_ONLY', None)
    env.setdefault('RCUTILS_COLORIZED_OUTPUT', '0')
    env['PYTHONUNBUFFERED'] = '1'
    return env


def node_available(name: str) -> bool:
    """Whether executable `name` is installed and is more than the placeholder."""
    try:
        path = executable_path(name)
    except (FileNotFoundError, Exception):  # noqa: BLE001 - no ament index at all
        return False
    module = {'parachute_node': 'dps_parachute_ros/node.py',
              'servo_bus_node': 'desheng_servo_ros/node.py',
              'virtual_parachute': 'dps_parachute_ros/virtual_node.py',
              'virtual_servo_bus': 'desheng_servo_ros/virtual_node.py'}.get(name)
    if module is None:
        return os.path.exists(path)
    try:
        return 'not implemented yet' not in (ROOT / module).read_text()
    except OSError:
        return False


# ------------------------------------------------------------------------------------------
# Processes
# ------------------------------------------------------------------------------------------

def write_params(directory: Path, name: str, parameters: Dict[str, Any]) -> Path:
    """Write a ``/**`` parameter file and return its path."""
    import yaml
    path = directory / f'{name}.params.yaml'
    path.write_text(yaml.safe_dump({'/**': {'ros__parameters': parameters}}))
    return path


class NodeProcess:
    """One installed executable run as a child process, stopped by PID."""

    def __init__(self, executable: str, workdir: Path, parameters: Optional[Dict] = None,
                 node_name: Optional[str] = None, tag: Optional[str] = None) -> None:
        self.executable = executable
        tag = tag or executable
        args = [executable_path(executable), '--ros-args']
        if node_name:
            args += ['-r', f'__node:={node_name}']
        if parameters:
            args += ['--params-file', str(write_params(workdir, tag, parameters))]
        self.log_path = workdir / f'{tag}.log'
        with open(self.log_path, 'ab') as log:
            self.popen = subprocess.Popen(args, stdout=log, stderr=subprocess.STDOUT,
                                          env=ros_env(), start_new_session=True,
                                          preexec_fn=die_with_parent)

    @property
    def pid(self) -> int:
        """Return the process id."""
        return self.popen.pid

    def alive(self) -> bool:
        """Return whether the process still runs."""
        return self.popen.poll() is None

    def output(self) -> str:
        """Return what the process printed so far."""
        try:
            return self.log_path.read_text(errors='replace')
        except OSError:
            return ''

    def stop(self, sig: int = signal.SIGINT, timeout: float = 10.0) -> Optional[int]:
        """Send `sig`, wait up to `timeout` s, then SIGKILL; return the exit code."""
        if self.popen.poll() is None:
            with contextlib.suppress(ProcessLookupError):
                os.kill(self.popen.pid, sig)
            try:
                self.popen.wait(timeout)
            except subprocess.TimeoutExpired:
                with contextlib.suppress(ProcessLookupError):
                    os.kill(self.popen.pid, signal.SIGKILL)
                self.popen.wait(5)
        return self.popen.returncode


@contextlib.contextmanager
def workdir(prefix: str = 'uavbench-') -> Iterator[Path]:
    """Yield a temporary directory that is removed afterwards."""
    with tempfile.TemporaryDirectory(prefix=prefix) as path:
        yield Path(path)


@contextlib.contextmanager
def node_process(executable: str, directory: Path, parameters: Optional[Dict] = None,
                 **kwargs: Any) -> Iterator[NodeProcess]:
    """Run one node process for the duration of a ``with`` block."""
    proc = NodeProcess(executable, directory, parameters, **kwargs)
    try:
        yield proc
    finally:
        proc.stop()


# ------------------------------------------------------------------------------------------
# /proc figures
# ------------------------------------------------------------------------------------------

def cpu_seconds(pid: int) -> float:
    """Return user + system CPU seconds of process `pid` (all its threads)."""
    with open(f'/proc/{pid}/stat') as f:
        fields = f.read().rsplit(')', 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / CLK_TCK


def rss_bytes(pid: int) -> int:
    """Return the resident set size of `pid` in bytes."""
    with open(f'/proc/{pid}/statm') as f:
        return int(f.read().split()[1]) * PAGE_SIZE


def fd_count(pid: int) -> int:
    """Return the number of open file descriptors of `pid`."""
    return len(os.listdir(f'/proc/{pid}/fd'))


def thread_count(pid: int) -> int:
    """Return the number of threads of `pid`."""
    return len(os.listdir(f'/proc/{pid}/task'))


def pty_fds(pid: int) -> int:
    """Return how many of `pid`'s descriptors point at a pseudo-terminal."""
    count = 0
    for fd in os.listdir(f'/proc/{pid}/fd'):
        with contextlib.suppress(OSError):
            if os.readlink(f'/proc/{pid}/fd/{fd}').startswith('/dev/pts/'):
                count += 1
    return count


class CpuMeter:
    """CPU use of a process over a window, in percent of one core."""

    def __init__(self, pid: int) -> None:
        self.pid = pid
        self.start()

    def start(self) -> None:
        """Begin a new window now."""
        self._t0 = time.monotonic()
        self._c0 = cpu_seconds(self.pid)

    def percent(self) -> float:
        """Return CPU percent of one core since `start()`."""
        elapsed = time.monotonic() - self._t0
        return 100.0 * (cpu_seconds(self.pid) - self._c0) / elapsed if elapsed > 0 else 0.0


# ------------------------------------------------------------------------------------------
# Statistics
# ------------------------------------------------------------------------------------------

def percentile(values: List[float], q: float) -> float:
    """Return the nearest-rank percentile `q` (0..100) of `values`; NaN when empty."""
    if not values:
        return math.nan
    ordered = sorted(values)
    rank = max(1, math.ceil(q / 100.0 * len(ordered)))
    return ordered[min(rank, len(ordered)) - 1]


def median(values: List[float]) -> float:
    """Return the 50th percentile by nearest rank."""
    return percentile(values, 50)


# ------------------------------------------------------------------------------------------
# ROS client side, in a private rclpy context
# ------------------------------------------------------------------------------------------

class RosClient:
    """A private rclpy Context on the benchmark's domain, with one node spinning in a thread.

    The context, node and single-threaded executor are `uav_serial_common.ros_client`'s
    `RosHarness` (rclpy's multi-threaded executor can spin hot in Python while tasks are in
    flight and starve the in-process virtual devices of the GIL); this adds callback
    subscriptions and calls that raise TimeoutError.
    """

    def __init__(self, name: str = 'bench_client') -> None:
        from uav_serial_common.ros_client import RosHarness
        self._ros = RosHarness(name, domain_id=claim_domain_id())
        self.context = self._ros.context
        self.node = self._ros.node
        self.executor = self._ros.executor

    def subscribe(self, msg_type: Any, topic: str, callback: Callable[[Any], None],
                  latched: bool = False, depth: int = 50) -> Any:
        """Subscribe `callback` to `topic` (reliable; transient local if `latched`)."""
        from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
        qos = QoSProfile(depth=depth)
        qos.reliability = ReliabilityPolicy.RELIABLE
        if latched:
            qos.durability = DurabilityPolicy.TRANSIENT_LOCAL
        return self.node.create_subscription(msg_type, topic, callback, qos)

    def client(self, srv_type: Any, name: str, timeout: float = 20.0) -> Any:
        """Create a service client and wait for its server."""
        client = self.node.create_client(srv_type, name)
        if not client.wait_for_service(timeout_sec=timeout):
            raise TimeoutError(f'service {name} not available after {timeout:.0f} s')
        return client

    def call(self, client: Any, request: Any, timeout: float = 10.0) -> Any:
        """Call a service through `client`; raise TimeoutError after `timeout` s."""
        future = client.call_async(request)
        done = threading.Event()
        future.add_done_callback(lambda _f: done.set())
        if not done.wait(timeout):
            client.remove_pending_request(future)
            raise TimeoutError(f'{client.srv_name} did not answer within {timeout:.0f} s')
        return future.result()

    def wait_for_service(self, name: str, timeout: float = 20.0) -> None:
        """Wait until a service of that fully qualified name exists; TimeoutError if not."""
        self._ros.wait_for_service(name, timeout)

    def close(self) -> None:
        """Stop spinning and shut the context down."""
        self._ros.close()


@contextlib.contextmanager
def ros_client(name: str = 'bench_client') -> Iterator[RosClient]:
    """Yield a `RosClient` that is closed afterwards."""
    client = RosClient(name)
    try:
        yield client
    finally:
        client.close()


# ------------------------------------------------------------------------------------------
# Wire taps
# ------------------------------------------------------------------------------------------

class ServoWireTap:
    """Decode both directions of a servo bus tap into timed request/reply transactions.

    Install with ``runner.add_tap(tap)``. Requests are decoded as they arrive at the device,
    replies as the device sends them; a READ request is paired with the next reply of the same
    id. ``transactions`` holds ``(t_request, t_reply, request, reply)``.
    """

    def __init__(self) -> None:
        from desheng_servo_ros.protocol import StreamDecoder
        self._req = StreamDecoder('request')
        self._rep = StreamDecoder('reply')
        self._lock = threading.Lock()
        self._open: Optional[tuple] = None
        self.transactions: List[tuple] = []
        self.requests: List[tuple] = []
        self.bytes_rx = 0
        self.bytes_tx = 0

    def __call__(self, direction: str, data: bytes, t: float) -> None:
        with self._lock:
            if direction == 'rx':
                self.bytes_rx += len(data)
                for req in self._req.feed(data):
                    self.requests.append((t, req))
                    self._open = (t, req)
            else:
                self.bytes_tx += len(data)
                for rep in self._rep.feed(data):
                    if self._open is not None and self._open[1].servo_id == rep.servo_id:
                        t_req, req = self._open
                        self.transactions.append((t_req, t, req, rep))
                        self._open = None

    def snapshot(self) -> tuple:
        """Return copies of (transactions, requests)."""
        with self._lock:
            return list(self.transactions), list(self.requests)


class DpsWireTap:
    """Decode both directions of a parachute port into timed frames: ``rx`` and ``tx`` lists."""

    def __init__(self) -> None:
        from dps_parachute_ros.protocol import StreamDecoder
        self._host = StreamDecoder('from_host')
        self._module = StreamDecoder('from_module')
        self._lock = threading.Lock()
        self._cond = threading.Condition(self._lock)
        self.rx: List[tuple] = []
        self.tx: List[tuple] = []
        self.bytes_rx = 0

    def __call__(self, direction: str, data: bytes, t: float) -> None:
        with self._cond:
            if direction == 'rx':
                self.bytes_rx += len(data)
                self.rx.extend((t, f) for f in self._host.feed(data))
            else:
                self.tx.extend((t, f) for f in self._module.feed(data))
            self._cond.notify_all()

    def wait_rx(self, predicate: Callable[[Any], bool], start: int,
                timeout: float) -> Optional[tuple]:
        """Return the first ``(t, frame)`` received at index >= `start` matching `predicate`."""
        deadline = time.monotonic() + timeout
        with self._cond:
            while True:
                for item in self.rx[start:]:
                    if predicate(item[1]):
                        return item
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    return None
                self._cond.wait(remaining)


# ------------------------------------------------------------------------------------------
# Rigs: a device model behind a pty in this process, its driver node as a process
# ------------------------------------------------------------------------------------------

POSITION_ADDRESS = 0x38
# The virtual servo's own answer time after a request, in the benchmarks: none, so that the time
# between wire bytes is the host's (servo_read_ratio is measured against the wire alone).
BENCH_SERVO_RESPONSE_DELAY_S = 0.0


def is_position_read(req: Any) -> bool:
    """Whether a servo request is a READ that covers the present-position register."""
    from desheng_servo_ros.protocol import Instruction
    if req.instruction != Instruction.READ or len(req.params) != 2:
        return False
    address, length = req.params[0], req.params[1]
    return address <= POSITION_ADDRESS and address + length >= POSITION_ADDRESS + 2


class _Rig:
    """A device runner in this process with a tap on it, and its driver node as a process."""

    executable = ''

    def __init__(self, directory: Path, runner: Any, tap: Any, parameters: Dict[str, Any],
                 tag: str) -> None:
        self.directory = directory
        self.runner = runner
        self.tap = tap
        self.runner.add_tap(tap)
        self.parameters = parameters
        self.tag = tag
        self.node: Optional[NodeProcess] = None

    def __enter__(self) -> '_Rig':
        self.runner.start()
        try:
            self.start_node()
        except BaseException:
            self.runner.stop()
            raise
        return self

    def __exit__(self, *exc: object) -> None:
        try:
            if self.node is not None:
                self.node.stop()
        finally:
            self.runner.stop()

    def start_node(self) -> NodeProcess:
        """Start (or restart) the driver process."""
        self.node = NodeProcess(self.executable, self.directory, self.parameters, tag=self.tag)
        return self.node

    def _wait_ready(self, ready: Callable[[], bool], timeout: float, what: str) -> None:
        def check() -> bool:
            if not self.node.alive():
                raise RuntimeError(f'{self.executable} exited:\n{self.node.output()[-3000:]}')
            return ready()
        wait_for(check, timeout, interval=0.05, what=what)


class ServoRig(_Rig):
    """A virtual servo bus in this process (taps on its wire) and `servo_bus_node` on it.

    The bus is `desheng_servo_ros.virtual_node.VirtualServoBus` (the core of
    ``virtual_servo_bus``) with `BENCH_SERVO_RESPONSE_DELAY_S`, or `bus_class` (a subclass of it)
    and `response_delay_s` where given.
    """

    executable = 'servo_bus_node'

    def __init__(self, directory: Path, ids: List[int], baud: int = 115200,
                 parameters: Optional[Dict[str, Any]] = None, seed: int = 1,
                 tag: str = 'servo_bus_node', bus_class: Any = None,
                 response_delay_s: float = BENCH_SERVO_RESPONSE_DELAY_S) -> None:
        from desheng_servo_ros.virtual_node import VirtualServoBus
        self.ids = list(ids)
        self.baud = baud
        self.link = str(directory / f'{tag}.pty')
        self.bus = (bus_class or VirtualServoBus)(self.link, self.ids, baud=baud,
                                                  response_delay_s=response_delay_s, seed=seed)
        self.sim = self.bus.sim
        params = {'port': self.link, 'baud': baud, 'servo_ids': self.ids,
                  'joint_names': [f'servo_{i}' for i in self.ids]}
        params.update(parameters or {})
        super().__init__(directory, self.bus.runner, ServoWireTap(), params, tag)

    def position_transactions(self, since: float = 0.0) -> List[tuple]:
        """Return the position-read transactions whose request arrived at or after `since`."""
        transactions, _ = self.tap.snapshot()
        return [t for t in transactions if t[0] >= since and is_position_read(t[2])]

    def wait_ready(self, timeout: float = 40.0) -> None:
        """Wait until every servo's position has been read once; raise if the node died."""
        self._wait_ready(lambda: {t[3].servo_id for t in self.position_transactions()}
                         >= set(self.ids), timeout, 'position reads of every servo')


class ParachuteRig(_Rig):
    """A virtual DPS-S module in this process (taps on its wire) and `parachute_node` on it.

    The module is `VirtualParachute` behind `dps_parachute_ros.virtual_node.create_runner`, as
    in ``virtual_parachute``.
    """

    executable = 'parachute_node'

    def __init__(self, directory: Path, baud: int = 115200, stream_period_s: float = 0.05,
                 parameters: Optional[Dict[str, Any]] = None, seed: int = 1,
                 tag: str = 'parachute_node') -> None:
        from dps_parachute_ros.simulation import VirtualParachute
        from dps_parachute_ros.virtual_node import create_runner
        self.link = str(directory / f'{tag}.pty')
        self.blackbox_dir = directory / f'{tag}-blackbox'
        self.sim = VirtualParachute(now=time.monotonic(), stream_period_s=stream_period_s)
        params = {'port': self.link, 'baud': baud, 'blackbox_dir': str(self.blackbox_dir)}
        params.update(parameters or {})
        super().__init__(directory, create_runner(self.sim, self.link, baud, seed), DpsWireTap(),
                         params, tag)

    def wait_ready(self, timeout: float = 40.0) -> None:
        """Wait until the driver has turned the status stream on; raise if it died."""
        def streaming() -> bool:
            with self.runner.locked():
                return self.sim.streaming
        self._wait_ready(streaming, timeout, 'the driver to turn the stream on')


# ------------------------------------------------------------------------------------------
# The handset link: a virtual handset in this process, handset_link_node as a process
# ------------------------------------------------------------------------------------------

class HandsetWireTap:
    """The virtual handset's wire: every frame sent, with the time its last byte arrived.

    The runner writes one frame per chunk (``step_frames``), so a chunk's time is its frame's
    end. ``rx_bytes`` counts what the driver wrote to the modem's port: H11 says none.
    """

    def __init__(self) -> None:
        from handset_link_ros.protocol import StreamDecoder
        self._decoder = StreamDecoder()
        self._lock = threading.Lock()
        self.sent: List[tuple] = []
        self.rx_bytes = 0

    def __call__(self, direction: str, data: bytes, t: float) -> None:
        from handset_link_ros.protocol import Command
        with self._lock:
            if direction == 'rx':
                self.rx_bytes += len(data)
                return
            self.sent.extend((t, r) for r in self._decoder.feed(data) if isinstance(r, Command))

    def snapshot(self) -> List[tuple]:
        """Return a copy of ``[(t_last_byte, Command)]``."""
        with self._lock:
            return list(self.sent)


def numbered_stick(k: int) -> Dict[str, float]:
    """Return stick values unique to tick `k` (within 1800 ticks), all inside the H4 ranges."""
    return {'yaw_deg': round(-180.0 + (k % 3600) * 0.1, 1),
            'pitch_deg': round(-90.0 + (k % 1800) * 0.1, 1),
            'roll_deg': round(90.0 - (k % 1800) * 0.1, 1),
            'altitude_m': round(-100.0 + (k % 110000) * 0.01, 2)}


class HandsetRig(_Rig):
    """A virtual handset in this process (a tap on its wire) and `handset_link_node` on it.

    The handset is `VirtualHandset` behind `handset_link_ros.virtual_node.create_runner`, as in
    ``virtual_handset`` (frames paced at the baud, wire faults per frame). With `numbered`, the
    four stick values change every tick (`numbered_stick`), so each frame can be matched to the
    ``~/setpoint`` that carries it.
    """

    executable = 'handset_link_node'

    def __init__(self, directory: Path, baud: int = 115200, numbered: bool = False,
                 parameters: Optional[Dict[str, Any]] = None, seed: int = 1,
                 tag: str = 'handset_link_node') -> None:
        from handset_link_ros.simulation import VirtualHandset
        from handset_link_ros.virtual_node import create_runner
        self.link = str(directory / f'{tag}.pty')
        self.sim = VirtualHandset(now=time.monotonic())
        self.ticks = 0
        params = {'port': self.link, 'baud': baud}
        params.update(parameters or {})
        runner = create_runner(self.sim, self.link, baud, seed,
                               on_tick=self._numbered if numbered else None)
        super().__init__(directory, runner, HandsetWireTap(), params, tag)

    def _numbered(self, now: float) -> List[bytes]:
        due = self.sim.next_event_time()
        if due is not None and due <= now + 1e-9:
            self.ticks += 1
            self.sim.set_sticks(**numbered_stick(self.ticks))
        return self.sim.step_frames(now)

    def wait_ready(self, timeout: float = 40.0) -> None:
        """Wait until the driver has heard the handset (its log says so); raise if it died."""
        self._wait_ready(lambda: 'handset heard' in self.node.output(), timeout,
                         'the driver to hear the handset')


# ------------------------------------------------------------------------------------------
# The OriginMan board: a virtual board in this process, originman_board_node as a process
# ------------------------------------------------------------------------------------------

class OriginManWireTap:
    """Decode both directions of the OriginMan board's port into timed messages.

    ``rx``: ``(t, command)`` as the board's parser reads what the driver wrote; ``tx``:
    ``(t, message)`` of what the board sent, IMU reports aside: they are only counted
    (``imu_count``), and with ``keep_imu`` their wire times are kept by gyro x in rad
    (``imu_times``), the value the driver publishes as ``angular_velocity.x``.
    """

    def __init__(self, keep_imu: bool = False) -> None:
        from originman_board_ros import protocol as p
        self._p = p
        self._parser = p.BoardParser()
        self._decoder = p.StreamDecoder()
        self._lock = threading.Lock()
        self.keep_imu = keep_imu
        self.rx: List[tuple] = []
        self.tx: List[tuple] = []
        self.imu_times: Dict[float, float] = {}
        self.imu_count = 0

    def __call__(self, direction: str, data: bytes, t: float) -> None:
        p = self._p
        with self._lock:
            if direction == 'rx':
                self.rx.extend((t, p.decode_host_command(f)) for f in self._parser.feed(data))
                return
            for frame in self._decoder.feed(data):
                if frame.function == p.Function.IMU:
                    self.imu_count += 1
                    if self.keep_imu:
                        report = p.decode_board_frame(frame)
                        self.imu_times[math.radians(report.gyro_dps[0])] = t
                else:
                    self.tx.append((t, p.decode_board_frame(frame)))

    def snapshot(self) -> tuple:
        """Return copies of (rx, tx)."""
        with self._lock:
            return list(self.rx), list(self.tx)

    def bus_replies(self, since: float = 0.0) -> List[tuple]:
        """Return ``(t, reply)`` of the successful bus-servo replies sent at or after `since`."""
        p = self._p
        with self._lock:
            return [(t, m) for t, m in self.tx
                    if t >= since and isinstance(m, p.BusServoReply) and m.ok]


class OriginManRig(_Rig):
    """A virtual OriginMan board in this process (taps on its wire) and `originman_board_node`.

    The board is `originman_board_ros.virtual_node.VirtualOriginManBoard`, the core of
    ``virtual_originman_board``: the firmware model at 1 Mbaud with the wire faults applied to
    everything it sends. The driver polls bus servos 1..3 unless `parameters` say otherwise.
    """

    executable = 'originman_board_node'

    def __init__(self, directory: Path, parameters: Optional[Dict[str, Any]] = None,
                 seed: int = 1, tag: str = 'originman_board_node', keep_imu: bool = False,
                 **board_kwargs: Any) -> None:
        from originman_board_ros.virtual_node import VirtualOriginManBoard
        self.link = str(directory / f'{tag}.pty')
        params = {'port': self.link, 'bus_servo_ids': [1, 2, 3]}
        params.update(parameters or {})
        self.board = VirtualOriginManBoard(self.link, seed=seed, **board_kwargs)
        self.model = self.board.model
        super().__init__(directory, self.board.runner, OriginManWireTap(keep_imu), params, tag)

    def wait_ready(self, timeout: float = 40.0) -> None:
        """Wait until every polled servo's position read was answered; raise if the node died."""
        ids = set(self.parameters['bus_servo_ids'])
        self._wait_ready(lambda: {m.servo_id for _, m in self.tap.bus_replies()} >= ids,
                         timeout, 'bus servo reads of every polled servo')
