"""Multi-process training through ``jax.distributed``: one process per host, the global env batch
split over every device of every process (docs/task.md §3 "Multiple devices").

Start the same command on every host, each with its ``--process-id``::

    # host 0 (the coordinator)                        # host 1
    python -m sagrasp_jax.train --out runs/big \\       python -m sagrasp_jax.train --out runs/big \\
        --coordinator host0:12355 --num-processes 2 \\      --coordinator host0:12355 --num-processes 2 \\
        --process-id 0 [--preset ... --set ...]              --process-id 1 [--preset ... --set ...]

Every process builds the same config, the same global env batch (``ppo.num_envs`` in all) and
the same replicated parameters; each steps only its own devices' envs (their keys are slices of
one global split, so the processes' envs are seeded apart), and gradients, normaliser and
advantage statistics are averaged over all devices (``ppo.make_cycle``).  The SA schedule runs
on every process on the same (replicated) evaluation, so all take the same decisions.  Only
process 0 writes the run folder; ``--resume`` needs its checkpoint readable by every process
(a shared file system or a copy).  On CPU the collectives go through gloo.

**Checked and time-boxed start.**  The options are checked first (``check_options``: a
``HOST:PORT`` coordinator, ``--num-processes`` ≥ 1, ``--process-id`` in range, a ``ppo.num_envs``
that every process gets an equal share of).  Then, before ``jax.distributed`` (whose own waits
end in an abort after minutes), the processes meet at the coordinator's port (``rendezvous``):
process 0 listens there and waits for every other process to check in, the others connect to it.
Whoever is missing after ``--connect-timeout`` seconds (default ``CONNECT_TIMEOUT``, 300) is
named in a ``DistributedError`` (exit status 2): "process 1 never connected" on process 0,
"cannot reach the coordinator" on the others (also when something else at that address accepts the
connection without answering as process 0: a proxy or a firewall in front of an unroutable address).  Process 0 then closes the port and jax's
coordination service takes it over, with the same timeout.
"""

from __future__ import annotations

import sagrasp_jax  # noqa: F401  (XLA flags before jax)

import math
import socket
import time

import numpy as np

from sagrasp_jax.task.config import ConfigError

CONNECT_TIMEOUT = 300.0  # s: how long the processes wait for each other at start (--connect-timeout)
MAX_PROCESSES = 65_536
_HELLO = b"sagrasp-jax-rendezvous"
_ACK = b"sagrasp-jax-coordinator\n"  # process 0's answer to a hello, before the go
HELLO_TIMEOUT = 5.0  # s: a process sends its hello as it connects; a silent connection is dropped after this


class DistributedError(RuntimeError):
    """The processes of a multi-process run could not all meet; the message names who is missing."""


def parse_coordinator(coordinator: str) -> tuple[str, int]:
    """``HOST:PORT`` (``[v6 address]:PORT`` too) -> (host, port); ConfigError naming the option."""
    host, sep, port = str(coordinator).strip().rpartition(":")
    host = host[1:-1] if host.startswith("[") and host.endswith("]") else host
    if not sep or not host or not port.isdigit() or not 1 <= int(port) <= 65_535:
        raise ConfigError(f"--coordinator {coordinator!r} must be HOST:PORT (e.g. host0:12355), with a port in 1 … 65535")
    return host, int(port)


def check_options(coordinator: str | None, num_processes: int, process_id: int, num_envs: int,
                  timeout: float = CONNECT_TIMEOUT) -> None:
    """Refuse unusable multi-process options (ConfigError naming the option) before anything starts."""
    if not 1 <= num_processes <= MAX_PROCESSES:
        raise ConfigError(f"--num-processes={num_processes} must lie in 1 … {MAX_PROCESSES}")
    if not 0 <= process_id < num_processes:
        raise ConfigError(f"--process-id={process_id} must lie in 0 … {num_processes - 1} (--num-processes {num_processes})")
    if not (math.isfinite(timeout) and 1 <= timeout <= 86_400):
        raise ConfigError(f"--connect-timeout={timeout} must be a number of seconds in 1 … 86400")
    if coordinator is None:
        if num_processes != 1 or process_id != 0:
            raise ConfigError("--num-processes and --process-id need --coordinator HOST:PORT (the address of process 0)")
        return
    parse_coordinator(coordinator)
    if num_envs % num_processes:
        raise ConfigError(f"ppo.num_envs={num_envs} must be divisible by --num-processes={num_processes} (every "
                          "process steps an equal share of the env batch)")


def _peer_id(conn: socket.socket, deadline: float) -> int | None:
    """The process id a connecting process announces (None: not one of ours)."""
    conn.settimeout(max(0.1, deadline - time.monotonic()))
    data = b""
    while not data.endswith(b"\n") and len(data) < 128:
        chunk = conn.recv(128)
        if not chunk:
            break
        data += chunk
    words = data.strip().split(b" ")
    if len(words) == 2 and words[0] == _HELLO and words[1].isdigit():
        return int(words[1])
    return None


