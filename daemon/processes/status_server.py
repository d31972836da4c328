"""The read-only status HTTP endpoint: /livez, /readyz, /status, /metrics and the latest map previews.

Everything it shows comes from the processes' health topics on the bus (the latest DriverHealth of
each; recorder, mapper, replay and supervisor put their extras as JSON in `detail`) and from the
preview PNGs the mapping worker writes. No request changes the daemon's state; any other path,
including path tricks, gets 404. Requests are served by threads, so a busy mapper never blocks it; at most
MAX_THREADS at once (more connections are answered 503 and counted on /metrics), each closed when idle, and
each request read whole within REQUEST_DEADLINE_S of its first byte (a client trickling it is cut off, counted).
"""

from __future__ import annotations

import argparse
import io
import json
import logging
import socket
import sys
import threading
import time
from collections import deque
from dataclasses import asdict
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

from prometheus_client import CollectorRegistry, generate_latest
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily

from daemon.spine.config import CarConfig, ConfigError, data_dir, load_config, reports_config_errors
from daemon.spine.data_layout import PREVIEWS, preview_dir
from daemon.spine.messages import DriverHealth
from daemon.spine.process_logging import setup_logging
from daemon.spine.process_table import required_drivers
from daemon.spine.stop_signals import on_signals
from daemon.spine.topics import topic_table

LISTEN_BACKLOG = 256  # connections the kernel queues before the server accepts them
IDLE_TIMEOUT_S = 10.0  # a client that sends nothing (or stops reading) for this long is disconnected
REQUEST_DEADLINE_S = 5.0  # the whole request (line and headers) must arrive within this of its first byte
MAX_THREADS = 32  # connections served at once (one thread each); more are answered 503 and closed
REFUSED_LINGER_S = 1.0  # longest wait for a refused client's request before its connection is closed
BUSY_RESPONSE = (b"HTTP/1.0 503 Service Unavailable\r\nContent-Type: text/plain\r\nContent-Length: 5\r\n"
                 b"Retry-After: 1\r\nConnection: close\r\n\r\nbusy\n")


def health_age_s(health: DriverHealth, now_ns: int | None = None) -> float:
    """Seconds since the process published this health, by its own stamp (host CLOCK_MONOTONIC, which every process
    shares): the age of a stopped or hung publisher's last message grows, however often it is read again."""
    if health.host_mono_ns <= 0:
        return float("inf")
    return max(0.0, ((time.monotonic_ns() if now_ns is None else now_ns) - health.host_mono_ns) / 1e9)
log = logging.getLogger(__name__)


class HealthBoard:
    """The latest DriverHealth of every process, read from the bus by a background thread (each with the time the
    board last read it; how old it is comes from the publisher's stamp: `health_age_s`)."""

    def __init__(self, config: CarConfig):
        self.config = config
        self._lock = threading.Lock()
        self._latest: dict[str, tuple[DriverHealth, float]] = {}
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._poll, daemon=True, name="health-board")

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()

    def _poll(self) -> None:
        from daemon.bus.pubsub import open_subscriber  # the bus is only needed when serving a live daemon

        subscribers = {}
        while not self._stop.is_set():
            for name in topic_table(self.config):
                if not name.startswith("health/"):
                    continue
                if name not in subscribers:
                    try:
                        subscribers[name] = open_subscriber(self.config, name, start="latest")
                    except (FileNotFoundError, OSError):
                        continue
                msg = subscribers[name].latest(copy=True)
                if msg is not None:
                    self.update(msg)
            self._stop.wait(0.2)
        for sub in subscribers.values():
            sub.close()

    def update(self, health: DriverHealth, received_at: float | None = None) -> None:
        with self._lock:
            self._latest[health.process] = (health, time.monotonic() if received_at is None else received_at)

    def snapshot(self) -> dict[str, tuple[DriverHealth, float]]:
        with self._lock:
            return dict(self._latest)


def _detail(health: DriverHealth) -> dict | None:
    """A health detail as JSON: {} when it is not JSON (plain text), None when it looks like JSON but cannot be read
    (cut off, a number past Python's digit limit, nested past the recursion limit)."""
    if not health.detail.startswith("{"):
        return {}
    try:
        return json.loads(health.detail)
    except (ValueError, RecursionError):  # JSONDecodeError is a ValueError
        return None


