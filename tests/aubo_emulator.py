"""An emulated AUBO ARCS controller's RPC service, for the tests to run the vendor's own client against.

    with AuboEmulator(joints=HOME_Q) as emu:            # a child process serving 127.0.0.1:emu.port
        robot = AuboRobot("127.0.0.1", emu.port)        # deploy.aubo with pyaubo_sdk.RpcClient inside
        ...
        emu.calls("servoJoint"), emu.state()            # what the controller received, where its joints are

It speaks the wire protocol of ``pyaubo-sdk`` 0.24.1's ``RpcClient`` as found by pointing that client at
loopback listeners, logging its bytes and answering until it accepted the answers (issue 53).  Nothing here
has seen a real controller: where the SDK accepts several answers (the login's reply text, the code a refused
command returns), the emulator's choice is marked a GUESS.

**Why a child process.**  The SDK holds the GIL while it waits for a reply, so a server thread in the test's
own process could never answer (found: the version check then times out although the reply is written
right after).  ``AuboEmulator`` runs this file as a script (``python tests/aubo_emulator.py CONFIG``): a
threaded TCP server on 127.0.0.1 at an ephemeral port, controlled over its stdin/stdout, one JSON line each
way (``calls``, ``state``, ``set``).

**The protocol, as found** (SDK 0.24.1, "SDK INTERFACE VERSION 0.24.0"):

* Framing, both ways: ``b"SOF"``, one type byte (``0x01`` on every request seen; the emulator answers with
  ``0x01``), the payload's length as 4 bytes big-endian, the payload.  Requests and replies are matched
  one to one (the client has one request in flight).
* ``connect(host, port)``: opens TCP and sends the JSON-RPC 2.0 request
  ``{"id": "<8-4-4 random>", "jsonrpc": "2.0", "method": "SystemInfo.getInterfaceVersionCode"}``; the
  reply ``{"id": <same>, "jsonrpc": "2.0", "result": 24000}`` (major·10⁶ + minor·10³ + patch = 0.24.0) makes
  it return 0.  Unanswered: -7 after the request timeout (``hasConnected()`` is True all the same); another
  major version (1024000): -15 (``AUBO_VERSION_INCOMPAT``) and the client disconnects; another minor: 0.
* ``login(user, password)``: a *text* payload ``"__login__\\n<user>\\n<token>\\n0.24.0\\n"`` (the token is
  the SDK's encoding of the password, not a cryptographic hash: "123456" and "abcdef" encode alike).  The
  reply is text too: starting ``__login__`` and ending ``SUCCEED``, the client goes on with ``getRobotNames``
  and ``getAxisNames`` (JSON-RPC, both must be arrays) and returns 0; ending ``FAILED``, it logs
  "login failed" (warning) and raises ``AuboException("RPC request timeout.")`` once the request timeout
  has passed; ``hasLogined()`` is True after that too.  Any other reply: a "reply parse error" warning and
  the login goes on as if accepted.  The emulator answers ``__login__\\nSUCCEED`` or ``__login__\\nFAILED``
  (GUESS: the SDK reads only the two ends).
* Robot calls: ``"method": "<robot>.<Interface>.<name>"`` (``rob1.RobotState.getJointPositions``), the
  arguments as a JSON object by name, no ``params`` without arguments: ``setServoModeSelect {mode}``,
  ``servoJoint {q, a, v, t, lookahead_time, gain}``, ``isToolIoInput {index}``, ``setToolIoInput {index,
  input}``, ``setToolDigitalOutput {index, value}``, ``getToolDigitalOutput {index}``.
* Results: return codes and counts as integers, booleans, joint lists as arrays of numbers, and enums as
  their names: ``"Running"``, ``"Normal"`` (an integer, or a name the enum lacks, decodes silently as the
  enum's first member, ``RobotModeType.NoController`` / ``SafetyModeType.Undefined``).  A result of the
  wrong JSON type raises ``AuboException("<method>-[json.exception.type_error.302] ...")``; a JSON-RPC
  ``error {code, message}`` raises ``AuboException("<method>-<code>: <message>")``; a reply with another id
  fails the pending call (logged "JsonRPC id unmatch", raised at the request timeout).
* ``logout()`` sends nothing (the client forgets the login); ``disconnect()`` closes the socket.
* The controller closing the connection: the call in flight raises ``AuboException("RPC request
  timeout.")`` at the request timeout (a FIN) or at once ``"RPC client recv package failed: Connection reset
  by peer"`` (an RST); later calls raise ``"RPC client has not connected"`` at once, ``hasConnected()``
  is False.

**The emulated controller.**  One robot, ``rob1``, running (``robot_mode``/``safety_mode`` settable).  Its
joints move kinematically: ``servoJoint(q, t)`` in servo mode takes every joint from where it is to ``q`` in
``t`` seconds, no joint faster than ``max_joint_speed`` (clamped: then it gets there later).  ``servoJoint``
outside servo mode returns -1 (GUESS; ``AUBO_BAD_STATE``), and a ``q`` without 6 finite numbers -5
(``AUBO_INVL_ARGUMENT``).  Tool pins 0-3 start as inputs; ``setToolDigitalOutput`` on an input pin returns -1
(GUESS).  Robot calls on a connection that has not logged in get a JSON-RPC error (GUESS).  Unknown methods get
JSON-RPC error -32601.  It accepts the user ``aubo`` with the token the SDK sends for the factory password
``123456`` (``FACTORY_LOGIN_TOKEN``, captured from the SDK) unless ``refuse_login``.

Misbehaviour, for the tests (``AuboEmulator(...)`` or ``emu.set(...)``): ``refuse_login`` (answers
FAILED), ``silent`` (reads every request, answers none), ``drop_at_servo=N`` (closes the connection, without
answering, when the N-th ``servoJoint`` of the emulator's life arrives; ``drop_mode`` ``"close"``, a FIN,
or ``"reset"``, an RST).

Every request is recorded (``calls``): connection number, the child's ``time.monotonic()`` (the same clock as
the tests' on Linux), the method in full and its short name, the parameters and the answer (``None``:
unanswered); and the connection's events (``accept``, ``eof``: closed by the client, ``dropped``).
"""

