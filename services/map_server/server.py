"""`gmmap server`: one process holding a fleet's map, fed over Zenoh, served over Zenoh and HTTP.

Start-up: open the store, replay it into the FleetMap, then open the Zenoh session (scan and
pose subscribers, occupancy and point queryables) and the HTTP app under uvicorn. SIGTERM/SIGINT stop
the HTTP server, undeclare the Zenoh entities, drain the ingest queue and close the session.
"""

from __future__ import annotations

import logging
import ssl
import sys
import threading
import time
from concurrent.futures import Future, ThreadPoolExecutor

import zenoh

from gmm_core import Grid
from gmm_core.reconstruct import ReconstructionConfig
from protocol import (
    MapQuery,
    MapReply,
    PointQuery,
    PointReply,
    ProtocolError,
    decode,
    encode,
    inventory_key,
    inventory_wildcard,
    occupancy_key,
    parse_key,
    points_key,
    poses_wildcard,
    scan_wildcard,
)
from services.api import params  # one set of limits for both APIs
from services.api.points import evaluate
from services.config import summary
from services.host import release_free_memory
from services.ros2.config import Ros2Config
from services.stopping import POLL_S, StopSignal
from services.zenoh_config import zenoh_config

from .collector import freeze_survivors
from .config import ServerConfig, split_address
from .fleet_map import FleetMap
from .ingest import Ingest
from .state import ServerState
from .store import Store
from .tile_updates import BUSY_SAMPLES_PER_CELL
from .tokens import TokenFile
from .tracers import TracingStopped
from .warmup import warm_kernels

log = logging.getLogger("gmmap.server")

RELEASE_MEMORY_S = 10.0  # s between handing freed memory back to the OS (services.host.release_free_memory)
# s from SIGTERM / SIGINT until a server that has not stopped exits anyway: what it acknowledged is
# committed (SQLite, WAL), so ending mid-stop loses nothing acknowledged; it normally stops in 1-2 s.
STOP_DEADLINE_S = 10.0


def query_grid(query: MapQuery) -> Grid:
    """The grid of a MapQuery, within the limits the HTTP API also enforces.

    The cells are counted in Python integers before a Grid exists: Grid.from_bbox casts to int64,
    where a huge box wraps around to a small (or zero) cell count.
    """
    try:
        return params.grid(query.lo, query.hi, params.resolution(query.resolution))
    except params.ApiError as error:
        raise ProtocolError(error.field, error.message) from None


def _query_of(state: ServerState, payload: bytes, kind: type):
    """The query message of `kind` in `payload`, asked of this server's fleet; else ProtocolError."""
    query = decode(payload, expect=kind)
    if query.fleet != state.fleet:
        raise ProtocolError("fleet", f"this server holds fleet {state.fleet}, not {query.fleet}")
    return query


def _selected(state: ServerState, robots: tuple[str, ...] | None) -> tuple[str, ...] | None:
    """The robots a query names (None: every robot), refused as the HTTP API refuses them."""
    if robots is None:
        return None
    try:
        return params.named_robots(robots, state.fleet_map.unknown_robots, state.fleet)
    except params.ApiError as error:
        raise ProtocolError(error.field, error.message) from None


def answer(state: ServerState, payload: bytes) -> bytes:
    """MapQuery bytes -> MapReply bytes; ProtocolError or ValueError for a bad query."""
    query = _query_of(state, payload, MapQuery)
    grid = query_grid(query)
    robots = _selected(state, query.robots)
    started = time.perf_counter()
    prob = state.fleet_map.occupancy(grid, robots)
    state.metrics.query_seconds.observe(time.perf_counter() - started)
    return encode(MapReply(state.fleet, grid.origin, grid.resolution, prob))


