"""The status endpoint over real HTTP: liveness, readiness, JSON status, Prometheus metrics, previews, 404s."""

import json
import socket
import threading
import time
import urllib.error
import urllib.request

import numpy as np
import pytest
from prometheus_client.parser import text_string_to_metric_families

from daemon.bus.pubsub import open_publisher, unlink_all
from daemon.processes.status_server import HealthBoard, make_server
from daemon.spine.data_layout import preview_dir
from daemon.spine.health import HealthCounters
from daemon.spine.process_table import required_drivers
from daemon.spine.topics import LIDAR_VIEW, health_topic, topic_table
from tests.daemon_fixtures import private_config


@pytest.fixture
def served(tmp_path):
    cfg, _ = private_config(tmp_path, recorder={"output_dir": str(tmp_path / "logs")})
    board = HealthBoard(cfg)
    server = make_server(cfg, board, tmp_path / "logs", port=0)
    thread = threading.Thread(target=server.serve_forever, kwargs={"poll_interval": 0.05}, daemon=True)
    thread.start()
    base = f"http://127.0.0.1:{server.server_address[1]}"
    yield cfg, board, base, tmp_path / "logs"
    board.stop()
    server.shutdown()
    server.server_close()
    unlink_all(cfg)


def _get(url):
    try:
        with urllib.request.urlopen(url, timeout=5) as r:
            return r.status, r.headers.get("Content-Type"), r.read()
    except urllib.error.HTTPError as e:
        return e.code, e.headers.get("Content-Type"), e.read()


def _healthy(process, rate=10.0, detail=""):
    h = HealthCounters(process, expected_rate_hz=rate)
    now = time.monotonic_ns()
    for i in range(int(rate * 2)):
        h.count_published(1, now - int(i * 1e9 / rate))
    snap = h.snapshot(now)
    snap.detail = detail
    return snap


def test_readiness_waits_for_one_driver_per_configured_sensor(tmp_path):
    full, _ = private_config(tmp_path)
    assert required_drivers(full) == ["camera_front_left", "camera_front_right", "camera_front_wide", "can", "gnss",
                                      "lidar"]
    data = full.model_dump(mode="json")
    data["sensors"].update(lidar=None, can=None, cameras=data["sensors"]["cameras"][:1])
    assert required_drivers(type(full).model_validate(data)) == ["camera_front_wide", "gnss"]
    # every sensor topic comes from a driver readiness waits for, and no driver goes without one (the viewing clouds
    # are made from the Lidar's packets, not a sensor's topic: readiness does not wait for them)
    assert required_drivers(full) == sorted({t.source for t in topic_table(full).values()
                                             if t.name.startswith(("camera/", "lidar/", "gnss/", "can/"))
                                             and t.name != LIDAR_VIEW})
    assert topic_table(full)[LIDAR_VIEW].source == "lidar_view"


def test_livez_and_readiness_follow_the_drivers(served):
    cfg, board, base, _ = served
    assert _get(base + "/livez")[0] == 200
    code, _, body = _get(base + "/readyz")
    assert code == 503 and "no health yet" in body.decode()
    for process in required_drivers(cfg):
        board.update(_healthy(process))
    assert _get(base + "/readyz")[0] == 200
    slow = _healthy("lidar", rate=640.0)
    slow.rate_hz, slow.state = 100.0, "degraded"
    board.update(slow)
    code, _, body = _get(base + "/readyz")
    assert code == 503 and "lidar: degraded" in body.decode()


def test_status_json_and_metrics(served):
    cfg, board, base, _ = served
    for process in required_drivers(cfg):
        board.update(_healthy(process))
    board.update(_healthy("recorder", detail=json.dumps(
        {"segment": "x.mcap.open", "disk_free_bytes": 123, "written": {"imu": 500}, "lost": {"imu": 2}})))
    board.update(_healthy("supervisor", detail=json.dumps(
        {"processes": {"lidar": {"state": "running", "restarts": 2}}})))
    code, ctype, body = _get(base + "/status")
    doc = json.loads(body)
    assert code == 200 and ctype == "application/json"
    assert doc["recorder"]["lost"] == {"imu": 2} and doc["recorder"]["disk_free_bytes"] == 123
    assert doc["processes"]["lidar"]["rate_hz"] == pytest.approx(10.0, abs=1)
    assert doc["supervisor"]["processes"]["lidar"]["restarts"] == 2
    code, ctype, body = _get(base + "/metrics")
    text = body.decode()
    assert code == 200 and ctype.startswith("text/plain")
    assert 'roadlog_recorder_lost_messages_total{topic="imu"} 2.0' in text
    assert 'roadlog_process_restarts_total{process="lidar"} 2.0' in text
    assert 'roadlog_published_total{process="gnss"}' in text