from __future__ import annotations

import json
import math
import os
import socket
import socketserver
import struct
import subprocess
import sys
import threading
import time
from typing import Any, Sequence

INTERFACE_VERSION_CODE = 24000  # 0.24.0, what pyaubo-sdk 0.24.1 calls itself
FACTORY_USER = "aubo"
FACTORY_LOGIN_TOKEN = "3353545435353664345433434443435463466335333566235443434253142434333426365553"  # "123456"
ROBOT_NAME = "rob1"
TOOL_PINS = 4
DEFAULT_MAX_JOINT_SPEED = math.radians(150.0)  # rad/s: the AUBO-i5's joint speed limit (datasheet)
BAD_STATE, INVALID_ARGUMENT = -1, -5


def frame(payload: bytes, kind: int = 1) -> bytes:
    """``SOF``, the type byte, the length (4 bytes, big-endian), the payload."""
    return b"SOF" + bytes([kind]) + struct.pack(">I", len(payload)) + payload


class Controller:
    """The emulated controller's state and behaviour; every method is called under ``lock``."""

    def __init__(self, joints: Sequence[float], robot_mode: str = "Running", safety_mode: str = "Normal",
                 max_joint_speed: float = DEFAULT_MAX_JOINT_SPEED, refuse_login: bool = False, silent: bool = False,
                 drop_at_servo: int | None = None, drop_mode: str = "close",
                 users: dict[str, str] | None = None) -> None:
        self.lock = threading.Lock()
        self.robot_mode, self.safety_mode = robot_mode, safety_mode
        self.max_joint_speed = float(max_joint_speed)
        self.refuse_login, self.silent = refuse_login, silent
        self.drop_at_servo, self.drop_mode = drop_at_servo, drop_mode
        self.users = dict(users) if users is not None else {FACTORY_USER: FACTORY_LOGIN_TOKEN}
        self.servo_mode = 0
        self.tool_is_input = {i: True for i in range(TOOL_PINS)}
        self.tool_output = {i: False for i in range(TOOL_PINS)}
        # the joints' motion: from q_from at t_from towards q_to at per-joint speeds
        self.q_from = [float(v) for v in joints]
        self.q_to = list(self.q_from)
        self.speed = [0.0] * 6
        self.t_from = time.monotonic()
        self.servo_count = 0
        self.calls: list[dict[str, Any]] = []
        self.connections = 0
        self.open_connections: set[int] = set()

    # -- the arm --

    def joints(self, now: float | None = None) -> list[float]:
        dt = (time.monotonic() if now is None else now) - self.t_from
        out = []
        for a, b, v in zip(self.q_from, self.q_to, self.speed):
            step = min(abs(b - a), v * dt)
            out.append(a + math.copysign(step, b - a))
        return out

    def servo_to(self, q: list[float], t: float) -> None:
        now = time.monotonic()
        here = self.joints(now)
        duration = max(float(t), 1e-3)
        self.speed = [min(abs(b - a) / duration, self.max_joint_speed) for a, b in zip(here, q)]
        self.q_from, self.q_to, self.t_from = here, list(q), now

    def set_joints(self, q: Sequence[float]) -> None:
        self.q_from = [float(v) for v in q]
        self.q_to, self.speed, self.t_from = list(self.q_from), [0.0] * 6, time.monotonic()

    # -- the RPC service --

    def answer(self, method: str, params: dict[str, Any], logged_in: bool) -> tuple[str, Any]:
        """("result", value) or ("error", {code, message}) for one JSON-RPC request."""
        name = method.rsplit(".", 1)[-1]
        if method == "SystemInfo.getInterfaceVersionCode":
            return "result", INTERFACE_VERSION_CODE
        if not logged_in:
            return "error", {"code": -32000, "message": "not logged in"}
        if method == "getRobotNames":
            return "result", [ROBOT_NAME]
        if method == "getAxisNames":
            return "result", []
        prefix = method.rsplit(".", 2)[0] if method.count(".") == 2 else None
        if prefix != ROBOT_NAME:
            return "error", {"code": -32601, "message": "Method not found"}
        interface = method.split(".")[1]
        if interface == "RobotState":
            if name == "getJointPositions":
                return "result", self.joints()
            if name == "getRobotModeType":
                return "result", self.robot_mode
            if name == "getSafetyModeType":
                return "result", self.safety_mode
        if interface == "MotionControl":
            if name == "setServoModeSelect":
                self.servo_mode = int(params["mode"])
                return "result", 0
            if name == "getServoModeSelect":
                return "result", self.servo_mode
            if name == "isServoModeEnabled":
                return "result", self.servo_mode != 0
            if name == "servoJoint":
                q = params.get("q")
                if not (isinstance(q, list) and len(q) == 6 and all(isinstance(v, (int, float)) and math.isfinite(v)
                                                                    for v in q)):
                    return "result", INVALID_ARGUMENT
                if self.servo_mode == 0 or self.robot_mode != "Running":
                    return "result", BAD_STATE
                self.servo_to([float(v) for v in q], float(params.get("t", 0.0)))
                return "result", 0
        if interface == "IoControl":
            index = params.get("index")
            if name in ("isToolIoInput", "setToolIoInput", "setToolDigitalOutput", "getToolDigitalOutput") and \
                    index not in self.tool_is_input:
                return "result", INVALID_ARGUMENT if name.startswith("set") else False
            if name == "isToolIoInput":
                return "result", self.tool_is_input[index]
            if name == "setToolIoInput":
                self.tool_is_input[index] = bool(params["input"])
                return "result", 0
            if name == "setToolDigitalOutput":
                if self.tool_is_input[index]:
                    return "result", BAD_STATE
                self.tool_output[index] = bool(params["value"])
                return "result", 0
            if name == "getToolDigitalOutput":
                return "result", self.tool_output[index]
        return "error", {"code": -32601, "message": "Method not found"}

    def state(self) -> dict[str, Any]:
        now = time.monotonic()
        return {"joints": self.joints(now), "target": list(self.q_to), "servo_mode": self.servo_mode,
                "robot_mode": self.robot_mode, "safety_mode": self.safety_mode,
                "tool_is_input": {str(k): v for k, v in self.tool_is_input.items()},
                "tool_output": {str(k): v for k, v in self.tool_output.items()},
                "servo_count": self.servo_count, "connections": self.connections,
                "open_connections": sorted(self.open_connections), "time": now}

    def configure(self, **kw: Any) -> None:
        for key, value in kw.items():
            if key == "joints":
                self.set_joints(value)
            elif key in ("robot_mode", "safety_mode", "refuse_login", "silent", "drop_at_servo", "drop_mode",
                         "max_joint_speed", "users"):
                setattr(self, key, value)
            else:
                raise KeyError(f"unknown emulator setting {key!r}")


