"""Connecting to a Ray cluster (the optional `ray` extra): one owner of addresses, runtime environment
and worker threads, used by Ray registration (drsplat.registration.ray) and Ray features
(drsplat.features.ray).

`ray` is optional (`pip install 'drsplat[ray]'`); without it `import_ray` raises a DrsplatError that
says so. Nothing here imports ray at module level.
"""

from __future__ import annotations

import builtins
import contextlib
import logging
import os
import signal
import socket
import threading
import time
import types
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any
from pathlib import Path

from drsplat.defaults import OPENMP_WAIT_POLICY, openmp_wait_policy
from drsplat.errors import Cancelled, DrsplatError
from drsplat.utils import CancelToken

log = logging.getLogger(__name__)

TASK_RETRIES = 3
WAIT_SECONDS = 0.5  # a driver's wait on Ray results at a time, between checks of its cancel token (and stalled workers)
STALL_SECONDS = 120.0  # a call that waits this long (plus 10x the slowest call seen) is stalled (its node gone, or never
#                        placed: the cluster's CPUs busy); see `stalled`
LOCAL_ADDRESSES = ("", "local")


@dataclass(frozen=True)
class ClusterOptions:
    """Where Ray work runs. address: None / "" / "local" starts a local Ray instance, "auto" joins
    the cluster of this machine, "HOST:PORT" a running cluster. workers: tasks or actors at once
    (default: the cluster's CPUs). views_per_task: registration views a task computes (default:
    drsplat.registration.ray.VIEWS_PER_TASK)."""

    address: str | None = None
    workers: int | None = None
    views_per_task: int | None = None


def import_ray():
    try:
        import ray
    except ImportError:
        raise DrsplatError("--ray needs the ray package: pip install 'drsplat[ray]' (ray==2.60.0)") from None
    return ray


def _runtime_env(address: str | None) -> dict:
    """Make workers run the driver's drsplat code whatever is installed on their side.

    On this machine (a local instance, or a cluster address on this host) workers import the
    package from the driver's folder (PYTHONPATH), which also reuses numba's on-disk cache of
    compiled kernels; on other hosts Ray ships the package (`py_modules`). A cluster joined on this
    host (`auto`, or its address) that has nodes on other hosts is joined again with the package
    shipped (`connect`), so those nodes run the driver's code, not what their PYTHONPATH holds.
    """
    package = Path(__file__).resolve().parent  # the drsplat package folder
    if _on_this_host(address):
        return {"env_vars": {"PYTHONPATH": str(package.parent), **_worker_env()}}
    return _shipped_env()


def _shipped_env() -> dict:
    """The runtime environment that ships the driver's drsplat package to every node (`py_modules`:
    Ray zips the folder once, each node unpacks it once per cluster session, keyed by its contents)."""
    return {"py_modules": [str(Path(__file__).resolve().parent)], "excludes": ["__pycache__", "*.pyc"], "env_vars": _worker_env()}


def _worker_env() -> dict[str, str]:
    """The workers' OpenMP wait policy: the driver's, else OPENMP_WAIT_POLICY. Several workers share a node's cores,
    where a spinning OpenMP thread takes a core from the others (`drsplat.console.prefer_passive_openmp_waits`; a
    value the runtimes would call invalid, empty included, counts as unset there too)."""
    given = os.environ.get("OMP_WAIT_POLICY", "")
    return {"OMP_WAIT_POLICY": given if openmp_wait_policy(given) else OPENMP_WAIT_POLICY}


def _host_addresses() -> set[str]:
    """This machine's addresses as Ray nodes report theirs (NodeManagerAddress)."""
    addresses = {"127.0.0.1"}
    try:
        addresses.update(socket.gethostbyname_ex(socket.gethostname())[2])
    except OSError:
        pass
    try:
        import ray

        addresses.add(ray.util.get_node_ip_address())
    except Exception:  # noqa: BLE001 - Ray not connected, or no address to read
        pass
    return addresses


def _nodes_elsewhere(ray) -> list[str]:
    """The addresses of the cluster's live nodes that are not this machine's."""
    mine = _host_addresses()
    return sorted({n.get("NodeManagerAddress", "?") for n in ray.nodes() if n.get("Alive") and n.get("NodeManagerAddress") not in mine})


def _on_this_host(address: str | None) -> bool:
    if address is None or address in LOCAL_ADDRESSES or address == "auto":
        return True
    host = address.split("://", 1)[-1].rpartition(":")[0]
    try:
        ip = socket.gethostbyname(host)
    except OSError:
        return False
    return ip.startswith("127.") or ip in _host_addresses()