def _families(base: str) -> dict:
    """/metrics over HTTP, parsed by prometheus_client's own parser: {family name: (type, {labels: value})}."""
    code, _, body = _get(base + "/metrics")
    assert code == 200
    families = text_string_to_metric_families(body.decode())
    return {f.name: (f.type, {tuple(sorted(s.labels.items())): s.value for s in f.samples
                              if not s.name.endswith("_created")}) for f in families}


def test_metrics_counts_are_counters_from_zero_and_the_disk_and_segments_are_exported(served):
    """Prometheus conventions, checked with its own parser: counts are counters named *_total, every logged topic
    has its lost and written series at 0 before anything is lost (so `rate()` and alerts on loss have a series),
    and the recorder's disk and segment figures of /status are on /metrics too."""
    cfg, board, base, _ = served
    logged = sorted(name for name, t in topic_table(cfg).items() if t.logged)
    families = _families(base)  # nothing reported yet
    for name in ("roadlog_recorder_lost_messages", "roadlog_recorder_written_messages"):
        kind, samples = families[name]
        assert kind == "counter" and samples == {(("topic", t),): 0.0 for t in logged}, name
    board.update(_healthy("recorder", detail=json.dumps(
        {"segment": "x.mcap.open", "segments_closed": 4, "segments_deleted": 1, "segments_quarantined": 0,
         "disk_free_bytes": 5e9, "disk_full": True, "written": {"imu": 500}, "lost": {"imu": 2}})))
    board.update(_healthy("supervisor", detail=json.dumps(
        {"processes": {"lidar": {"state": "running", "restarts": 2}, "gnss": {"state": "running", "restarts": 0}}})))
    families = _families(base)
    lost = families["roadlog_recorder_lost_messages"]
    assert lost[0] == "counter" and lost[1][(("topic", "imu"),)] == 2.0 and lost[1][(("topic", "gnss/fix"),)] == 0.0
    assert set(lost[1]) == {(("topic", t),) for t in logged}
    assert families["roadlog_recorder_written_messages"][1][(("topic", "imu"),)] == 500.0
    assert families["roadlog_process_restarts"] == ("counter", {(("process", "gnss"),): 0.0,
                                                                (("process", "lidar"),): 2.0})
    assert families["roadlog_recorder_disk_free_bytes"] == ("gauge", {(): 5e9})
    assert families["roadlog_recorder_disk_full"] == ("gauge", {(): 1.0})
    assert families["roadlog_recorder_segment_open"] == ("gauge", {(): 1.0})
    for name, n in (("segments_closed", 4.0), ("segments_deleted", 1.0), ("segments_quarantined", 0.0)):
        assert families[f"roadlog_recorder_{name}"] == ("counter", {(): n}), name
    assert families["roadlog_status_malformed_details"][1] == {(("process", "recorder"),): 0.0,
                                                              (("process", "supervisor"),): 0.0}
    # no count is left a gauge, and every counter's sample is *_total
    body = _get(base + "/metrics")[2].decode()
    assert not [line for line in body.splitlines() if line.startswith("# TYPE") and line.endswith(" gauge")
                and any(w in line for w in ("lost", "written", "restarts", "segments_"))]


def test_previews_and_404s(served):
    cfg, _, base, data = served
    assert _get(base + "/preview/rgb.png")[0] == 404  # nothing mapped yet
    import cv2

    preview_dir(data).mkdir(parents=True)
    ok, png = cv2.imencode(".png", np.full((8, 8, 3), 200, np.uint8))
    (preview_dir(data) / "rgb.png").write_bytes(png.tobytes())
    code, ctype, body = _get(base + "/preview/rgb.png")
    assert code == 200 and ctype == "image/png" and body == png.tobytes()
    for path in ["/nope", "/preview/../../car.yaml", "/preview/%2e%2e/rgb.png", "/status/",
                 "/preview/rgb.png/../rgb.png", "/preview/", "/metrics/x"]:
        assert _get(base + path)[0] == 404, path
    req = urllib.request.Request(base + "/status", method="POST", data=b"x")
    with pytest.raises(urllib.error.HTTPError) as err:
        urllib.request.urlopen(req, timeout=5)
    assert err.value.code == 405