def _number(value: object) -> float | None:
    """A number as a float; None for another shape, or an integer past a float."""
    return float(value) if isinstance(value, float) or type(value) is int and abs(value) <= sys.float_info.max else None


def _numbers(value: object) -> tuple[dict[str, float], int]:
    """A detail's {label: number} (what /metrics exports), and how many of its entries were not numbers (a value
    of another shape counts as one): those are skipped, counted, and do not cost the other metrics."""
    if not isinstance(value, dict):
        return {}, 1
    numbers = {str(k): _number(v) for k, v in value.items()}
    good = {k: v for k, v in numbers.items() if v is not None}
    return good, len(value) - len(good)


def _flags(value: dict[str, object]) -> tuple[dict[str, float], int]:
    """{label: true/false} as 1/0, and how many entries were not booleans (skipped and counted)."""
    good = {k: float(v) for k, v in value.items() if isinstance(v, bool)}
    return good, len(value) - len(good)


def _restarts(detail: dict) -> tuple[dict[str, float], int]:
    """The supervisor's restart count per process, and how many entries were badly shaped."""
    processes = detail.get("processes", {})
    if not isinstance(processes, dict):
        return {}, 1
    return _numbers({name: info.get("restarts", 0) if isinstance(info, dict) else None
                     for name, info in processes.items()})


def status_document(config: CarConfig, board: HealthBoard) -> dict:
    now_ns = time.monotonic_ns()
    processes = {}
    for name, (h, _) in sorted(board.snapshot().items()):
        entry = asdict(h)
        entry.pop("detail")
        entry["health_age_s"] = round(health_age_s(h, now_ns), 3)
        entry["detail"] = _detail(h) or h.detail
        processes[name] = entry
    supervisor = processes.get("supervisor", {}).get("detail", {})
    recorder = processes.get("recorder", {}).get("detail", {})
    mapper = processes.get("mapper", {}).get("detail", {})
    ready, why = readiness(config, board)
    return {
        "ready": ready,
        "not_ready_because": why,
        "processes": processes,
        "supervisor": supervisor if isinstance(supervisor, dict) else {},
        "recorder": recorder if isinstance(recorder, dict) else {},
        "mapping": mapper if isinstance(mapper, dict) else {},
    }


def readiness(config: CarConfig, board: HealthBoard, max_health_age_s: float = 3.0) -> tuple[bool, list[str]]:
    """Ready only when every required driver reports `ok` (delivering at its expected rate) in a health message it
    published within `max_health_age_s` (a stopped or hung driver's last one grows old)."""
    now_ns = time.monotonic_ns()
    snapshot = board.snapshot()
    problems = []
    for process in required_drivers(config):
        if process not in snapshot:
            problems.append(f"{process}: no health yet")
            continue
        h, _ = snapshot[process]
        age = health_age_s(h, now_ns)
        if age > max_health_age_s:
            problems.append(f"{process}: health is {age:.1f} s old")
        elif h.state != "ok":
            problems.append(f"{process}: {h.state} ({h.rate_hz:.1f} Hz)")
    return not problems, problems


RECORDER_GAUGES = {  # /status recorder detail key -> (gauge name, help): its state now
    "disk_free_bytes": ("roadlog_recorder_disk_free_bytes", "free bytes on the recorder's disk (last check)"),
    "disk_full": ("roadlog_recorder_disk_full", "1 while the recorder is paused for lack of disk"),
    "segment_open": ("roadlog_recorder_segment_open", "1 while a segment is open for writing"),
}
RECORDER_COUNTERS = {  # /status recorder detail key -> (counter name without _total, help): counts since it started
    "segments_closed": ("roadlog_recorder_segments_closed", "segments closed"),
    "segments_deleted": ("roadlog_recorder_segments_deleted", "closed segments the disk policy deleted"),
    "segments_quarantined": ("roadlog_recorder_segments_quarantined", "unclosed segments that could not be read in "
                             "full, kept as .mcap.damaged"),
}