def _host_rendezvous(port: int, num_processes: int, timeout: float, address: str) -> None:
    """Process 0: accept every other process's hello on ``port``, then let them all go."""
    try:
        if socket.has_dualstack_ipv6():
            server = socket.create_server(("", port), family=socket.AF_INET6, dualstack_ipv6=True, reuse_port=False)
        else:
            server = socket.create_server(("", port))
    except OSError as exc:
        raise DistributedError(f"process 0 cannot listen on port {port} of --coordinator {address}: "
                               f"{exc.strerror or exc} (is another run using it?)") from None
    deadline = time.monotonic() + timeout
    peers: dict[int, socket.socket] = {}
    try:
        with server:
            while len(peers) < num_processes - 1:
                server.settimeout(max(0.0, deadline - time.monotonic()))
                try:
                    conn, _ = server.accept()
                except (socket.timeout, TimeoutError):
                    missing = [i for i in range(1, num_processes) if i not in peers]
                    raise DistributedError(
                        f"process {_names(missing)} never connected to the coordinator {address} within "
                        f"{timeout:g} s (--connect-timeout): start every process with the same --coordinator and "
                        f"--num-processes {num_processes}, each with its own --process-id") from None
                try:
                    pid = _peer_id(conn, min(deadline, time.monotonic() + HELLO_TIMEOUT))
                except OSError:
                    pid = None
                if pid is None or not 1 <= pid < num_processes or pid in peers:
                    conn.close()  # not one of ours (a port scanner), or a duplicate --process-id
                    if pid is not None and (pid in peers or pid == 0):
                        raise DistributedError(f"two processes started with --process-id {pid} (coordinator {address})")
                    continue
                try:
                    conn.sendall(_ACK)  # "you reached process 0": the peer now waits for the others
                except OSError:
                    conn.close()
                    continue
                peers[pid] = conn
            for conn in peers.values():
                conn.sendall(b"go\n")
            for conn in peers.values():  # they close first: the port is free of our connections for jax
                conn.settimeout(max(1.0, deadline - time.monotonic()))
                try:
                    conn.recv(16)
                except OSError:
                    pass
    finally:
        for conn in peers.values():
            conn.close()


def _read_line(conn: socket.socket, deadline: float, buffer: bytearray, limit: int = 64) -> bytes | None:
    """The next line from ``conn`` (without its newline; what follows it stays in ``buffer``) before
    ``deadline``; b"" when the other side closed first, None when no whole line came in time."""
    while b"\n" not in buffer and len(buffer) < limit:
        conn.settimeout(max(0.01, deadline - time.monotonic()))
        try:
            chunk = conn.recv(limit)
        except (socket.timeout, TimeoutError):
            return None
        if not chunk:
            break
        buffer += chunk
    line, _, rest = bytes(buffer).partition(b"\n")
    buffer[:] = rest
    return line


def _peer_rendezvous(host: str, port: int, process_id: int, timeout: float, address: str) -> None:
    """Process ``process_id`` > 0: check in with process 0 (retrying until it listens), wait for the go.

    Process 0 answers a hello at once (``_ACK``), so a connection that something else accepted (a proxy,
    a firewall or another service at an unroutable or wrong address) is told from process 0 waiting for
    the others: only after that answer is the coordinator reached."""
    deadline = time.monotonic() + timeout
    last = "no answer"
    while True:
        left = deadline - time.monotonic()
        if left <= 0:
            raise DistributedError(f"process {process_id} cannot reach the coordinator {address} (process 0) within "
                                   f"{timeout:g} s (--connect-timeout): {last}; is process 0 running, and is "
                                   f"{address} its address?")
        try:
            with socket.create_connection((host, port), timeout=min(left, 5.0)) as conn:
                conn.sendall(_HELLO + b" %d\n" % process_id)
                buffer = bytearray()
                ack = _read_line(conn, deadline, buffer)
                if ack != _ACK.strip():
                    last = (f"something at {address} accepted the connection but never answered as process 0"
                            + (f" (it answered {ack[:24]!r})" if ack else "") + ": the coordinator was not reached")
                else:
                    answer = _read_line(conn, deadline, buffer)
                    if answer is None:
                        raise DistributedError(
                            f"process {process_id}: the coordinator {address} did not see every process within "
                            f"{timeout:g} s (--connect-timeout); see process 0's error for the missing one")
                    if answer.startswith(b"go"):
                        return
                    last = "the coordinator closed the connection"
        except socket.gaierror as exc:
            raise DistributedError(f"--coordinator {address}: unknown host {host!r} ({exc.strerror or exc})") from None
        except OSError as exc:
            last = exc.strerror or str(exc)
        time.sleep(min(0.5, max(0.0, deadline - time.monotonic())))


def _names(ids: list[int]) -> str:
    return ", ".join(str(i) for i in ids[:10]) + (f" and {len(ids) - 10} more" if len(ids) > 10 else "")


def rendezvous(coordinator: str, num_processes: int, process_id: int, timeout: float = CONNECT_TIMEOUT) -> None:
    """Meet every process of the run at the coordinator's port, or raise DistributedError naming the
    missing one within ``timeout`` seconds."""
    host, port = parse_coordinator(coordinator)
    if num_processes == 1:
        return
    if process_id == 0:
        _host_rendezvous(port, num_processes, timeout, coordinator)
    else:
        _peer_rendezvous(host, port, process_id, timeout, coordinator)


def initialize(coordinator: str, num_processes: int, process_id: int, timeout: float = CONNECT_TIMEOUT) -> None:
    """Join the distributed run (call before any jax computation): check the options, meet every
    process (``rendezvous``, time-boxed), then start ``jax.distributed``."""
    import jax

    check_options(coordinator, num_processes, process_id, num_processes, timeout)
    rendezvous(coordinator, num_processes, process_id, timeout)
    jax.config.update("jax_cpu_collectives_implementation", "gloo")  # CPU collectives across processes
    jax.distributed.initialize(coordinator_address=coordinator, num_processes=num_processes, process_id=process_id,
                               initialization_timeout=max(1, int(math.ceil(timeout))))


def all_ok(ok: bool) -> bool:
    """True on every process iff ``ok`` is true on every process (a collective when distributed)."""
    import jax

    if jax.process_count() == 1:
        return ok
    from jax.experimental import multihost_utils

    return bool(np.all(multihost_utils.process_allgather(np.int32(ok))))