class _Handler(socketserver.BaseRequestHandler):
    """One client connection: frames in, frames out, everything recorded."""

    server: _Server

    def _record(self, entry: dict[str, Any]) -> dict[str, Any]:
        entry = {"conn": self.conn, "t": time.monotonic(), **entry}
        self.server.controller.calls.append(entry)
        return entry

    def _recv(self, n: int) -> bytes:
        data = b""
        while len(data) < n:
            chunk = self.request.recv(n - len(data))
            if not chunk:
                raise EOFError
            data += chunk
        return data

    def _drop(self) -> None:
        ctl = self.server.controller
        if ctl.drop_mode == "reset":  # an RST: SO_LINGER on with a zero timeout
            self.request.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
        else:
            self.request.shutdown(socket.SHUT_RDWR)
        self.request.close()
        self._record({"event": "dropped", "mode": ctl.drop_mode})

    def handle(self) -> None:
        ctl = self.server.controller
        with ctl.lock:
            ctl.connections += 1
            self.conn = ctl.connections
            ctl.open_connections.add(self.conn)
            self._record({"event": "accept"})
        logged_in = False
        try:
            while True:
                try:
                    head = self._recv(8)
                    payload = self._recv(struct.unpack(">I", head[4:8])[0])
                except (EOFError, ConnectionError, OSError):
                    with ctl.lock:
                        self._record({"event": "eof"})
                    return
                with ctl.lock:
                    if head[:3] != b"SOF":
                        self._record({"event": "bad_frame", "head": head.hex()})
                        return
                    reply, drop, login = self._serve(head[3], payload, logged_in)
                    logged_in = logged_in or login
                    if drop:
                        self._drop()
                        return
                if reply is not None:
                    self.request.sendall(reply)
        finally:
            with ctl.lock:
                ctl.open_connections.discard(self.conn)

    def _serve(self, kind: int, payload: bytes, logged_in: bool) -> tuple[bytes | None, bool, bool]:
        """(the framed reply or None, whether to drop the connection instead, whether a login was accepted)."""
        ctl = self.server.controller
        if payload.startswith(b"__login__"):
            _, user, token, version = (payload.decode(errors="replace").split("\n") + ["", "", ""])[:4]
            accepted = not ctl.refuse_login and ctl.users.get(user) == token
            entry = self._record({"method": "__login__", "name": "login", "kind": kind,
                                  "params": {"user": user, "token": token, "sdk_version": version},
                                  "answer": None})
            if ctl.silent:
                return None, False, False
            entry["answer"] = "SUCCEED" if accepted else "FAILED"
            return frame(f"__login__\n{entry['answer']}".encode()), False, accepted
        try:
            request = json.loads(payload)
            method, params = str(request["method"]), dict(request.get("params") or {})
        except (ValueError, KeyError, TypeError):
            self._record({"event": "bad_request", "payload": payload.decode(errors="replace")})
            return None, False, False
        entry = self._record({"method": method, "name": method.rsplit(".", 1)[-1], "kind": kind, "params": params,
                              "answer": None})
        if entry["name"] == "servoJoint":
            ctl.servo_count += 1
            if ctl.drop_at_servo is not None and ctl.servo_count >= ctl.drop_at_servo:
                return None, True, False
        if ctl.silent:
            return None, False, False
        what, value = ctl.answer(method, params, logged_in)
        entry["answer"] = {what: value}
        return frame(json.dumps({"id": request.get("id"), "jsonrpc": "2.0", what: value}).encode()), False, False