def address_problem(address: str | None) -> str | None:
    """Why `address` is no Ray cluster address ("is ...", to follow the address), or None: nothing / "local" / "auto", or
    HOST:PORT (ray://HOST:PORT), the port 1-65535. A dashboard's http(s):// address is named as such (round 60b: Ray's
    advice about a RAY_ADDRESS variable the user never set came back, with a token hint)."""
    if address is None or address in LOCAL_ADDRESSES or address == "auto":
        return None
    expected = "HOST:PORT as `ray start --head` prints it (port 6379 by default), 'auto', or nothing for a local cluster"
    scheme, sep, target = address.partition("://")
    if sep and scheme.lower() in ("http", "https"):
        return f"is a web address (a dashboard's?), not a cluster's: expected {expected}"
    if sep and scheme.lower() != "ray":
        return f"is not an address (ray:// is the only scheme a cluster's takes): expected {expected}"
    if address != address.strip():
        return f"has spaces around it: expected {expected}"
    host, _, port = (target if sep else address).rpartition(":")
    if not host or not (port.isascii() and port.isdigit()) or not 1 <= int(port) <= 65535:  # '6379²' is a digit to isdigit
        return f"is not an address: expected {expected}"
    if ":" in host and not (host.startswith("[") and host.endswith("]")):  # round 60c: '::1' read as host '::', port 1
        return f"is not an address: an IPv6 host goes in brackets, [HOST]:PORT (e.g. [::1]:6379); expected {expected}"
    return None


def address_host_port(address: str) -> tuple[str, int]:
    """(host, port) of a HOST:PORT or ray://HOST:PORT address (`address_problem` None), an IPv6 host without its brackets."""
    host, _, port = address.split("://", 1)[-1].rpartition(":")
    return host.removeprefix("[").removesuffix("]"), int(port)


# HTTP/2's client connection preface and an empty SETTINGS frame: a gRPC server (Ray's GCS, the Ray Client server)
# answers them with a SETTINGS frame of its own (RFC 9113, 3.4)
HTTP2_PREFACE = b"PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n" + bytes([0, 0, 0, 4, 0, 0, 0, 0, 0])
HTTP2_DATA, HTTP2_HEADERS, HTTP2_RST_STREAM, HTTP2_SETTINGS, HTTP2_GOAWAY = 0, 1, 3, 4, 7  # frame types
HTTP2_END_STREAM, HTTP2_ACK, HTTP2_END_HEADERS, HTTP2_PADDED = 0x1, 0x1, 0x4, 0x8  # frame flags
HTTP2_MAX_FRAME = 1 << 14  # the largest frame a peer may send before SETTINGS raise it (RFC 9113, 4.2)
# the GCS's cheapest call, the first ray.init makes (a raylet's port answers it "unimplemented", round 91a F3)
GCS_PROBE_METHOD = "/ray.rpc.NodeInfoGcsService/GetClusterId"


@dataclass(frozen=True)
class Http2Frame:
    kind: int
    flags: int
    stream: int
    payload: bytes


def _read_exact(sock: socket.socket, size: int, deadline: float) -> bytes | None:
    """`size` bytes from `sock` by time.monotonic() `deadline`, or None (closed, an error, or too late)."""
    data = b""
    while len(data) < size:
        left = deadline - time.monotonic()
        if left <= 0:
            return None
        sock.settimeout(left)
        try:
            part = sock.recv(size - len(data))
        except OSError:  # socket.timeout included
            return None
        if not part:
            return None
        data += part
    return data


def read_http2_frame(sock: socket.socket, deadline: float) -> Http2Frame | None:
    """The next HTTP/2 frame (9-byte header: 24-bit length, type, flags, 31-bit stream), or None: closed, late, or a
    length past HTTP2_MAX_FRAME (not HTTP/2)."""
    head = _read_exact(sock, 9, deadline)
    if head is None:
        return None
    size = int.from_bytes(head[:3], "big")
    if size > HTTP2_MAX_FRAME:
        return None
    payload = _read_exact(sock, size, deadline) if size else b""
    if payload is None:
        return None
    return Http2Frame(head[3], head[4], int.from_bytes(head[5:9], "big") & 0x7FFFFFFF, payload)


