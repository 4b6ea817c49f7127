"""The real AUBO-i5 through AUBO's own Python SDK (``pyaubo-sdk``, ARCS controllers): a ``RobotInterface``.

``pip install "sagrasp_jax[aubo]"``.  Only the controller's RPC service is used (``pyaubo_sdk.RpcClient``,
port 30004 by default, the factory login ``aubo``): one ``RobotState.getJointPositions`` and one
``MotionControl.servoJoint`` per control period (20 Hz) are a few milliseconds on a LAN, so the RTDE
stream the SDK also offers is not needed at this rate.

Why ``servoJoint`` in servo mode 1 (``setServoModeSelect(1)``, "truncating planning servo"): the loop sends
one absolute joint target per control period and each target supersedes the last, as the training's
position servo tracks the newest target; mode 1 re-plans to every new target at once (mode 5 would pass
through every queued point, a lag the policy never saw).  ``t`` is the control period, the SDK's own advice
("the optimal value is the interval between calls"), the look-ahead one period (clipped to the SDK's
[0.03, 0.2] s) and the gain 150 (SDK range [100, 200]).  The speed and acceleration passed are derived
from the deployment's ``SafetyLayer`` (``DeploySettings`` and the URDF, never the policy):
v = max_j step_limit_j / control_dt (1 rad/s with the defaults), a = v / control_dt.  The SDK documents that
servoJoint currently uses only ``q`` and ``t``, so what really bounds the speed is that every target passes
the same ``SafetyLayer.check`` here (joint limits, per-step change ≤ step_limit, workspace, table) before it
is sent, even when the loop has checked it already: a target at most step_limit away, reached in t.

The gripper (INSPIRE EG2 on the AUBO's tool flange) is driven by the tool digital outputs.  Which outputs at
which level open and close it is ``GripperIO``, configurable (deploy's ``--gripper-io``); the default (tool
DO 0 high = close, low = open, 1 s to settle) is a guess at a common wiring and is UNTESTED ON HARDWARE:
check it against the gripper's wiring, by hand, before a run.

Every SDK call is bounded by the SDK's own request timeout (``RpcClient.setRequestTimeout``; the SDK holds the
GIL while it waits, so no Python watchdog could interrupt it), and the TCP connection is first probed with a
plain socket and its own timeout, so an unreachable host fails in seconds with a message naming host and port
(``AuboConnectionError``: deploy exits 2 and nothing moved).  ``close`` leaves servo mode, logs out and
disconnects.  The controller's joint zero is assumed to be the URDF's (``joint_offset``, default 0); the dry
run (``deploy --backend aubo --host IP --dry-run``) shows the joints so that a user can check this at the home
pose before the first run.

What has run (issue 53): this class with the vendor's own ``RpcClient`` (pyaubo-sdk 0.24.1) inside, end to end
against an emulated controller, ``tests/aubo_emulator.py``, which speaks the wire protocol that client was found
to speak (framing, version check, text login, JSON-RPC calls and result shapes: that file's docstring):
``connect`` and the login, accepted and refused; ``getRobotNames``, ``getJointPositions``, ``getRobotModeType``,
``getSafetyModeType``; ``setServoModeSelect``/``getServoModeSelect``; ``servoJoint`` at the control period;
``isToolIoInput``/``setToolIoInput``/``setToolDigitalOutput`` for the gripper; ``logout`` (client-side only:
it sends nothing) and ``disconnect``; and a whole ``deploy --backend aubo`` episode, the dry run, the home
check, a wrong password, a silent controller and a connection dropped mid-episode (tests/deploy/test_aubo_emulator.py).
Found there and handled here: a refused login shows only in the SDK's log ("login failed"); ``login`` then
raises a request timeout and ``hasLogined()`` is True all the same (``_login``).

What has never run: a real ARCS controller (its own answers: the login reply's text, the codes it returns for
a command it refuses, the enum names it sends, how its servo mode 1 follows the targets, what it does with the
arm when the RPC connection drops in servo mode: the emulator's are guesses where the SDK accepts several);
the AUBO-i5 moving; the real network; the real gripper wiring (which tool outputs at which level open and
close the EG2: ``GripperIO``'s default is a guess).
"""