class _Server(socketserver.ThreadingTCPServer):
    daemon_threads = True
    allow_reuse_address = True

    def __init__(self, controller: Controller) -> None:
        self.controller = controller
        super().__init__(("127.0.0.1", 0), _Handler)


def _child(config: dict[str, Any]) -> None:
    """The child process: serve, and answer the parent's JSON lines on stdin until it closes them."""
    controller = Controller(**config)
    server = _Server(controller)
    threading.Thread(target=server.serve_forever, kwargs={"poll_interval": 0.05}, daemon=True).start()
    out = sys.stdout
    out.write(json.dumps({"port": server.server_address[1]}) + "\n")
    out.flush()
    for line in sys.stdin:
        try:
            cmd = json.loads(line)
            op = cmd.pop("op")
            with controller.lock:
                if op == "calls":
                    reply: Any = {"calls": list(controller.calls)}
                elif op == "state":
                    reply = {"state": controller.state()}
                elif op == "set":
                    controller.configure(**cmd)
                    reply = {"state": controller.state()}
                else:
                    reply = {"error": f"unknown op {op!r}"}
        except Exception as exc:  # a bad command must not kill the emulator: the parent raises it
            reply = {"error": f"{type(exc).__name__}: {exc}"}
        out.write(json.dumps(reply) + "\n")
        out.flush()
    server.shutdown()
    server.server_close()