def answer_points(state: ServerState, payload: bytes) -> bytes:
    """PointQuery bytes -> PointReply bytes, as `/v1/occupancy/points` answers (services/api/points.py:
    the same limits, auto's same choice); ProtocolError naming the field for a bad query."""
    query = _query_of(state, payload, PointQuery)
    try:
        resolution = params.resolution(query.resolution)
        params.check_dimension(query.dim, state.fleet_map.dim, "points")
        points = params.points(query.points, query.dim, "points")
        robots = _selected(state, None if query.robots is None else params.robots(list(query.robots)))
    except params.ApiError as error:
        raise ProtocolError(error.field, error.message) from None
    started = time.perf_counter()
    try:
        prob, method = evaluate(state.fleet_map, points, resolution, robots, query.method)
    except ValueError as error:
        raise ProtocolError("points", str(error)) from None
    state.metrics.query_seconds.observe(time.perf_counter() - started)
    return encode(PointReply(state.fleet, resolution, prob, method))


class ZenohSide:
    """The Zenoh session of a server: ingest subscribers, Ack publisher, occupancy and point queryables."""

    def __init__(self, state: ServerState, ingest: Ingest, config: zenoh.Config):
        self.state = state
        self.session = zenoh.open(config)
        # Queries run off Zenoh's threads so a slow map never stalls ingest; one worker because
        # the FleetMap traces one query at a time anyway.
        self._queries = ThreadPoolExecutor(max_workers=1, thread_name_prefix="gmmap-query")
        fleet = state.fleet
        on_sample = lambda sample: ingest.submit(str(sample.key_expr), sample.payload.to_bytes())  # noqa: E731
        self._subscribers = [
            self.session.declare_subscriber(scan_wildcard(fleet), on_sample),
            self.session.declare_subscriber(poses_wildcard(fleet), on_sample),
        ]
        self._queryables = [
            self.session.declare_queryable(
                occupancy_key(fleet), lambda q: self._queries.submit(self._reply, q, occupancy_key(fleet), answer)
            ),
            self.session.declare_queryable(
                points_key(fleet), lambda q: self._queries.submit(self._reply, q, points_key(fleet), answer_points)
            ),
            # answered on Zenoh's thread: one SQLite read, and a robot waits for it to resume
            self.session.declare_queryable(inventory_wildcard(fleet), self._inventory),
        ]

    def publish(self, key: str, payload: bytes) -> None:
        self.session.put(key, payload, congestion_control=zenoh.CongestionControl.DROP, express=True)

    def _reply(self, query: zenoh.Query, key: str, answer_bytes) -> None:
        """Answers `query` on `key` with answer_bytes(state, its payload) (answer, answer_points); a
        refused query is counted as a rejected message of its key's kind, by the field at fault."""
        with query:  # leaving the block finalises the query (the querier stops waiting)
            try:
                payload = query.payload
                if payload is None:
                    raise ProtocolError("payload", f"a query on {key} carries its query message")
                query.reply(key, answer_bytes(self.state, payload.to_bytes()))
            except (ProtocolError, ValueError) as error:
                field = error.field if isinstance(error, ProtocolError) else "value"
                self.state.metrics.rejected.labels(parse_key(key)[2], field).inc()
                query.reply_err(str(error))
            except TracingStopped:  # the server is stopping: no fault to log
                query.reply_err("server stopping: ask again once it is back")
            except Exception as error:  # noqa: BLE001 - reported to the querier, logged here
                log.exception("query on %s failed", key)
                query.reply_err(f"internal error: {type(error).__name__}")

    def _inventory(self, query: zenoh.Query) -> None:
        with query:
            try:
                fleet, robot, _, _ = parse_key(str(query.key_expr))
                inventory = self.state.store.inventory(fleet, robot)
                query.reply(inventory_key(fleet, robot), encode(inventory))
            except ProtocolError as error:
                query.reply_err(str(error))
            except Exception as error:  # noqa: BLE001 - reported to the querier, logged here
                log.exception("inventory query failed")
                query.reply_err(f"internal error: {type(error).__name__}")

    def stop_ingest(self) -> None:
        """Undeclare the subscribers (callback subscribers outlive their Python reference)."""
        for subscriber in self._subscribers:
            subscriber.undeclare()
        self._subscribers = []

    def close(self) -> None:
        self.stop_ingest()
        for queryable in self._queryables:
            queryable.undeclare()
        self._queries.shutdown(wait=False, cancel_futures=True)  # a long map query must not hold up a stop
        self.session.close()