def is_server_preface(frame: Http2Frame | None) -> bool:
    """Whether `frame` is what an HTTP/2 server must send first: a SETTINGS frame on stream 0, not an ACK, of whole
    6-byte settings (RFC 9113, 3.4 and 6.5)."""
    return (frame is not None and frame.kind == HTTP2_SETTINGS and frame.stream == 0 and not frame.flags & HTTP2_ACK
            and len(frame.payload) % 6 == 0)


def _hpack_literal(name: str, value: str) -> bytes:
    """One header field as HPACK's "literal without indexing, new name", no Huffman (RFC 7541, 6.2.2); names and
    values under 127 bytes (one-byte lengths)."""
    raw_name, raw_value = name.encode("ascii"), value.encode("ascii", "replace")  # a host of other letters: '?' (no server reads it)
    return bytes([0, len(raw_name)]) + raw_name + bytes([len(raw_value)]) + raw_value


def gcs_probe_request(authority: str) -> bytes:
    """The frames of a unary gRPC call of GCS_PROBE_METHOD on stream 1 after the preface: HEADERS, then DATA holding
    the empty request message (gRPC's 5-byte prefix, uncompressed, length 0) and ending the stream."""
    block = b"".join(_hpack_literal(name, value) for name, value in (
        (":method", "POST"), (":scheme", "http"), (":path", GCS_PROBE_METHOD), (":authority", authority[:100]),
        ("content-type", "application/grpc"), ("te", "trailers")))
    headers = len(block).to_bytes(3, "big") + bytes([HTTP2_HEADERS, HTTP2_END_HEADERS]) + (1).to_bytes(4, "big") + block
    message = bytes(5)
    data = len(message).to_bytes(3, "big") + bytes([HTTP2_DATA, HTTP2_END_STREAM]) + (1).to_bytes(4, "big") + message
    return headers + data


def protobuf_bytes_field(message: bytes, number: int) -> bytes | None:
    """The last value of length-delimited field `number` in the protobuf `message`, b"" when absent, or None when
    `message` is not a protobuf message (a field of wire type 1, 3, 4 or 5 included: GetClusterIdReply has none)."""
    found, at = b"", 0

    def varint() -> int | None:
        nonlocal at
        value = shift = 0
        while at < len(message) and shift < 64:
            byte = message[at]
            at += 1
            value |= (byte & 0x7F) << shift
            shift += 7
            if not byte & 0x80:
                return value
        return None

    while at < len(message):
        tag = varint()
        if tag is None or tag >> 3 == 0:
            return None
        if tag & 7 == 0:
            if varint() is None:
                return None
        elif tag & 7 == 2:
            size = varint()
            if size is None or at + size > len(message):
                return None
            if tag >> 3 == number:
                found = message[at:at + size]
            at += size
        else:
            return None
    return found


def gcs_answer(sock: socket.socket, authority: str, deadline: float, ask_gcs: bool = True) -> str:
    """What the server at the other end of `sock` is, by `deadline` (time.monotonic()): "gcs" (it answers the
    GCS_PROBE_METHOD call with a GetClusterIdReply holding a cluster id: Ray's GCS), "grpc" (an HTTP/2 server that
    answers the call otherwise, or, with `ask_gcs` False, one that answers the preface at all), "grpc_silent" (an
    HTTP/2 server that says nothing of the call by the deadline) or "none" (no HTTP/2 answer: an HTTP/1 server answers
    "400", a silent one nothing, some other one bytes that are no SETTINGS frame).
    A gRPC error comes as trailers alone (a HEADERS frame that ends the stream); a reply as DATA on the stream."""
    try:
        sock.sendall(HTTP2_PREFACE + (gcs_probe_request(authority) if ask_gcs else b""))
    except OSError:
        return "none"
    if not is_server_preface(read_http2_frame(sock, deadline)):
        return "none"
    if not ask_gcs:
        return "grpc"
    with contextlib.suppress(OSError):
        sock.sendall(bytes([0, 0, 0, HTTP2_SETTINGS, HTTP2_ACK, 0, 0, 0, 0]))
    reply = b""
    while (frame := read_http2_frame(sock, deadline)) is not None:
        if frame.kind == HTTP2_GOAWAY or (frame.stream == 1 and frame.kind == HTTP2_RST_STREAM):
            return "grpc"
        if frame.stream != 1:
            continue
        if frame.kind == HTTP2_HEADERS and frame.flags & HTTP2_END_STREAM and not reply:
            return "grpc"  # trailers only: the call failed (unimplemented on a raylet's port)
        if frame.kind == HTTP2_DATA:
            payload = frame.payload
            if frame.flags & HTTP2_PADDED:
                payload = payload[1:len(payload) - payload[0]] if payload and payload[0] < len(payload) else b""
            reply += payload
            if len(reply) >= 5:
                size = int.from_bytes(reply[1:5], "big")
                if reply[0] != 0 or len(reply) > 5 + size:
                    return "grpc"
                if len(reply) == 5 + size:
                    return "gcs" if protobuf_bytes_field(reply[5:], 2) else "grpc"
        if frame.flags & HTTP2_END_STREAM:
            return "grpc"
    return "grpc" if reply else "grpc_silent"