from __future__ import annotations

import dataclasses
import importlib
import math
import socket
import time
from dataclasses import asdict, dataclass, field
from typing import Any, Callable, Sequence

import numpy as np

from sagrasp_jax.base import extras
from sagrasp_jax.deploy.loop import DeployError
from sagrasp_jax.deploy.safety import DeploySettings, SafetyLayer
from sagrasp_jax.task import robots

ROBOT = robots.AUBO_I5.name  # the one arm this driver drives (env.robot); deploy refuses a policy of another
ARM_DOF = robots.AUBO_I5.dof  # its joints: what the controller reports and takes
DEFAULT_PORT = 30004  # the ARCS controller's RPC port (AUBO's SDK examples)
DEFAULT_USER, DEFAULT_PASSWORD = "aubo", "123456"  # the controller's factory login (AUBO's SDK examples)
SERVO_MODES = {1: "truncating planning servo (the newest target wins)", 5: "planning servo (every target is passed)"}
SERVO_GAIN_RANGE = (100.0, 200.0)  # SDK docs, servoJoint's gain
LOOKAHEAD_RANGE = (0.03, 0.2)  # s, SDK docs, servoJoint's lookahead_time
READY_ROBOT_MODES = ("Running",)  # RobotModeType names a servo command is accepted in
READY_SAFETY_MODES = ("Normal", "ReducedMode")  # SafetyModeType names a servo command is accepted in
HOME_TOLERANCE = 0.05  # rad per joint: the training's start noise (env.task.start_noise, docs/task.md §2.2)


class AuboError(DeployError):
    """The controller refused or failed a call; nothing more is sent."""


class AuboConnectionError(AuboError):
    """No session with the controller (refused, timed out, login refused, SDK unusable): nothing was sent."""


@dataclass(frozen=True)
class ToolOutput:
    """One tool digital output set to one level."""

    index: int
    level: bool


@dataclass(frozen=True)
class GripperIO:
    """The gripper's tool-I/O mapping: the outputs to set to open and to close it, and its settle time.

    Configurable and untested on hardware (module docstring).  ``parse("close=0:1,open=0:0,settle=1.0")``
    reads deploy's ``--gripper-io``; several outputs per action are ``close=0:1+1:0``.
    """

    open: tuple[ToolOutput, ...] = (ToolOutput(0, False),)
    close: tuple[ToolOutput, ...] = (ToolOutput(0, True),)
    settle_s: float = 1.0

    def __post_init__(self) -> None:
        for name in ("open", "close"):
            outputs = getattr(self, name)
            if not outputs:
                raise ValueError(f"gripper I/O: '{name}' sets no tool output")
            for out in outputs:
                if not (isinstance(out.index, int) and 0 <= out.index < 16):
                    raise ValueError(f"gripper I/O: '{name}' tool output index {out.index!r} must be an integer in [0, 16)")
        if not (math.isfinite(self.settle_s) and 0.0 <= self.settle_s <= 10.0):
            raise ValueError(f"gripper I/O: settle time {self.settle_s!r} s must be in [0, 10]")

    @classmethod
    def parse(cls, spec: str) -> GripperIO:
        """``close=I:L[+I:L...],open=I:L[+...],settle=S`` (L is 0 or 1); a key left out keeps its default."""
        values: dict[str, Any] = {}
        for item in filter(None, (part.strip() for part in spec.split(","))):
            key, sep, value = item.partition("=")
            key = key.strip()
            if not sep or key not in ("open", "close", "settle"):
                raise ValueError(f"gripper I/O {spec!r}: {item!r} is not open=I:L, close=I:L or settle=S")
            if key == "settle":
                try:
                    values["settle_s"] = float(value)
                except ValueError:
                    raise ValueError(f"gripper I/O {spec!r}: settle {value!r} is not a number of seconds") from None
                continue
            outputs = []
            for pin in value.split("+"):
                index, colon, level = pin.strip().partition(":")
                if not (colon and index.isdigit() and level in ("0", "1")):
                    raise ValueError(f"gripper I/O {spec!r}: {key} output {pin!r} must be INDEX:LEVEL with LEVEL 0 or 1")
                outputs.append(ToolOutput(int(index), level == "1"))
            values[key] = tuple(outputs)
        return cls(**values)

    def describe(self) -> str:
        def pins(outs: Sequence[ToolOutput]) -> str:
            return "+".join(f"{o.index}:{int(o.level)}" for o in outs)

        return f"close={pins(self.close)},open={pins(self.open)},settle={self.settle_s:g}"


