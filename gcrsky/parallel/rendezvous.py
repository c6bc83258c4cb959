"""A pre-flight rendezvous of ``jax.distributed`` processes, so that a failed start is a Python error.

Why.  ``jax.distributed.initialize`` (JAX 0.10) cannot fail cleanly: its client's
``connect()`` retries registering with the coordinator until ``initialization_timeout``
(300 s by default), and the coordinator's registration is a barrier that waits for every
process.  When that deadline passes the C++ client calls its error callback, which is
``LOG(QFATAL)`` ("Terminating process because the JAX distributed service detected fatal
errors ... DEADLINE_EXCEEDED ... RegisterTask"): the process aborts with a C++ stack
trace, no Python exception, whichever process is waiting (a process whose coordinator
is unreachable, or process 0 whose peers never join).  The callback can be replaced only
through JAX's private client constructor, and the replacement cannot even be called (its
``absl::Status`` argument has no Python type).

What.  :func:`rendezvous` runs before JAX starts its coordinator: process 0 listens on
the coordinator's port (where JAX's service will bind: ``[::]:PORT`` unless a bind
address is given) with a plain TCP socket, and every other process connects there, says
who it is (``GCRSKY-DIST 1 <num_processes> <process_id>``) and waits.  When all
``num_processes - 1`` peers have joined, process 0 answers each ``GO``, closes the
socket, and every process goes on to ``jax.distributed.initialize`` at once; JAX's
client retries until process 0's service is up.  If the timeout passes first, process 0
answers the peers that did join ``ERR timeout ...`` and every process raises
:class:`DistributedTimeoutError`, naming the address, its process id, the number of
processes and the timeout, before any JAX state exists (the process stays usable).
A connection that is not a gcrsky peer (bad greeting) is dropped; a peer that gives
another number of processes, or a process id already taken, is answered ``ERR refused``
(it raises :class:`DistributedInitError`) and process 0 keeps waiting for the right one.
A peer that leaves before ``GO`` is forgotten (it may come back).  What this cannot
cover: a process that dies between the rendezvous and JAX's own registration (a
fraction of a second) still leaves the others to JAX's ``initialization_timeout``,
which :func:`gcrsky.parallel.init_distributed` sets to the same timeout.
"""

from __future__ import annotations

import logging
import os
import selectors
import socket
import time

__all__ = ["DEFAULT_DIST_TIMEOUT", "DistributedInitError", "DistributedTimeoutError", "parse_address", "rendezvous"]

_log = logging.getLogger("gcrsky")

#: Seconds :func:`gcrsky.parallel.init_distributed` (and ``gcrsky run --dist-timeout``) waits for the
#: processes to meet.
DEFAULT_DIST_TIMEOUT = 120.0

_HELLO = "GCRSKY-DIST 1"
_MAX_LINE = 512
_RETRY_S = 0.2  # between a peer's connection attempts


class DistributedInitError(ConnectionError):
    """The ``jax.distributed`` processes could not start together (the message says which and why)."""


class DistributedTimeoutError(DistributedInitError, TimeoutError):
    """The coordinator was not reached, or not every process joined, within the timeout."""


def parse_address(address: str) -> tuple[str, int]:
    """``"host:port"`` (``"[v6]:port"`` too) as ``(host, port)``; a ValueError names a malformed one."""
    host, sep, port = str(address).rpartition(":")
    if not sep or not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise ValueError(f"coordinator address must be HOST:PORT with a port in 1..65535, got {address!r}")
    if host.startswith("[") and host.endswith("]"):
        host = host[1:-1]
    return host, int(port)


def _who(process_id: int, num_processes: int) -> str:
    return f"process {process_id} of {num_processes}"