def check_tls_files(cert: str, key: str) -> None:
    """OSError naming the files unless they are a PEM certificate and its key: said before the server
    starts, where uvicorn would only fail in its thread."""
    try:
        ssl.create_default_context(ssl.Purpose.CLIENT_AUTH).load_cert_chain(cert, key)
    except (OSError, ssl.SSLError) as error:
        raise OSError(
            f"--http-tls-cert {cert} --http-tls-key {key}: not a PEM certificate and its key ({error})"
        ) from None


def start_http(state: ServerState, options: ServerConfig, variance: float, tokens=None):
    """uvicorn on options.http in a thread, over TLS when options say so, with `tokens` (a TokenFile)
    if given; (server, thread), or None when the API is absent."""
    try:
        from services.api.app import create_app
        from services.api.limits import MAX_REQUEST_HEAD, JsonErrorH11
    except ImportError as error:
        log.warning("HTTP disabled: services.api.app is not available (%s)", error)
        return None
    import uvicorn

    host, port = split_address(options.http)
    # h11 refuses a request head (request line with its query string, and headers) over this size
    # with a 400, JSON as the app's errors (services/api/limits.py).
    config = uvicorn.Config(
        create_app(state, default_variance=variance, tokens=tokens),
        host=host,
        port=port,
        log_level="warning",
        lifespan="on",
        http=JsonErrorH11,
        h11_max_incomplete_event_size=MAX_REQUEST_HEAD,
        ssl_certfile=options.http_tls_cert,
        ssl_keyfile=options.http_tls_key,
        timeout_graceful_shutdown=1,  # a tile being traced is cut off rather than delay a stop
    )
    server = uvicorn.Server(config)
    # uvicorn leaves signal handling to the main thread when it runs elsewhere.
    thread = threading.Thread(target=server.run, name="gmmap-http", daemon=True)
    thread.start()
    while not server.started:
        if not thread.is_alive():
            raise OSError(f"HTTP server could not start on {options.http}")
        time.sleep(0.01)
    return server, thread


def http_banner(options: ServerConfig, tokens) -> str:
    scheme = "https" if options.http_tls else "http"
    who = f"{len(tokens.clients)} token clients" if tokens is not None else "no tokens"
    return f"{scheme}://{options.http} ({who})"


def warm_up(stop: StopSignal) -> float | None:
    """The seconds warm_kernels took, or None when a stop came first. It runs in a thread of its own
    while this one watches `stop`: on an empty numba cache it compiles for about a minute, and with
    nothing opened yet a stop need not wait for it (cmd_server ends the process without joining
    the thread). In the main thread, it kept a stop waiting until STOP_DEADLINE_S ended the process."""
    warming: Future = Future()

    def run() -> None:
        try:
            warming.set_result(warm_kernels())
        except BaseException as error:  # raised by the caller
            warming.set_exception(error)

    threading.Thread(target=run, name="gmmap-warm-up", daemon=True).start()
    while not warming.done():
        if stop.wait(POLL_S):
            return None
    return warming.result()