def check_reachable(address: str, timeout: float = 3.0) -> None:
    """A clear error within `timeout` seconds when host:port accepts no connection, or accepts one but is not Ray's
    GCS: ray.init would wait much longer, or forever (round 90c F1: an HTTP server or a silent port hung
    `register --ray HOST:PORT`, a first Ctrl-C unheard; round 91a F3: an HTTP/2 server that is not gRPC, or a
    raylet's port). The GCS is asked its cluster id (`gcs_answer`). A ray:// address (the Ray Client server, another
    service), RAY_AUTH_MODE=token (the call would need the token) only need an HTTP/2 answer; with RAY_USE_TLS the
    probe only connects."""
    problem = address_problem(address)
    if problem is not None:
        raise DrsplatError(f"--ray {address!r} {problem}")
    host, port = address_host_port(address)
    deadline = time.monotonic() + timeout
    client = address.lower().startswith("ray://")
    plain = os.environ.get("RAY_AUTH_MODE", "").strip().lower() != "token"
    try:
        with socket.create_connection((host, port), timeout=timeout) as sock:
            if os.environ.get("RAY_USE_TLS", "0").strip().lower() in ("1", "true"):
                return
            answer = gcs_answer(sock, f"{host}:{port}", deadline, ask_gcs=plain and not client)
    except (OSError, UnicodeError) as exc:  # UnicodeError: a host name IDNA cannot encode ('..', a 64-letter label)
        reason = exc.strerror if isinstance(exc, OSError) and exc.strerror else f"{exc}"
        raise DrsplatError(
            f"cannot reach a Ray cluster at {address} ({reason}); start one with `ray start --head` "
            f"and pass the address it prints, or use --ray with no address for a local cluster"
        ) from None
    if answer == "gcs" or (answer == "grpc" and (client or not plain)):
        return
    start_hint = "pass the address `ray start --head` prints, or use --ray with no address for a local cluster"
    if answer == "grpc":
        # the call's refusal is not decoded (HPACK): "unimplemented" (a raylet's port) and "unauthenticated" (a cluster
        # that asks for a token this process does not send) look alike here (round 93a F1)
        raise DrsplatError(f"{address} answers gRPC but refused the cluster-id call every Ray GCS answers: a raylet's or another "
                           f"service's port, or a cluster that asks for a token{auth_hint()}; otherwise {start_hint}")
    if answer == "grpc_silent":
        raise DrsplatError(f"{address} answers HTTP/2 but not the cluster-id call every Ray GCS answers within "
                           f"{timeout:g} s (another service on that port?); {start_hint}")
    raise DrsplatError(f"{address} accepts a connection but does not answer as a Ray cluster does (its GCS speaks gRPC; to HTTP/2's "
                       f"preface it closed the connection, sent no SETTINGS frame or nothing within {timeout:g} s: another service "
                       f"on that port?); {start_hint}")