def test_board_reads_health_from_the_bus(served):
    cfg, board, base, _ = served
    board.start()
    pub = open_publisher(cfg, health_topic("gnss"))
    deadline = time.monotonic() + 10
    doc = {}
    while time.monotonic() < deadline:
        pub.publish(_healthy("gnss"))
        doc = json.loads(_get(base + "/status")[2])
        if "gnss" in doc["processes"]:
            break
        time.sleep(0.1)
    pub.close()
    assert doc["processes"]["gnss"]["state"] == "ok"


def test_metrics_answer_despite_badly_shaped_health_details(served):
    """One process's odd detail is skipped and counted; /metrics still answers with everything else."""
    cfg, board, base, _ = served
    board.update(_healthy("recorder", detail=json.dumps({"lost": [1, 2], "written": {"imu": "many", "gnss": 3}})))
    board.update(_healthy("supervisor", detail=json.dumps({"processes": {"lidar": "up", "gnss": {"restarts": 1}}})))
    code, _, body = _get(base + "/metrics")
    text = body.decode()
    assert code == 200
    assert 'roadlog_recorder_written_messages_total{topic="gnss"} 3.0' in text
    assert 'roadlog_process_restarts_total{process="gnss"} 1.0' in text
    assert 'roadlog_status_malformed_details_total{process="recorder"} 2.0' in text
    assert 'roadlog_status_malformed_details_total{process="supervisor"} 1.0' in text
    assert 'roadlog_published_total{process="recorder"}' in text


@pytest.mark.parametrize("detail, gnss_written", [
    ('{"written": {"imu": 1' + "0" * 400 + ', "gnss": 3}}', 3.0),  # past a float: OverflowError in float()
    ('{"disk_policy": {"deleted_bytes": -1' + "0" * 400 + '}, "written": {"gnss": 3}}', 3.0),
    ('{"written": {"imu": 1' + "0" * 5000 + ', "gnss": 3}}', None),  # past int's digit limit: ValueError in json
    ('{"a": ' * 100_000 + "1" + "}" * 100_000, None),  # RecursionError in json
    ('{"written": {"gnss": 3}', None),  # cut off: not JSON (was taken as an empty detail, uncounted)
], ids=["int-past-float", "negative-past-float", "past-digit-limit", "nested-past-recursion-limit", "cut-off"])
def test_metrics_and_status_answer_despite_a_detail_json_cannot_take(served, detail, gnss_written):
    """A detail with a number past a float, one past Python's digit limit or nested past the recursion limit made
    /metrics (and /status) close with no answer: the entry, or the detail that cannot be read, is skipped and
    counted like other bad shapes, and the rest is answered."""
    cfg, board, base, _ = served
    board.update(_healthy("recorder", detail=detail))
    code, _, body = _get(base + "/metrics")
    text = body.decode()
    assert code == 200
    assert 'roadlog_status_malformed_details_total{process="recorder"} 1.0' in text
    if gnss_written is None:  # nothing of a detail that cannot be read
        assert 'roadlog_recorder_written_messages_total{topic="gnss"}' not in text
    else:
        assert f'roadlog_recorder_written_messages_total{{topic="gnss"}} {gnss_written}' in text
    code, _, body = _get(base + "/status")
    assert code == 200 and "recorder" in json.loads(body)["processes"]


def test_idle_connections_are_closed_and_many_clients_are_served(tmp_path):
    cfg, _ = private_config(tmp_path)
    board = HealthBoard(cfg)
    server = make_server(cfg, board, tmp_path / "logs", port=0, idle_timeout_s=0.5)
    assert server.request_queue_size >= 128
    threading.Thread(target=server.serve_forever, kwargs={"poll_interval": 0.05}, daemon=True).start()
    host, port = server.server_address[:2]
    try:
        idle = [socket.create_connection((host, port), timeout=5) for _ in range(20)]  # connect, send nothing
        time.sleep(1.0)
        assert all(s.recv(1) == b"" for s in idle)  # the server hung up on each (recv would block otherwise)
        for s in idle:
            s.close()
        answers: list[int] = []
        lock = threading.Lock()

        def ask() -> None:
            code, _, _ = _get(f"http://{host}:{port}/livez")
            with lock:
                answers.append(code)

        clients = [threading.Thread(target=ask) for _ in range(200)]
        for c in clients:
            c.start()
        for c in clients:
            c.join(30)
        assert answers.count(200) == 200
    finally:
        server.shutdown()
        server.server_close()