class _BoardCollector:
    """Everything /metrics shows, made from the board at each scrape. Counts are counters (`*_total`), states are
    gauges; the recorder's per-topic counters have a series for every logged topic from the start (0 until the
    recorder counts one), and the restarts one for every process the supervisor runs."""

    def __init__(self, board: HealthBoard, refused=lambda: 0, request_timeouts=lambda: 0):
        self.board = board
        self.refused = refused  # connections the server answered 503 (all its threads busy)
        self.request_timeouts = request_timeouts  # requests cut off at their deadline
        self.logged_topics = sorted(name for name, t in topic_table(board.config).items() if t.logged)

    def collect(self):
        gauges = {
            "rate_hz": GaugeMetricFamily("roadlog_rate_hz", "messages per second published", labels=["process"]),
            "age": GaugeMetricFamily("roadlog_last_message_age_seconds", "age of the last message",
                                     labels=["process"]),
            "up": GaugeMetricFamily("roadlog_process_ok", "1 when the process reports ok", labels=["process"]),
        }
        counters = {k: CounterMetricFamily(f"roadlog_{k}", f"{k} messages or events", labels=["process"])
                    for k in ("received", "published", "dropped", "rejected", "errors", "sequence_gaps")}
        lost = CounterMetricFamily("roadlog_recorder_lost_messages", "messages the recorder lost (overwritten on "
                                   "the bus before it read them, or dropped for lack of disk)", labels=["topic"])
        written = CounterMetricFamily("roadlog_recorder_written_messages", "messages written to the log",
                                      labels=["topic"])
        recorder_gauges = {k: GaugeMetricFamily(name, text) for k, (name, text) in RECORDER_GAUGES.items()}
        recorder_counters = {k: CounterMetricFamily(name, text) for k, (name, text) in RECORDER_COUNTERS.items()}
        policy = GaugeMetricFamily("roadlog_recorder_disk_policy", "the recorder's disk policy since it started: "
                                   "deleted_segments, deleted_drive_s (seconds of drive), deleted_bytes, "
                                   "deletions_undone (space another program took), held_off_s, at_floor",
                                   labels=["figure"])
        restarts = CounterMetricFamily("roadlog_process_restarts", "restarts by the supervisor", labels=["process"])
        malformed = CounterMetricFamily("roadlog_status_malformed_details", "health detail entries of the wrong "
                                        "shape, skipped (in the latest health of each process)", labels=["process"])
        recorder_seen = False
        for name, (h, _) in sorted(self.board.snapshot().items()):
            gauges["rate_hz"].add_metric([name], h.rate_hz)
            gauges["age"].add_metric([name], h.last_message_age_s if h.last_message_age_s != float("inf") else -1)
            gauges["up"].add_metric([name], 1.0 if h.state == "ok" else 0.0)
            for k, fam in counters.items():
                fam.add_metric([name], getattr(h, k))
            detail = _detail(h)
            bad = 0 if detail is not None else 1  # one that cannot be read counts once, and shows nothing
            detail = detail or {}
            if name == "recorder":
                recorder_seen = True
                for family, key in ((lost, "lost"), (written, "written")):
                    figures, wrong = _numbers(detail.get(key, {}))
                    bad += wrong
                    for topic in sorted(set(self.logged_topics) | set(figures)):
                        family.add_metric([topic], figures.get(topic, 0.0))
                figures, wrong = _numbers({k: detail.get(k, 0) for k in ("disk_free_bytes", *RECORDER_COUNTERS)})
                flags, wrong_flags = _flags({"disk_full": detail.get("disk_full", False),
                                             "segment_open": detail.get("segment") is not None})
                bad += wrong + wrong_flags
                for k, n in {**figures, **flags}.items():
                    (recorder_gauges.get(k) or recorder_counters[k]).add_metric([], n)
                figures, wrong = _numbers(detail.get("disk_policy", {}))
                bad += wrong
                for figure, n in figures.items():
                    policy.add_metric([figure], n)
            if name == "supervisor":
                figures, wrong = _restarts(detail)
                bad += wrong
                for proc, n in figures.items():
                    restarts.add_metric([proc], n)
            malformed.add_metric([name], bad)
        if not recorder_seen:  # the series exist, at 0, before the recorder's first report
            for family in (lost, written):
                for topic in self.logged_topics:
                    family.add_metric([topic], 0.0)
        yield from gauges.values()
        yield from counters.values()
        yield from (lost, written, *recorder_gauges.values(), *recorder_counters.values(), policy, restarts, malformed)
        yield CounterMetricFamily("roadlog_status_refused_connections", "connections answered 503 because every "
                                  "server thread was busy", value=self.refused())
        yield CounterMetricFamily("roadlog_status_request_timeouts", "connections closed because their request was "
                                  "not read whole within its deadline", value=self.request_timeouts())