def connect(address: str | None, *, num_cpus: int | None = None, object_store_memory: int | None = None) -> bool:
    """Connect this process to Ray. Returns True when this call started Ray (the caller shuts it down).

    address: None / "" / "local" starts a local Ray instance; "auto" joins the cluster this machine
    belongs to; "HOST:PORT" (or ray://HOST:PORT) joins that cluster, checked first to be reachable.
    An already initialised Ray session is reused.
    """
    ray = import_ray()
    local = address is None or address in LOCAL_ADDRESSES
    if not local and address != "auto":
        check_reachable(address)
    if ray.is_initialized():
        return False
    kwargs = {"runtime_env": _runtime_env(address), "logging_level": logging.WARNING, "log_to_driver": False}
    if local:  # "local": a new instance even where `ray start` runs one (ray.init() alone would join it)
        kwargs.update(address="local", include_dashboard=False, num_cpus=num_cpus, object_store_memory=object_store_memory)
    else:
        kwargs["address"] = address
    sigterm = signal.getsignal(signal.SIGTERM) if threading.current_thread() is threading.main_thread() else None
    try:
        with _process_state_kept(), _ctrl_c_raises():
            ray.init(**kwargs)
            elsewhere = [] if local or "py_modules" in kwargs["runtime_env"] else _nodes_elsewhere(ray)
            if elsewhere:  # the driver's folder is this host's: the nodes of other hosts get the package itself
                log.info("Ray: %d node(s) on other hosts (%s): drsplat is shipped to them with Ray's py_modules", len(elsewhere),
                         ", ".join(elsewhere[:3]))
                ray.shutdown()
                ray.init(**{**kwargs, "runtime_env": _shipped_env()})
    except KeyboardInterrupt:
        with contextlib.suppress(Exception):  # a half-made connection or local instance
            ray.shutdown()
        raise Cancelled(f"Ctrl-C while connecting to Ray ({address or 'a new local instance'}); nothing was computed") from None
    except (ConnectionError, RuntimeError, ValueError) as exc:
        hint = "" if local or address == "auto" else auth_hint()
        # Ray's own advice names its CLI's flag; drsplat's is --ray (round 90c F3)
        said = str(exc).replace("`--address` flag", "--ray").replace("--address flag", "--ray")
        raise DrsplatError(f"could not connect to the Ray cluster at {address or 'a new local instance'}: {said}{hint}") from None
    except SystemExit as exc:
        if exc.code != signal.SIGTERM or not callable(sigterm):
            raise
        _sigterm_during_init(ray, sigterm)
    _relay_errors_to_log()
    return True


@contextmanager
def _ctrl_c_raises() -> Iterator[None]:
    """Within the block (in the main thread), Ctrl-C raises KeyboardInterrupt at once, whatever handler the caller
    installed: ray.init waits in Ray's own loops (for a GCS slow to answer), which never look at a cancel token, so a
    command's first Ctrl-C, which only cancels its token, was unheard there (round 90c). Outside the main thread this
    does nothing."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.getsignal(signal.SIGINT)
    signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


def _sigterm_during_init(ray, handler: Callable) -> None:
    """A SIGTERM that came while ray.init ran met Ray's own handler (sys.exit(15): the process ended
    with status 15 and no line, round 60b). The program's handler is given it now (the command
    line's raises KeyboardInterrupt; a cancellable job's cancels its token), after the half-made
    connection is shut down; a handler that only cancels ends the connect with Cancelled."""
    with contextlib.suppress(Exception):  # a half-made local instance too (its agents outlived the process, round 62b)
        ray.shutdown()
    handler(signal.SIGTERM, None)
    raise Cancelled("SIGTERM while connecting to Ray")


def disconnect(owns: bool) -> None:
    """Leave Ray where `connect` returned True (`owns`): shut it down and give Ray's error printer back."""
    if owns:
        import_ray().shutdown()
        _restore_error_printer()


RAY_PRINTER = "print_to_stdstream"  # ray._private.worker's printer, which its error listener looks up at each message
RELAYED_LINE_CHARS = 300


def _relay_errors_to_log() -> None:
    """Ray's errors on this driver (a worker died, a task retried, a node lost) as one WARNING line each.

    Ray's driver runs a thread that prints every error the cluster publishes, whatever `log_to_driver`
    says, to stdout with the raylet's log tails: ~50 raw lines for a lost node, in the middle of a
    command's own output (round 60b of docs/hostile.md). The drivers here already act on a lost worker
    (its work moved, a warning of their own), so each message's first line, to the log (stderr), is
    what a user needs. Output that is not the listener's (pid "raylet") goes to Ray's printer as before.
    Ray's private printer is looked for by name; a Ray without it prints as it does.
    """
    from ray._private import worker

    printer = getattr(worker, RAY_PRINTER, None)
    if printer is None or getattr(printer, "drsplat_relay", False):
        return

    def relay(data: dict, *args, **kwargs) -> None:
        if data.get("pid") != "raylet":
            printer(data, *args, **kwargs)
            return
        for message in data.get("lines", ()):
            first = str(message).strip().splitlines()[:1]
            if first:
                log.warning("Ray: %s", relayed_line(first[0]))

    relay.drsplat_relay = True  # type: ignore[attr-defined]
    relay.ray_printer = printer  # type: ignore[attr-defined]
    setattr(worker, RAY_PRINTER, relay)


def relayed_line(line: str) -> str:
    """A Ray message's first line as relayed: at most RELAYED_LINE_CHARS, a cut marked with '...', and no colon left
    announcing the lines it is relayed without (round 62b: "Last 20 lines of the Raylet logs:")."""
    line = line.rstrip().rstrip(":")
    return line if len(line) <= RELAYED_LINE_CHARS else line[: RELAYED_LINE_CHARS - 3].rstrip() + "..."