class AuboEmulator:
    """The emulated controller in a child process (module docstring); a context manager.  ``port`` is its RPC port."""

    host = "127.0.0.1"

    def __init__(self, joints: Sequence[float] = (0.0,) * 6, **settings: Any) -> None:
        config = {"joints": [float(v) for v in joints], **settings}
        self._proc = subprocess.Popen([sys.executable, os.path.abspath(__file__), json.dumps(config)],
                                      stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
        line = self._proc.stdout.readline()
        if not line:
            self._proc.wait(5)
            raise RuntimeError(f"the AUBO emulator did not start (exit {self._proc.returncode})")
        self.port = int(json.loads(line)["port"])

    def _ask(self, op: str, **kw: Any) -> dict[str, Any]:
        self._proc.stdin.write(json.dumps({"op": op, **kw}) + "\n")
        self._proc.stdin.flush()
        reply = json.loads(self._proc.stdout.readline())
        if "error" in reply:
            raise RuntimeError(f"AUBO emulator: {reply['error']}")
        return reply

    def calls(self, *names: str) -> list[dict[str, Any]]:
        """Every recorded request and event, or only the requests with these short names (``servoJoint``)."""
        calls = self._ask("calls")["calls"]
        return [c for c in calls if c.get("name") in names] if names else calls

    def state(self) -> dict[str, Any]:
        return self._ask("state")["state"]

    def set(self, **settings: Any) -> dict[str, Any]:
        """Change state or behaviour now (``joints``, ``robot_mode``, ``silent``, ``drop_at_servo``, ...)."""
        return self._ask("set", **settings)["state"]

    def close(self) -> None:
        if self._proc.poll() is None:
            self._proc.stdin.close()
            try:
                self._proc.wait(5)
            except subprocess.TimeoutExpired:
                self._proc.kill()
                self._proc.wait()
        self._proc.stdout.close()

    def __enter__(self) -> AuboEmulator:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


if __name__ == "__main__":
    _child(json.loads(sys.argv[1]))