class _DeadlineSocketReader(io.RawIOBase):
    """A connection's bytes, each read waiting at most the idle timeout and, while a request is being read, no
    longer than its deadline: a client sending a byte now and then cannot stretch one request out."""

    def __init__(self, sock: socket.socket, idle_timeout_s: float, on_deadline=lambda: None):
        self.sock, self.idle_timeout_s, self.on_deadline = sock, idle_timeout_s, on_deadline
        self.deadline: float | None = None  # monotonic time by which the request must be read

    def readable(self) -> bool:
        return True

    def readinto(self, buffer) -> int:
        timeout, by_deadline = self.idle_timeout_s, False
        if self.deadline is not None:
            left = self.deadline - time.monotonic()
            timeout, by_deadline = min(timeout, max(left, 0.0)), left < timeout
        try:
            if timeout <= 0:
                raise TimeoutError("the request was not read whole within its deadline")
            self.sock.settimeout(timeout)
            return self.sock.recv_into(buffer)
        except TimeoutError:
            if by_deadline:
                self.deadline = None
                self.on_deadline()
            raise


def make_handler(config: CarConfig, board: HealthBoard, registry: CollectorRegistry, data_folder: Path,
                 idle_timeout_s: float = IDLE_TIMEOUT_S, request_deadline_s: float = REQUEST_DEADLINE_S):
    previews = {f"/preview/{name}.png": name for name in PREVIEWS}

    class Handler(BaseHTTPRequestHandler):
        server_version = "roadlog-status"
        timeout = idle_timeout_s  # a connection silent this long is closed (its thread ends)

        def log_message(self, fmt, *args):  # keep the journal quiet: one line per request is noise
            pass

        def setup(self):
            super().setup()
            self._reader = _DeadlineSocketReader(self.connection, idle_timeout_s,
                                                 self.server.count_request_timeout)
            self.rfile = io.BufferedReader(self._reader)

        def handle_one_request(self):
            """Wait (idle timeout) for a request's first byte, then read it whole within its deadline."""
            try:
                if not self.rfile.peek(1):  # the client closed the connection
                    self.close_connection = True
                    return
            except OSError:  # idle too long (TimeoutError), or reset
                self.close_connection = True
                return
            self._reader.deadline = time.monotonic() + request_deadline_s
            try:
                super().handle_one_request()  # answers nothing and closes on the deadline's TimeoutError
            finally:
                self._reader.deadline = None

        def parse_request(self):
            parsed = super().parse_request()  # line and headers read: the deadline is met
            self._reader.deadline = None
            self.connection.settimeout(idle_timeout_s)
            return parsed

        def _send(self, code: int, body: bytes, content_type: str) -> None:
            self.send_response(code)
            self.send_header("Content-Type", content_type)
            self.send_header("Content-Length", str(len(body)))
            self.send_header("Cache-Control", "no-store")
            self.end_headers()
            if self.command != "HEAD":
                self.wfile.write(body)

        def _json(self, code: int, doc: object) -> None:
            self._send(code, json.dumps(doc, indent=1, default=str).encode(), "application/json")

        def do_GET(self):  # noqa: N802 - http.server's naming
            path = self.path.split("?", 1)[0]
            if path == "/livez":
                self._send(200, b"ok\n", "text/plain")
            elif path == "/readyz":
                ready, why = readiness(config, board)
                self._json(200 if ready else 503, {"ready": ready, "not_ready_because": why})
            elif path == "/status":
                self._json(200, status_document(config, board))
            elif path == "/metrics":
                self._send(200, generate_latest(registry), "text/plain; version=0.0.4; charset=utf-8")
            elif path in previews:
                file = preview_dir(data_folder) / f"{previews[path]}.png"
                try:
                    body = file.read_bytes()
                except OSError:
                    self._send(404, b"no preview yet\n", "text/plain")
                    return
                self._send(200, body, "image/png")
            else:
                self._send(404, b"not found\n", "text/plain")

        do_HEAD = do_GET  # noqa: N815

        def _read_only(self):
            self._send(HTTPStatus.METHOD_NOT_ALLOWED, b"read-only\n", "text/plain")

        do_POST = do_PUT = do_DELETE = do_PATCH = _read_only  # noqa: N815

    return Handler