def _restore_error_printer() -> None:
    from ray._private import worker

    relay = getattr(worker, RAY_PRINTER, None)
    if getattr(relay, "drsplat_relay", False):
        setattr(worker, RAY_PRINTER, relay.ray_printer)


def auth_hint() -> str:
    """What to try when an explicit cluster address refuses this process: Ray (2.59 on) starts
    clusters with token authentication, and a driver given a HOST:PORT sends its token only when
    RAY_AUTH_MODE=token is set (`auto` learns it from the cluster's session on this machine)."""
    if os.environ.get("RAY_AUTH_MODE", "").lower() == "token":
        return ("; RAY_AUTH_MODE=token is set, so check the token (RAY_AUTH_TOKEN, RAY_AUTH_TOKEN_PATH or ~/.ray/auth_token "
                "must hold the head's: `ray get-auth-token` there)")
    return ("; if the cluster uses Ray's token authentication (the default for `ray start` since Ray 2.59), run with "
            "RAY_AUTH_MODE=token and the head's token (`ray get-auth-token` there) in ~/.ray/auth_token or RAY_AUTH_TOKEN, "
            "or use --ray auto on a node of the cluster")


@contextmanager
def _process_state_kept() -> Iterator[None]:
    """Keep what belongs to the program using drsplat, not to Ray, as it was across ray.init.

    ray.init replaces the SIGTERM handler (with sys.exit: the CLI's own handler, which turns
    SIGTERM into a clean interrupt, would be lost) and sets PYTHONBREAKPOINT to Ray's debugger.
    The first worker output or worker-death error that Ray's driver relays replaces
    builtins.print with ray.experimental.tqdm_ray.safe_print, from a background thread; numba then
    cannot compile jitted code that calls numba.get_num_threads() (its implementation prints).
    Creating Ray's progress-bar manager now, print put back, means Ray never replaces print later
    (the manager replaces it only when it is created).
    """
    from ray.experimental import tqdm_ray

    keep_print = builtins.print
    tqdm_ray.instance()
    builtins.print = keep_print
    in_main_thread = threading.current_thread() is threading.main_thread()  # signal handlers are the main thread's
    keep_sigterm = signal.getsignal(signal.SIGTERM) if in_main_thread else None
    keep_breakpoint = os.environ.get("PYTHONBREAKPOINT")
    try:
        yield
    finally:
        if keep_sigterm is not None:
            signal.signal(signal.SIGTERM, keep_sigterm)
        if keep_breakpoint is None:
            os.environ.pop("PYTHONBREAKPOINT", None)
        else:
            os.environ["PYTHONBREAKPOINT"] = keep_breakpoint