@dataclass(frozen=True)
class AuboSettings:
    """The adapter's own constants (connection, timeouts, servo); the motion limits are ``DeploySettings``'."""

    port: int = DEFAULT_PORT
    user: str = DEFAULT_USER
    password: str = DEFAULT_PASSWORD
    connect_timeout_s: float = 3.0  # TCP probe of host:port
    request_timeout_s: float = 1.0  # every RPC request (RpcClient.setRequestTimeout)
    servo_mode: int = 1
    servo_gain: float = 150.0
    lookahead_s: float | None = None  # default: one control period, clipped to LOOKAHEAD_RANGE
    joint_offset: tuple[float, ...] = (0.0,) * ARM_DOF  # rad: controller reading = URDF joint + offset
    gripper: GripperIO = field(default_factory=GripperIO)

    def __post_init__(self) -> None:
        if not (isinstance(self.port, int) and 1 <= self.port <= 65535):
            raise ValueError(f"AUBO port {self.port!r} must be an integer in [1, 65535]")
        for name in ("connect_timeout_s", "request_timeout_s"):
            value = getattr(self, name)
            if not (math.isfinite(value) and 0.05 <= value <= 60.0):
                raise ValueError(f"AUBO {name} = {value!r} s must be in [0.05, 60]")
        if self.servo_mode not in SERVO_MODES:
            raise ValueError(f"AUBO servo mode {self.servo_mode!r} must be one of {sorted(SERVO_MODES)}")
        lo, hi = SERVO_GAIN_RANGE
        if not lo <= self.servo_gain <= hi:
            raise ValueError(f"AUBO servo gain {self.servo_gain!r} must be in [{lo:g}, {hi:g}] (SDK docs)")
        if self.lookahead_s is not None and not LOOKAHEAD_RANGE[0] <= self.lookahead_s <= LOOKAHEAD_RANGE[1]:
            raise ValueError(f"AUBO look-ahead {self.lookahead_s!r} s must be in {list(LOOKAHEAD_RANGE)} (SDK docs)")
        offset = np.asarray(self.joint_offset, dtype=float)
        if offset.shape != (ARM_DOF,) or not np.isfinite(offset).all() or np.abs(offset).max() > math.pi:
            raise ValueError(f"AUBO joint offset {self.joint_offset!r} must be {ARM_DOF} finite angles within ±π rad")


# ---- pure conversions (NumPy only; tested without the SDK or a controller) ----


def joints_from_controller(values: Any, offset: Sequence[float] = (0.0,) * ARM_DOF) -> np.ndarray:
    """``RobotState.getJointPositions()`` (a list of floats, rad, one per joint) -> URDF joints (dof,), refused unless dof finite."""
    q = np.asarray(list(values) if values is not None else [], dtype=float)
    if q.shape != (ARM_DOF,) or not np.isfinite(q).all():
        raise AuboError(f"controller reported joints {q.tolist()!r}; expected {ARM_DOF} finite angles (rad)")
    return q - np.asarray(offset, dtype=float)