class StatusHTTPServer(ThreadingHTTPServer):
    """One thread per connection, at most `max_threads` at once: a connection beyond them is answered 503 by the
    accepting thread itself (without waiting for its request) and closed once its request is read or after
    REFUSED_LINGER_S, so many slow clients cannot make unbounded threads. Refusals are counted (`refused`)."""

    request_queue_size = LISTEN_BACKLOG  # socketserver's default of 5 left clients waiting seconds under load

    def __init__(self, address, handler, max_threads: int = MAX_THREADS):
        self.max_threads = max_threads  # before binding: a failed bind closes the server (server_close)
        self.refused = 0
        self.request_timeouts = 0  # requests not read whole within their deadline (the connection closed)
        self._timeouts_lock = threading.Lock()
        self._slots = threading.BoundedSemaphore(max_threads)
        self._refused: deque[tuple[float, socket.socket]] = deque()  # answered, waiting for the client's bytes
        super().__init__(address, handler)

    def process_request(self, request, client_address):
        if not self._slots.acquire(blocking=False):
            self._refuse(request)
            return
        try:
            super().process_request(request, client_address)
        except BaseException:  # no thread started: give its slot back
            self._slots.release()
            raise

    def count_request_timeout(self) -> None:
        with self._timeouts_lock:
            self.request_timeouts += 1

    def process_request_thread(self, request, client_address):
        try:
            super().process_request_thread(request, client_address)
        finally:
            self._slots.release()

    def _refuse(self, request: socket.socket) -> None:
        self.refused += 1
        try:
            request.setblocking(False)
            request.send(BUSY_RESPONSE)
            request.shutdown(socket.SHUT_WR)
        except OSError:
            self.shutdown_request(request)
            return
        # closing now, with the request still to come, would reset the connection and lose the answer
        self._refused.append((time.monotonic() + REFUSED_LINGER_S, request))
        while len(self._refused) > LISTEN_BACKLOG:
            self._refused.popleft()[1].close()

    def service_actions(self) -> None:
        """Between accepts: close the refused connections whose client has sent its request (or that waited long)."""
        now = time.monotonic()
        for _ in range(len(self._refused)):
            deadline, sock = self._refused.popleft()
            try:
                done = sock.recv(65536) == b"" or now > deadline
            except BlockingIOError:
                done = now > deadline
            except OSError:
                done = True
            if done:
                sock.close()
            else:
                self._refused.append((deadline, sock))

    def server_close(self) -> None:
        super().server_close()
        while self._refused:
            self._refused.popleft()[1].close()


def make_server(config: CarConfig, board: HealthBoard, data_folder: Path, port: int | None = None,
                idle_timeout_s: float = IDLE_TIMEOUT_S, max_threads: int = MAX_THREADS,
                request_deadline_s: float = REQUEST_DEADLINE_S) -> StatusHTTPServer:
    registry = CollectorRegistry()
    server = StatusHTTPServer((config.status.bind_address, config.status.port if port is None else port),
                              make_handler(config, board, registry, data_folder, idle_timeout_s, request_deadline_s),
                              max_threads)
    registry.register(_BoardCollector(board, lambda: server.refused, lambda: server.request_timeouts))
    server.daemon_threads = True
    return server


@reports_config_errors
def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="roadlog-status", description=__doc__)
    parser.add_argument("--config", required=True)
    parser.add_argument("--port", type=int, default=None, help="override the config's port")
    parser.add_argument("--output-dir", help="log and map folder (default: recorder.output_dir)")
    args = parser.parse_args(argv)
    setup_logging("status")
    config = load_config(args.config)
    board = HealthBoard(config)
    port = config.status.port if args.port is None else args.port
    try:
        server = make_server(config, board, data_dir(config, args.output_dir), port)
    except (OSError, OverflowError) as exc:  # the port is taken or not 0-65535 (--port), the address not this host's
        raise ConfigError(f"{args.config}: status endpoint {config.status.bind_address}:{port}: "
                          f"{getattr(exc, 'strerror', None) or exc}") from None
    board.start()
    on_signals(lambda _signum: server.shutdown())  # SIGTERM, SIGINT: the relay waits until serve_forever ends
    log.info("status endpoint on http://%s:%s", *server.server_address[:2])
    server.serve_forever(poll_interval=0.2)
    board.stop()
    server.server_close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