def worker_slots(nodes: list[dict], gpus_per_worker: int) -> int:
    """Workers of one CPU (and `gpus_per_worker` GPUs) the cluster can run at once: the sum over its
    live nodes of what fits on each. Starting more actors than this would leave some waiting for
    resources forever, and the calls queued on them with them. nodes: ray.nodes()."""
    slots = 0
    for node in nodes:
        if not node.get("Alive", False):
            continue
        resources = node.get("Resources", {})
        fit = int(resources.get("CPU", 0))
        if gpus_per_worker:
            fit = min(fit, int(resources.get("GPU", 0)) // gpus_per_worker)
        slots += fit
    return slots


def stalled(waited: float, slowest: float) -> bool:
    """Whether a Ray call (or a worker's start) that has waited `waited` seconds is stalled: STALL_SECONDS plus 10x
    the slowest call seen (`slowest`) have passed. Ray drivers then have its work done elsewhere (registration sends
    the call as well to an idle worker and takes the first answer; features, whose workers hold one call each, move
    it while the others progress: drsplat.registration.ray, drsplat.features.ray); a worker never placed (the cluster's
    CPUs or GPUs taken by other work, or its node lost with no room to restart it) would otherwise
    be waited for forever. With no other worker progressing, `stalled(waited, 0.0)` bounds the
    wait for a worker that never starts at all. Read at call time, so a test may lower it."""
    return waited > STALL_SECONDS + 10 * slowest


def kill_if_cancelled(ray, actors: list, cancel: CancelToken | None) -> None:
    """Stop `actors` and raise Cancelled when `cancel` is set (a Ctrl-C never waits for a worker)."""
    if cancel is not None and cancel.cancelled:
        for actor in actors:
            ray.kill(actor, no_restart=True)
        cancel.raise_if_cancelled()


def placed_actors(actors: list, what: str, work: str, cancel: CancelToken | None = None,
                  queue_after_ready: Callable[[Any], None] | None = None) -> list:
    """The actors among `actors` that Ray placed (each answered its `ready` call), in their order.

    A worker not placed (the cluster's CPUs or GPUs taken by other work, its node lost) while others
    are is stopped with a warning once `stalled` says so (STALL_SECONDS plus 10x the slowest
    placement): its `work` goes to the others. None placed in STALL_SECONDS is one DrsplatError, not
    a wait (a registration on a cluster whose CPUs were all held waited forever: its stall rule needs
    a worker that progresses). A cancel is seen within WAIT_SECONDS.

    what: the workers' kind in messages ("feature", "registration"); work: what they are given ("images").
    queue_after_ready: called with each actor right after its `ready` call is sent, to queue a call
    behind it (a feature worker loads its models as soon as it is placed, not after the others).
    """
    ray = import_ray()
    t0 = time.monotonic()
    pending = {}
    for actor in actors:
        pending[actor.ready.remote()] = actor
        if queue_after_ready is not None:
            queue_after_ready(actor)
    placed: set[int] = set()
    unavailable = 0
    slowest = 0.0
    try:
        while pending:
            ready, _ = ray.wait(list(pending), num_returns=len(pending), timeout=WAIT_SECONDS)
            kill_if_cancelled(ray, actors, cancel)
            for ref in ready:
                actor = pending.pop(ref)
                try:
                    ray.get(ref)
                except ray.exceptions.ActorUnavailableError:  # its node lost once its process started: the others go on
                    unavailable += 1  # (round 74d F3: this ended the whole run while other workers were placed)
                    with contextlib.suppress(Exception):  # an actor already gone
                        ray.kill(actor, no_restart=True)
                    continue
                placed.add(id(actor))
                slowest = max(slowest, time.monotonic() - t0)
            waited = time.monotonic() - t0
            if pending and stalled(waited, slowest if placed else 0.0):
                if not placed:
                    raise DrsplatError(f"no Ray {what} worker started in {waited:.0f} s: the cluster's CPUs (or GPUs) are "
                                       "taken by other work, or its nodes lost: rerun when the cluster has room")
                log.warning("Ray: %d of %d %s workers did not start in %.0f s while the others did (the cluster's CPUs taken by "
                            "other work, or their node lost); their %s go to the %d that did", len(pending), len(actors), what, waited,
                            work, len(placed))
                for a in pending.values():
                    ray.kill(a, no_restart=True)
                break
    except ray.exceptions.RayError as exc:
        raise DrsplatError(f"a Ray {what} worker could not start: {exc}") from None
    if unavailable:
        if not placed:
            raise DrsplatError(f"no Ray {what} worker started: the node of each became unavailable (lost) as it started; rerun "
                               "when the cluster is whole")
        log.warning("Ray: %d of %d %s workers became unavailable as they started (their node lost); their %s go to the %d that "
                    "started", unavailable, len(actors), what, work, len(placed))
    return [a for a in actors if id(a) in placed]


def set_worker_threads() -> None:
    """numba threads = the CPUs Ray gave this task (workers otherwise oversubscribe the node)."""
    import numba
    import ray

    cpus = ray.get_runtime_context().get_assigned_resources().get("CPU", 1)
    numba.set_num_threads(max(1, min(numba.config.NUMBA_NUM_THREADS, int(round(cpus)))))


@contextmanager
def session(address: str | None) -> Iterator[None]:
    """Connected to Ray inside the block; a Ray instance this block started is shut down after it."""
    owns = connect(address)
    try:
        yield
    finally:
        disconnect(owns)


def _code_identity(modules: tuple[str, ...] = ()) -> dict[str, str]:
    """What a process must share with the driver for the same bits: drsplat's sources (a digest of every
    .py file of the package it imports), Python, numpy and numba, and the version of each of `modules`
    (features add torch and open_clip, whose arithmetic makes their embeddings). Self-contained (its imports
    inside): `check_nodes_run_this_code` ships it by value, so a node runs this code, not its own drsplat's."""
    import hashlib
    import importlib
    import sys
    from pathlib import Path

    import numba
    import numpy

    import drsplat  # inside: the function is shipped by value and runs on another node

    package = Path(drsplat.__file__).resolve().parent
    h = hashlib.sha1()
    for f in sorted(package.rglob("*.py")):
        h.update(str(f.relative_to(package)).encode() + b"\0" + f.read_bytes())
    found = {"drsplat sources": h.hexdigest()[:12], "python": sys.version.split()[0], "numpy": numpy.__version__, "numba": numba.__version__}
    for name in modules:
        try:
            found[name] = str(getattr(importlib.import_module(name), "__version__", "?"))
        except ImportError:
            found[name] = "missing"
    return found


PROBE_SECONDS = 60.0  # a node that does not answer the code probe in this time is not checked (said at debug level)


def probe_answers(ray, refs: list, cancel: CancelToken | None) -> list:
    """The refs of `refs` done within PROBE_SECONDS, waited for in steps of WAIT_SECONDS so that a cancel is seen."""
    deadline = time.monotonic() + PROBE_SECONDS
    ready: list = []
    while refs:
        done, refs = ray.wait(refs, num_returns=len(refs), timeout=max(0.0, min(WAIT_SECONDS, deadline - time.monotonic())))
        ready += done
        if cancel is not None:
            cancel.raise_if_cancelled()
        if time.monotonic() >= deadline:
            break
    return ready


def check_nodes_run_this_code(ray, modules: tuple[str, ...] = (), what: str = "its views", cancel: CancelToken | None = None) -> list[dict]:
    """One task on every live node (no CPU asked, so a busy node answers too) reports what its workers
    import (`_code_identity` with `modules`, shipped by value); a node that imports another drsplat, Python, numpy,
    numba or version of `modules` is one DrsplatError before any work, naming the node, what differs and `what` it
    would make (registration's views; features' embeddings: round 60b, a node of other code wrote 9 of 16 feature
    files, exit 0). A node whose workers cannot import drsplat at all is said the same way, not as Ray's traceback.

    Returns the nodes (ray.nodes() entries) to place workers on: a node that ray.nodes() still lists
    as alive but that is gone (lost a moment ago: Ray says its probe cannot be scheduled, "the node
    ... doesn't exist any more") is left out with a warning, not refused and not counted as a worker
    slot (a worker asked for there would never be placed); a node that does not answer in PROBE_SECONDS is kept. cancel:
    read every WAIT_SECONDS of that wait (round 74d F4: a Ctrl-C waited up to PROBE_SECONDS for a node that did not answer)."""
    from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy

    by_value = types.FunctionType(_code_identity.__code__, {"__builtins__": __builtins__}, "_code_identity")
    mine = _code_identity(modules)
    task = ray.remote(num_cpus=0, max_retries=0)(by_value)
    nodes = [n for n in ray.nodes() if n.get("Alive")]
    refs = {task.options(scheduling_strategy=NodeAffinitySchedulingStrategy(n["NodeID"], soft=False)).remote(modules): n for n in nodes}
    ready = probe_answers(ray, list(refs), cancel)
    gone = []
    for ref in ready:
        node = refs[ref].get("NodeManagerHostname") or refs[ref].get("NodeManagerAddress")
        try:
            theirs = ray.get(ref)
        except ray.exceptions.TaskUnschedulableError:  # the node left the cluster since ray.nodes() listed it
            gone.append(refs[ref])
            continue
        except ray.exceptions.RayError as exc:
            cause = getattr(exc, "cause", None) or exc
            raise DrsplatError(f"the Ray node {node} cannot run drsplat ({type(cause).__name__}: {str(cause).splitlines()[-1]}): every node "
                               "needs drsplat importable with its dependencies (a node of another host gets the driver's package "
                               "through Ray's py_modules unless its address is this host's)") from None
        differ = [f"{k} {theirs.get(k)} there, {v} here" for k, v in mine.items() if theirs.get(k) != v]
        if differ:
            raise DrsplatError(f"the Ray node {node} runs other code than this driver ({'; '.join(differ)}): {what} would not be "
                               "this run's bits; every node needs the driver's drsplat (a node of another host gets it through Ray's "
                               f"py_modules unless its address is this host's) and the same Python, numpy, numba{''.join(', ' + m for m in modules)}")
    if len(ready) < len(refs):
        log.debug("Ray: %d node(s) did not answer the code probe in %.0f s", len(refs) - len(ready), PROBE_SECONDS)
    if gone:
        log.warning("Ray: %d node(s) listed as alive are gone (lost a moment ago: %s); no worker is asked for there", len(gone),
                    ", ".join(n.get("NodeID", "?")[:12] for n in gone))
    return [n for n in nodes if all(n is not g for g in gone)]