def joints_to_controller(q: Any, offset: Sequence[float] = (0.0,) * ARM_DOF) -> list[float]:
    """URDF joints (dof,) -> the list ``servoJoint`` takes (controller convention)."""
    return [float(v) for v in np.asarray(q, dtype=float) + np.asarray(offset, dtype=float)]


def servo_limits(safety: SafetyLayer) -> tuple[float, float]:
    """(speed rad/s, acceleration rad/s²) for ``servoJoint`` from the deployment's safety layer, never the policy."""
    speed = float(np.max(safety.step_limit) / safety.control_dt)
    return speed, speed / safety.control_dt


def lookahead(settings: AuboSettings, control_dt: float) -> float:
    """The look-ahead time: the setting, else one control period within the SDK's range."""
    if settings.lookahead_s is not None:
        return float(settings.lookahead_s)
    return float(np.clip(control_dt, *LOOKAHEAD_RANGE))


def mode_name(value: Any) -> str:
    """An SDK enum value (``RobotModeType.Running``) or plain string -> its name (``"Running"``)."""
    name = getattr(value, "name", None)
    return str(name) if name is not None else str(value).rsplit(".", 1)[-1]


def check_ready(robot_mode: Any, safety_mode: Any) -> None:
    """Refuse to servo unless the arm is running and its safety mode is normal or reduced."""
    robot, safe = mode_name(robot_mode), mode_name(safety_mode)
    if robot not in READY_ROBOT_MODES or safe not in READY_SAFETY_MODES:
        raise AuboError(f"the arm is not ready to move: robot mode {robot} (needs {' or '.join(READY_ROBOT_MODES)}), "
                        f"safety mode {safe} (needs {' or '.join(READY_SAFETY_MODES)}); power it on, release the brakes "
                        "and clear any stop on the teach pendant")


def code_name(code: int, names: dict[int, str] | None = None) -> str:
    """An SDK return code as ``-8 (AUBO_CONN_REFUSED)``: negative codes are errors, positive warnings."""
    name = (names or {}).get(abs(int(code)))
    return f"{int(code)} ({name})" if name else str(int(code))


@dataclass(frozen=True)
class HomeCheck:
    """Measured joints against the home pose."""

    joints: list[float]
    home: list[float]
    error: list[float]  # joints − home, rad
    max_error: float
    tolerance: float
    at_home: bool


def home_check(q: Any, home: Any, tolerance: float = HOME_TOLERANCE) -> HomeCheck:
    """Whether every joint is within ``tolerance`` rad of ``home`` (the start the policy was trained from)."""
    q, home = np.asarray(q, dtype=float), np.asarray(home, dtype=float)
    err = q - home
    worst = float(np.max(np.abs(err)))
    return HomeCheck([float(v) for v in q], [float(v) for v in home], [float(v) for v in err], worst, float(tolerance),
                     bool(worst <= tolerance))


@dataclass
class DryRunReport:
    """``deploy --backend aubo --dry-run``: what the controller reported; nothing was commanded."""

    host: str
    port: int
    robot_name: str
    robot_mode: str
    safety_mode: str
    home: HomeCheck
    gripper_io: str

    def to_dict(self) -> dict[str, Any]:
        return asdict(self) | {"outcome": "dry_run", "commanded": False}

    def format(self) -> str:
        h = self.home
        deg = ", ".join(f"{math.degrees(v):8.3f}" for v in h.joints)
        err = ", ".join(f"{math.degrees(v):8.3f}" for v in h.error)
        verdict = "AT HOME" if h.at_home else "NOT at home (deploy refuses to start: move it home on the teach pendant)"
        return "\n".join([
            f"controller     {self.host}:{self.port}, robot {self.robot_name!r}, mode {self.robot_mode}, "
            f"safety {self.safety_mode}",
            f"joints (deg)   [{deg}]",
            f"- home (deg)   [{err}]",
            f"home pose      {verdict}: largest error {math.degrees(h.max_error):.3f}° "
            f"(tolerance {math.degrees(h.tolerance):.3f}°)",
            f"gripper I/O    {self.gripper_io} (configurable, untested on hardware; not touched by the dry run)",
            "commanded      nothing (read-only dry run)",
        ])