def rendezvous(coordinator_address: str, num_processes: int, process_id: int, timeout: float,
               bind_address: str | None = None) -> None:
    """Wait until all ``num_processes`` processes have met at ``coordinator_address``, for at most ``timeout`` s.

    Process 0 listens on the coordinator's port (``bind_address``, default
    ``$JAX_COORDINATOR_BIND_ADDRESS`` or ``[::]:PORT`` as JAX binds) until the other
    processes have connected; the others connect and wait for process 0's go-ahead
    (see the module docstring).  Call it on every process just before
    ``jax.distributed.initialize`` (:func:`gcrsky.parallel.init_distributed` does).

    Raises:
        DistributedTimeoutError: the coordinator could not be reached, or not every
            process joined, within ``timeout`` seconds (message: the address, the process
            id, the number of processes and the timeout).
        DistributedInitError: process 0 cannot listen on the port, or refused this
            process (another number of processes, a process id already taken).
        ValueError: a malformed address, process id, number of processes or timeout.
    """
    num_processes, process_id = int(num_processes), int(process_id)
    if num_processes < 1 or not 0 <= process_id < num_processes:
        raise ValueError(f"need 0 <= process_id < num_processes, got process_id={process_id}, "
                         f"num_processes={num_processes}")
    if not timeout > 0:
        raise ValueError(f"timeout must be positive (seconds), got {timeout!r}")
    parse_address(coordinator_address)
    if num_processes == 1:
        return
    deadline = time.monotonic() + float(timeout)
    if process_id == 0:
        _lead(coordinator_address, num_processes, float(timeout), deadline, bind_address)
    else:
        _join(coordinator_address, num_processes, process_id, float(timeout), deadline)


def _listen(coordinator_address: str, bind_address: str | None, backlog: int) -> socket.socket:
    bind = bind_address or os.environ.get("JAX_COORDINATOR_BIND_ADDRESS")
    host, port = parse_address(bind) if bind else ("::", parse_address(coordinator_address)[1])
    if host in ("::", "", "0.0.0.0"):
        if socket.has_dualstack_ipv6():
            return socket.create_server(("", port), family=socket.AF_INET6, dualstack_ipv6=True, backlog=backlog)
        return socket.create_server(("", port), backlog=backlog)
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    return socket.create_server((host, port), family=family, backlog=backlog)


def _send(sock: socket.socket, line: str) -> None:
    try:
        sock.setblocking(True)
        sock.settimeout(2.0)
        sock.sendall((line + "\n").encode())
    except OSError:
        pass


def _lead(address: str, n: int, timeout: float, deadline: float, bind_address: str | None) -> None:
    """Process 0: accept the ``n - 1`` peers, then answer each ``GO`` (or ``ERR timeout`` at the deadline)."""
    try:
        listener = _listen(address, bind_address, backlog=max(n, 8))
    except OSError as e:
        raise DistributedInitError(
            f"{_who(0, n)} cannot listen on the coordinator port of {address} to wait for the other processes: {e}"
        ) from e
    sel = selectors.DefaultSelector()
    listener.setblocking(False)
    sel.register(listener, selectors.EVENT_READ, None)
    pending: dict[socket.socket, bytes] = {}
    joined: dict[int, socket.socket] = {}

    def drop(sock: socket.socket) -> None:
        pending.pop(sock, None)
        for pid, s in list(joined.items()):
            if s is sock:
                del joined[pid]
                _log.info("jax.distributed: process %d left the rendezvous before it completed", pid)
        try:
            sel.unregister(sock)
        except (KeyError, ValueError):
            pass
        sock.close()

    def greet(sock: socket.socket, line: bytes) -> None:
        words = line.decode(errors="replace").split()
        if len(words) != 4 or " ".join(words[:2]) != _HELLO or not all(w.isdigit() for w in words[2:]):
            _log.debug("jax.distributed: dropped a connection that is not a gcrsky process: %r", line[:80])
            drop(sock)
            return
        their_n, pid = int(words[2]), int(words[3])
        if their_n != n or not 0 < pid < n or pid in joined:
            why = (f"it was started with --num-processes {their_n}" if their_n != n else
                   f"process id {pid} is out of range" if not 0 < pid < n else f"process id {pid} has already joined")
            _send(sock, f"ERR refused process 0 at {address} refused it: {why}")
            drop(sock)
            return
        pending.pop(sock, None)
        joined[pid] = sock

    try:
        while len(joined) < n - 1:
            left = deadline - time.monotonic()
            if left <= 0:
                missing = [p for p in range(1, n) if p not in joined]
                what = (f"process{'es' if len(missing) > 1 else ''} {', '.join(map(str, missing))} did not "
                        f"join the coordinator at {address} within the timeout of {timeout:g} s")
                for sock in list(joined.values()):
                    _send(sock, f"ERR timeout process 0 gave up: {what}")
                raise DistributedTimeoutError(f"{_who(0, n)}: {what}")
            for key, _ in sel.select(timeout=min(left, 1.0)):
                if key.fileobj is listener:
                    try:
                        conn, _addr = listener.accept()
                    except OSError:
                        continue
                    conn.setblocking(False)
                    sel.register(conn, selectors.EVENT_READ, None)
                    pending[conn] = b""
                    continue
                sock = key.fileobj
                try:
                    data = sock.recv(_MAX_LINE)
                except (BlockingIOError, InterruptedError):
                    continue
                except OSError:
                    data = b""
                if not data:  # closed: a stray connection, or a peer that gave up
                    drop(sock)
                elif sock in pending:
                    buf = pending[sock] + data
                    if b"\n" in buf:
                        greet(sock, buf.split(b"\n", 1)[0])
                    elif len(buf) > _MAX_LINE:
                        drop(sock)
                    else:
                        pending[sock] = buf
                # data from a peer that has joined: nothing is expected, ignore it
        for sock in joined.values():
            _send(sock, "GO")
        _log.info("jax.distributed: all %d processes met at %s", n, address)
        for sock in joined.values():  # let each peer close first (its side keeps TIME_WAIT, not our port)
            try:
                sock.settimeout(max(0.1, min(2.0, deadline - time.monotonic())))
                sock.recv(_MAX_LINE)
            except OSError:
                pass
    finally:
        for sock in list(pending) + list(joined.values()):
            sock.close()
        sel.close()
        listener.close()