def run_server(
    options: ServerConfig, reconstruction: ReconstructionConfig = ReconstructionConfig(), ros2: Ros2Config | None = None
) -> int:
    started = time.perf_counter()
    sections = {"server": options, "reconstruction": reconstruction} | ({"ros2": ros2} if ros2 is not None else {})
    print(f"gmmap server config: {summary(**sections)}", file=sys.stderr, flush=True)
    options.check_http()  # before anything is opened: a refusal leaves nothing behind
    tokens = None
    if options.http and options.http_tokens:
        tokens = TokenFile(options.http_tokens)
    if options.http and options.http_tls:
        check_tls_files(options.http_tls_cert, options.http_tls_key)
    exposure = options.http_exposure()
    if exposure:
        print(f"gmmap server: WARNING {exposure}", file=sys.stderr, flush=True)
    stop = StopSignal()
    stop.exit_if_stuck(STOP_DEADLINE_S, "gmmap server")
    warm_s = warm_up(stop)  # before anything arrives: the first scans and tiles do not wait for numba
    if warm_s is None:
        print("gmmap server: stopped while loading its kernels", file=sys.stderr, flush=True)
        return 0

    store = Store(options.data_dir, synchronous=options.synchronous)
    fleet_map = FleetMap(
        options.fleet,
        samples_per_cell=reconstruction.samples_per_cell,
        prior=reconstruction.prior,
        trace_threads=options.trace_threads,
        busy_samples_per_cell=(
            BUSY_SAMPLES_PER_CELL if options.busy_samples_per_cell is None else options.busy_samples_per_cell or None
        ),
        stored_bytes=store.scan_reader(options.fleet),
        trace_store=store.path if options.trace_processes else None,
    )
    state = ServerState(options.fleet, fleet_map, store)
    zenoh_side: ZenohSide | None = None
    quota = int(options.robot_quota_mb * 2**20) if options.robot_quota_mb > 0 else None
    ingest = Ingest(state, lambda key, payload: zenoh_side.publish(key, payload), quota)
    replayed = ingest.replay()
    thaw = freeze_survivors()  # what survives a full collection is left out of the next: no growing pauses
    ingest.start()
    http = None
    ros_publisher = None
    try:
        config = zenoh_config(
            "peer", listen=options.listen, connect=options.zenoh_connect, config_file=options.zenoh_config
        )
        ros_map = ros2 is not None and ros2.map_topic is not None
        if ros_map:
            from services.ros2.map_out import RosMapPublisher, timestamped

            config = timestamped(config)
        try:
            zenoh_side = ZenohSide(state, ingest, config)
        except zenoh.ZError as error:
            raise OSError(f"cannot open the Zenoh session: {error}") from None
        if ros_map:
            ros_publisher = RosMapPublisher(zenoh_side.session, fleet_map, ros2, options.fleet)
        if options.http:
            http = start_http(state, options, reconstruction.variance, tokens)
        print(
            f"gmmap server ready: fleet {options.fleet}, {replayed} scans from {store.path}, "
            f"zenoh {','.join(options.listen) or '-'}"
            f"{' -> ' + ','.join(options.zenoh_connect) if options.zenoh_connect else ''}, "
            f"http {http_banner(options, tokens) if http else 'off'}, {time.perf_counter() - started:.1f} s "
            f"(kernels loaded in {warm_s:.1f} s)",
            file=sys.stderr,
            flush=True,
        )
        while not stop.wait(RELEASE_MEMORY_S):  # the main thread has nothing else to do
            release_free_memory()
        print("gmmap server: stopping", file=sys.stderr, flush=True)
    finally:
        stopping = time.perf_counter()
        fleet_map.close()  # tiles being traced end now, and their requests with them
        if http is not None:
            server, thread = http
            server.should_exit = True
            thread.join(1)
        http_s = time.perf_counter() - stopping
        if ros_publisher is not None:
            ros_publisher.close()
        if zenoh_side is not None:
            zenoh_side.stop_ingest()  # no new messages; then what can be stored in time is stored and acked
        ingest.stop()
        ingest_s = time.perf_counter() - stopping - http_s
        if zenoh_side is not None:
            zenoh_side.close()
        print(
            f"gmmap server: stopped in {time.perf_counter() - stopping:.1f} s "
            f"(http {http_s:.1f} s, ingest {ingest_s:.1f} s)",
            file=sys.stderr,
            flush=True,
        )
        store.close()
        thaw()
    return 0