# ---- the SDK session ----


def probe_tcp(host: str, port: int, timeout_s: float) -> None:
    """Open and close a TCP connection to ``host:port`` within ``timeout_s``, or raise ``AuboConnectionError``
    naming both: the SDK's own connect has no timeout we can set for an unreachable host."""
    where = f"AUBO controller at {host}:{port}"
    try:
        with socket.create_connection((host, port), timeout=timeout_s):
            pass
    except ConnectionRefusedError:
        raise AuboConnectionError(f"{where}: connection refused (is the controller on, and is its RPC service "
                                  "on this port?)") from None
    except socket.timeout:
        raise AuboConnectionError(f"{where}: no connection within {timeout_s:g} s (wrong address, or a cable or "
                                  "network problem?)") from None
    except socket.gaierror as exc:
        raise AuboConnectionError(f"{where}: cannot resolve the host name ({exc})") from None
    except OSError as exc:
        raise AuboConnectionError(f"{where}: {exc.strerror or exc}") from None


def import_sdk() -> Any:
    """``pyaubo_sdk``, or ``MissingExtra`` (exit 2 with the install hint) / ``AuboConnectionError`` (installed, broken)."""
    extras.require("aubo", what="--backend aubo (AUBO's SDK)")
    try:
        return importlib.import_module("pyaubo_sdk")
    except ImportError as exc:
        raise AuboConnectionError(f"pyaubo_sdk is installed but does not import on this machine: {exc}") from None