def _join(address: str, n: int, pid: int, timeout: float, deadline: float) -> None:
    """A process other than 0: connect to process 0, say who it is, wait for ``GO``; retry until the deadline."""
    host, port = parse_address(address)
    hello = f"{_HELLO} {n} {pid}\n".encode()
    reason, answered = "no attempt was made", False
    while True:
        left = deadline - time.monotonic()
        if left <= 0:
            if answered:
                msg = (f"{_who(pid, n)}: the coordinator at {address} answered, but not every process joined "
                       f"within the timeout of {timeout:g} s")
            else:
                msg = f"{_who(pid, n)}: could not reach the coordinator at {address} within the timeout of {timeout:g} s"
            raise DistributedTimeoutError(f"{msg} ({reason})")
        try:
            with socket.create_connection((host, port), timeout=min(left, 5.0)) as s:
                s.sendall(hello)
                answered = True
                s.settimeout(max(0.01, deadline - time.monotonic()))
                line = _readline(s)
        except socket.timeout:
            reason = "process 0 did not give the go-ahead" if answered else "connection timed out"
            continue
        except OSError as e:
            reason = e.strerror or str(e)
            answered = False
            time.sleep(max(0.0, min(_RETRY_S, deadline - time.monotonic())))
            continue
        if line == "GO":
            return
        if line.startswith("ERR "):
            kind, _, msg = line[4:].partition(" ")
            if kind == "timeout":
                raise DistributedTimeoutError(f"{_who(pid, n)}: {msg}")
            raise DistributedInitError(f"{_who(pid, n)}: {msg}")
        reason = ("process 0 closed the connection" if not line else
                  f"the process listening at {address} is not a gcrsky process 0 (it answered {line[:40]!r})")
        answered = False
        time.sleep(max(0.0, min(_RETRY_S, deadline - time.monotonic())))


def _readline(s: socket.socket) -> str:
    buf = b""
    while b"\n" not in buf and len(buf) <= _MAX_LINE:
        chunk = s.recv(_MAX_LINE)
        if not chunk:
            break
        buf += chunk
    return buf.split(b"\n", 1)[0].decode(errors="replace").strip()