def test_slow_clients_cannot_make_more_threads_than_the_cap(tmp_path):
    cfg, _ = private_config(tmp_path)
    server = make_server(cfg, HealthBoard(cfg), tmp_path / "logs", port=0, idle_timeout_s=30.0, max_threads=8)
    threading.Thread(target=server.serve_forever, kwargs={"poll_interval": 0.05}, daemon=True).start()
    host, port = server.server_address[:2]
    before = threading.active_count()
    slow = []
    try:
        for _ in range(40):  # each sends half a request line and then nothing: a thread waits on every one
            s = socket.create_connection((host, port), timeout=5)
            s.sendall(b"GET /liv")
            slow.append(s)
        time.sleep(0.5)
        assert threading.active_count() - before <= 8  # the old server: one thread per connection, 40
        refused = []
        for s in slow:  # those beyond the cap were answered at once, without waiting for their request
            s.settimeout(0.05)
            try:
                refused.append(s.recv(4096))
            except TimeoutError:
                pass
        assert len(refused) == 32 and all(r.startswith(b"HTTP/1.0 503") for r in refused)
        answer = socket.create_connection((host, port), timeout=5)
        answer.sendall(b"GET /livez HTTP/1.0\r\n\r\n")
        assert answer.recv(4096).startswith(b"HTTP/1.0 503")  # still full: refused, and the answer arrives
        answer.close()
        for s in slow:
            s.close()
        time.sleep(0.5)  # the held threads see their clients gone and end
        code, _, body = _get(f"http://{host}:{port}/livez")
        assert (code, body) == (200, b"ok\n")
        assert "roadlog_status_refused_connections_total 33.0" in _get(f"http://{host}:{port}/metrics")[2].decode()
    finally:
        server.shutdown()
        server.server_close()


def _trickle(sock: socket.socket, request: bytes, stop: threading.Event, every_s: float = 0.5) -> float | None:
    """Send the request one byte every `every_s`; the time the server closed the connection (None: it never did)."""
    start = time.monotonic()
    for byte in request:
        try:
            sock.sendall(bytes([byte]))
        except OSError:  # reset: the server closed it
            return time.monotonic() - start
        if stop.wait(every_s):
            return None
        sock.setblocking(False)
        try:
            if sock.recv(4096) == b"":
                return time.monotonic() - start
        except BlockingIOError:
            pass
        except OSError:
            return time.monotonic() - start
        finally:
            sock.setblocking(True)
    return None


def test_a_trickling_client_is_cut_off_at_its_request_deadline_and_others_are_answered(tmp_path):
    cfg, _ = private_config(tmp_path)
    server = make_server(cfg, HealthBoard(cfg), tmp_path / "logs", port=0, idle_timeout_s=30.0, max_threads=2,
                         request_deadline_s=2.0)
    threading.Thread(target=server.serve_forever, kwargs={"poll_interval": 0.05}, daemon=True).start()
    host, port = server.server_address[:2]
    request = b"GET /livez HTTP/1.0\r\nHost: x\r\n\r\n"  # 33 bytes: 16 s at one byte per 0.5 s
    stop = threading.Event()
    closed_after: dict[int, float | None] = {}
    tricklers = [socket.create_connection((host, port), timeout=5) for _ in range(2)]  # both server threads
    threads = [threading.Thread(target=lambda i=i: closed_after.__setitem__(i, _trickle(tricklers[i], request, stop)))
               for i in range(2)]
    try:
        for t in threads:
            t.start()
        time.sleep(0.7)
        busy = socket.create_connection((host, port), timeout=5)  # every thread held: refused for now
        busy.sendall(b"GET /livez HTTP/1.0\r\n\r\n")
        assert busy.recv(4096).startswith(b"HTTP/1.0 503")
        busy.close()
        for t in threads:
            t.join(6.0)
        assert all(not t.is_alive() for t in threads)  # each was hung up on, well before its 16 s trickle ended
        assert all(after is not None and 1.5 <= after <= 4.0 for after in closed_after.values()), closed_after
        code, _, body = _get(f"http://{host}:{port}/livez")  # the threads are free again: a normal client is served
        assert (code, body) == (200, b"ok\n")
        quick = socket.create_connection((host, port), timeout=5)  # sent in pieces, whole within the deadline
        for piece in (b"GET /li", b"vez HTTP/1.0\r\n", b"\r\n"):
            quick.sendall(piece)
            time.sleep(0.3)
        assert quick.recv(4096).startswith(b"HTTP/1.0 200")
        quick.close()
        assert "roadlog_status_request_timeouts_total 2.0" in _get(f"http://{host}:{port}/metrics")[2].decode()
    finally:
        stop.set()
        for s in tricklers:
            s.close()
        server.shutdown()
        server.server_close()