class AuboRobot:
    """The AUBO-i5 over RPC: ``read_joints``, ``command_joint_targets`` (returns after one control period),
    ``open_gripper``, ``close_gripper``; ``status`` and ``dry_run`` are read-only.  A context manager.

    ``client_factory`` builds the SDK's ``RpcClient`` (default ``pyaubo_sdk.RpcClient``); tests pass a test
    double there, which exercises this class's logic and never the controller's.
    """

    def __init__(self, host: str, port: int | None = None, settings: AuboSettings | None = None,
                 deploy: DeploySettings | None = None, *, client_factory: Callable[[], Any] | None = None,
                 log: Callable[[str], None] | None = None) -> None:
        if not isinstance(host, str) or not host.strip():
            raise AuboConnectionError(f"AUBO host {host!r} must be an IP address or host name")
        self.settings = settings or AuboSettings()
        if port is not None:
            self.settings = dataclasses.replace(self.settings, port=port)
        self.host, self.port = host.strip(), self.settings.port
        self.safety = SafetyLayer(deploy)  # the same limits as the loop's, from DeploySettings and the URDF
        self.control_dt = self.safety.control_dt
        self.speed, self.acceleration = servo_limits(self.safety)
        self.lookahead = lookahead(self.settings, self.control_dt)
        self.overruns = 0  # control periods the command call itself took longer than
        self._log = log or (lambda message: None)
        self._sdk_messages: list[str] = []  # what the SDK logged (its login refusal is only said there)
        self._sdk = None
        self._code_names: dict[int, str] = {}
        if client_factory is None:
            self._sdk = import_sdk()
            self._code_names = {int(v): k for k, v in self._sdk.AuboErrorCodes.__members__.items()}
            client_factory = self._sdk.RpcClient
        self._last: np.ndarray | None = None  # last target sent (URDF convention)
        self._servo = False
        self._outputs_ready: set[int] = set()
        self._next_tick = 0.0
        self._client = None
        self._connect(client_factory)

    # -- session --

    def _where(self) -> str:
        return f"AUBO controller at {self.host}:{self.port}"

    def _connect(self, client_factory: Callable[[], Any]) -> None:
        s = self.settings
        probe_tcp(self.host, self.port, s.connect_timeout_s)
        client = client_factory()
        self._client = client
        try:
            if hasattr(client, "setLogHandler"):  # the SDK prints to stderr otherwise; keep its lines for messages
                client.setLogHandler(self._sdk_log)
            client.setRequestTimeout(int(round(s.request_timeout_s * 1000)))
            code = client.connect(self.host, self.port)
            if code != 0 or not client.hasConnected():
                raise AuboConnectionError(
                    f"{self._where()}: the SDK could not open a session (code {code_name(code, self._code_names)}; a "
                    f"controller that does not answer within {s.request_timeout_s:g} s gives -7)")
            self._login(client)
            names = list(client.getRobotNames())
            if not names:
                raise AuboConnectionError(f"{self._where()}: the controller reports no robot")
            self.robot_name = str(names[0])
            robot = client.getRobotInterface(self.robot_name)
            self._state = robot.getRobotState()
            self._motion = robot.getMotionControl()
            self._io = robot.getIoControl()
        except AuboConnectionError:
            self.close()
            raise
        except Exception as exc:  # AuboException (timeouts) and anything else the SDK raises
            self.close()
            raise AuboConnectionError(f"{self._where()}: {type(exc).__name__}: {exc} (request timeout "
                                      f"{s.request_timeout_s:g} s)") from None

    def _sdk_log(self, level: int, source: str, line: int, message: str) -> None:
        self._sdk_messages.append(str(message))
        self._log(f"[aubo sdk] {message}")

    def _login(self, client: Any) -> None:
        """``RpcClient.login``; a refusal is told apart from a silent controller by the SDK's own log line.

        Found against the SDK 0.24.1 (tests/aubo_emulator.py): a controller that refuses the login answers
        ``__login__...FAILED``; the SDK then logs "login failed" and ``login`` raises ``AuboException("RPC
        request timeout.")`` once the request timeout has passed, and ``hasLogined()`` is True all the same, so
        neither the exception nor ``hasLogined`` says that the login was refused.  The log line comes from the
        SDK's I/O thread, which needs the GIL that the waiting call held: it is given a moment to arrive.
        """
        s = self.settings
        refused = AuboConnectionError(f"{self._where()}: login as {s.user!r} refused (wrong user or password? deploy "
                                      "takes them from $AUBO_USER and $AUBO_PASSWORD)")
        try:
            code = client.login(s.user, s.password)
        except Exception:
            deadline = time.monotonic() + 2.0  # only when login raised: a loaded machine delays the log line
            while "login failed" not in self._sdk_messages and time.monotonic() < deadline:
                time.sleep(0.01)
            if "login failed" in self._sdk_messages:
                raise refused from None
            raise
        if "login failed" in self._sdk_messages:
            raise refused
        if code is not None and int(code) != 0:  # the SDK returns 0 on every login seen; checked all the same
            raise AuboConnectionError(f"{self._where()}: login as {s.user!r} returned "
                                      f"{code_name(code, self._code_names)}")

    def _call(self, what: str, fn: Callable[..., Any], *args: Any) -> Any:
        """One SDK call; its exceptions (request timeouts) become ``AuboError`` naming the call and the controller."""
        try:
            return fn(*args)
        except Exception as exc:
            raise AuboError(f"{self._where()}: {what} failed: {type(exc).__name__}: {exc}") from None

    def _ok(self, what: str, code: Any) -> None:
        code = int(code)
        if code != 0:
            raise AuboError(f"{self._where()}: {what} returned {code_name(code, self._code_names)}; stopped")

    def close(self) -> None:
        """Leave servo mode, log out, disconnect; never raises (a close runs after errors too)."""
        client, self._client = self._client, None
        if client is None:
            return
        steps = []
        if self._servo:
            steps.append(("setServoModeSelect(0)", lambda: self._motion.setServoModeSelect(0)))
        steps += [("logout", client.logout), ("disconnect", client.disconnect)]
        if hasattr(client, "setLogHandler"):  # the SDK logs again when the client is collected; nothing to say then
            steps.append(("setLogHandler", lambda: client.setLogHandler(lambda *args: None)))
        for what, fn in steps:
            try:
                fn()
            except Exception as exc:
                self._log(f"{self._where()}: {what} during close failed: {exc}")
        self._servo = False

    def __enter__(self) -> AuboRobot:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def _session(self) -> None:
        if self._client is None:
            raise AuboError(f"{self._where()}: not connected")

    # -- read-only --

    def read_joints(self) -> np.ndarray:
        self._session()
        return joints_from_controller(self._call("getJointPositions", self._state.getJointPositions),
                                      self.settings.joint_offset)

    def status(self) -> tuple[str, str]:
        """(robot mode, safety mode) names, e.g. ("Running", "Normal")."""
        self._session()
        return (mode_name(self._call("getRobotModeType", self._state.getRobotModeType)),
                mode_name(self._call("getSafetyModeType", self._state.getSafetyModeType)))

    def dry_run(self, home: Any, tolerance: float = HOME_TOLERANCE) -> DryRunReport:
        """Joints, modes and the home check; sends no command and writes no output."""
        robot_mode, safety_mode = self.status()
        return DryRunReport(self.host, self.port, self.robot_name, robot_mode, safety_mode,
                            home_check(self.read_joints(), home, tolerance), self.settings.gripper.describe())

    # -- motion --

    def _start_servo(self) -> None:
        check_ready(*self.status())
        mode = self.settings.servo_mode
        self._ok(f"setServoModeSelect({mode})", self._call("setServoModeSelect", self._motion.setServoModeSelect, mode))
        self._servo = True
        for _ in range(50):  # the SDK's examples poll until the mode shows (a few ms)
            if int(self._call("getServoModeSelect", self._motion.getServoModeSelect)) == mode:
                break
            time.sleep(0.005)
        else:
            raise AuboError(f"{self._where()}: servo mode {mode} did not come on within 0.25 s")
        self._last = self.read_joints()
        self._next_tick = time.monotonic()

    def command_joint_targets(self, q: np.ndarray) -> None:
        """Check ``q`` with the deployment's safety layer against the last target (the measured joints at the
        first), send it with ``servoJoint`` and return at the end of this control period."""
        self._session()
        if not self._servo:
            self._start_servo()
        q = self.safety.check(q, self._last)  # raises SafetyViolation, nothing sent
        code = self._call("servoJoint", self._motion.servoJoint, joints_to_controller(q, self.settings.joint_offset),
                          self.acceleration, self.speed, self.control_dt, self.lookahead, self.settings.servo_gain)
        self._ok("servoJoint", code)
        self._last = q.copy()
        self._next_tick += self.control_dt
        delay = self._next_tick - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        else:
            self.overruns += 1
            self._next_tick = time.monotonic()

    def _set_outputs(self, outputs: Sequence[ToolOutput], what: str) -> None:
        self._session()
        for out in outputs:
            if out.index not in self._outputs_ready:
                if self._call("isToolIoInput", self._io.isToolIoInput, out.index):
                    self._ok(f"setToolIoInput({out.index}, False)",
                             self._call("setToolIoInput", self._io.setToolIoInput, out.index, False))
                self._outputs_ready.add(out.index)
            self._ok(f"{what}: setToolDigitalOutput({out.index}, {out.level})",
                     self._call("setToolDigitalOutput", self._io.setToolDigitalOutput, out.index, out.level))
        time.sleep(self.settings.gripper.settle_s)
        self._next_tick = time.monotonic()  # the arm held its last target meanwhile; restart the period clock

    def open_gripper(self) -> None:
        self._set_outputs(self.settings.gripper.open, "open gripper")

    def close_gripper(self) -> None:
        self._set_outputs(self.settings.gripper.close, "close gripper")
