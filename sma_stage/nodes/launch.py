"""Start the package's node executables as child processes and talk to them from this process.

`NodeProcesses` starts installed executables (stage_node, compensator_node, identification_node) with
parameters, logs each one to a file and stops them all (SIGTERM, then SIGKILL) when its `with` block
ends, whatever ends it; on Linux a child also gets SIGTERM if this process dies without cleaning up.
`RosClient` is a private rclpy context with a background executor: wait for services, call Trigger
services, set and get parameters, read the (simulated) clock.
"""

from __future__ import annotations

import ctypes
import gc
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path
from types import TracebackType
from typing import Any

import yaml

from sma_stage.errors import InputError


def find_config_dir(package_file: Path = Path(__file__)) -> Path:
    """The parameter files' folder: `config/` of the source tree (a checkout or an editable install), else
    `share/sma_stage/config` of the install prefix the package sits in (colcon's `install/sma_stage`)."""
    here = package_file.resolve()
    source = here.parents[2] / "config"
    if (source / "stage.yaml").is_file():
        return source
    for prefix in here.parents:
        installed = prefix / "share" / "sma_stage" / "config"
        if (installed / "stage.yaml").is_file():
            return installed
    raise InputError(f"no config/stage.yaml next to {here.parents[2]} nor under any share/sma_stage above it")


CONFIG_DIR = find_config_dir()
DEFAULT_MODEL_FILE = CONFIG_DIR / "model_default.yaml"  # the model the compensator starts with
STOP_TIMEOUT_S = 10.0
_PR_SET_PDEATHSIG = 1


def find_executable(name: str) -> Path:
    """The installed executable `name`: next to this Python (a venv's bin/) or on PATH."""
    beside = Path(sys.executable).parent / name
    if beside.is_file() and os.access(beside, os.X_OK):
        return beside
    found = shutil.which(name)
    if found is None:
        raise InputError(f"executable '{name}' not found next to {sys.executable} or on PATH: is sma_stage installed?")
    return Path(found)


def ros_environment(domain_id: int) -> dict[str, str]:
    """This process's environment for a child node: the given domain, local discovery, Fast DDS by default."""
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain_id), PYTHONUNBUFFERED="1", RCUTILS_COLORIZED_OUTPUT="0")
    env.setdefault("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp")
    env.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    env.pop("ROS_LOCALHOST_ONLY", None)
    return env


def _die_with_parent() -> Callable[[], None] | None:
    """A preexec_fn asking Linux to send the child SIGTERM when this process dies (None elsewhere)."""
    if not sys.platform.startswith("linux"):
        return None
    try:
        prctl = ctypes.CDLL(None, use_errno=True).prctl
    except (OSError, AttributeError):
        return None
    return lambda: prctl(_PR_SET_PDEATHSIG, signal.SIGTERM)


class NodeProcess:
    """One child process running a node executable, its output going to log_path."""

    def __init__(self, name: str, popen: subprocess.Popen, log_path: Path) -> None:
        self.name = name
        self.popen = popen
        self.log_path = log_path

    @property
    def running(self) -> bool:
        """True while the process has not exited."""
        return self.popen.poll() is None

    def log_tail(self, lines: int = 15) -> str:
        """The last lines of its output."""
        try:
            text = self.log_path.read_text(errors="replace")
        except OSError:
            return ""
        return "\n".join(text.splitlines()[-lines:])

    def failure(self) -> str:
        """One line saying how it ended: its own error line (logged [ERROR]/[FATAL], or 'error:' before ROS
        started), else its last line, and where the log is."""
        lines = [line.strip() for line in self.log_tail(50).splitlines() if line.strip()]
        errors = [line for line in lines if line.startswith(("error:", "[ERROR]", "[FATAL]"))]
        detail = errors[-1] if errors else (lines[-1] if lines else "no output")
        return f"{self.name} exited with status {self.popen.returncode}: {detail} (log: {self.log_path})"


class NodeProcesses:
    """Node executables started as child processes, all stopped when the `with` block ends."""

    def __init__(self, log_dir: Path, domain_id: int) -> None:
        self.log_dir = Path(log_dir)
        self.domain_id = domain_id
        self.processes: list[NodeProcess] = []
        self._lock = threading.Lock()

    def start(self, executable: str, parameters: Mapping[str, Any] | None = None,
              params_files: Iterable[Path] = (), namespace: str = "") -> NodeProcess:
        """Start an executable with its parameter files, then `parameters` (which win), in this domain, in
        `namespace` when given (e.g. /stage_3: its topics and services under it).

        Call it from the thread that outlives the child (Linux ties the child's life to that thread).
        """
        self.log_dir.mkdir(parents=True, exist_ok=True)
        command = [str(find_executable(executable)), "--ros-args"]
        if namespace:
            command += ["-r", f"__ns:={namespace}"]
        for path in params_files:
            command += ["--params-file", str(path)]
        stem = f"{namespace.strip('/').replace('/', '_')}_{executable}" if namespace else executable
        if parameters:
            overrides = self.log_dir / f"{stem}.params.yaml"
            overrides.write_text(yaml.safe_dump({"/**": {"ros__parameters": dict(parameters)}}, sort_keys=False))
            command += ["--params-file", str(overrides)]
        log_path = self.log_dir / f"{stem}.log"
        with open(log_path, "wb") as log:
            popen = subprocess.Popen(command, stdin=subprocess.DEVNULL, stdout=log, stderr=subprocess.STDOUT,
                                     env=ros_environment(self.domain_id), preexec_fn=_die_with_parent())
        process = NodeProcess(f"{namespace.rstrip('/')}/{executable}" if namespace else executable, popen, log_path)
        with self._lock:
            self.processes.append(process)
        return process

    def forget(self, process: NodeProcess) -> None:
        """Stop tracking a child that has exited (stop_all no longer waits for it)."""
        with self._lock:
            self.processes.remove(process)

    def check_running(self) -> None:
        """InputError naming the first child that has exited, with its error line."""
        for process in self.processes:
            if not process.running:
                raise InputError(process.failure())

    def stop_all(self, timeout_s: float = STOP_TIMEOUT_S) -> dict[str, int]:
        """SIGTERM every child, wait up to timeout_s for all, SIGKILL the rest; their exit statuses."""
        with self._lock:
            processes, self.processes = self.processes, []
        for process in processes:
            if process.running:
                process.popen.terminate()
        deadline = time.monotonic() + timeout_s
        for process in processes:
            try:
                process.popen.wait(max(deadline - time.monotonic(), 0.0))
            except subprocess.TimeoutExpired:
                process.popen.kill()
                process.popen.wait()
        return {process.name: process.popen.returncode for process in processes}

    def __enter__(self) -> NodeProcesses:
        return self

    def __exit__(self, kind: type[BaseException] | None, error: BaseException | None,
                 traceback: TracebackType | None) -> None:
        self.stop_all()


def wait_for(predicate: Callable[[], bool], timeout_s: float, what: str,
             check: Callable[[], None] | None = None, poll_s: float = 0.01) -> None:
    """Poll until predicate() is true; InputError after timeout_s [wall s]; check() may raise meanwhile."""
    deadline = time.monotonic() + timeout_s
    while not predicate():
        if check is not None:
            check()
        if time.monotonic() > deadline:
            raise InputError(f"timed out after {timeout_s:g} s waiting for {what}")
        time.sleep(poll_s)


_frozen_clients = 0  # RosClients open in this process: the objects held before the first stay frozen until the last closes
_frozen_lock = threading.Lock()


def _freeze_long_lived() -> None:
    """Keep the objects this process holds now out of the garbage collector's full collections (gc.freeze), once
    for all the RosClients open at a time."""
    global _frozen_clients
    with _frozen_lock:
        if _frozen_clients == 0:
            gc.collect()
            gc.freeze()
        _frozen_clients += 1


def _unfreeze_long_lived() -> None:
    """Undo _freeze_long_lived when the last RosClient closes (gc.unfreeze)."""
    global _frozen_clients
    with _frozen_lock:
        _frozen_clients -= 1
        if _frozen_clients == 0:
            gc.unfreeze()


class RosClient:
    """A node of this process in a private rclpy context, spun by a background executor.

    executor_kind: as the nodes' (`_common.EXECUTORS`); "events" costs a probe that receives many messages a
    second a third to a half of the CPU.

    While a client is open, the objects the process held when it opened (numpy, scipy, matplotlib, rclpy: some
    200,000) are left out of the garbage collector's full collections (gc.freeze; gc.unfreeze when the last
    client closes): each such collection paused the demo's process 0.27-0.68 s beside the three nodes, in
    which it published no setpoint, and the stage held the last one for 12-30 s of simulated time at 40x.
    """

    def __init__(self, domain_id: int, name: str = "sma_client", use_sim_time: bool = False,
                 executor_kind: str = "single") -> None:
        import rclpy
        from rclpy.context import Context
        from rclpy.node import Node
        from rclpy.parameter import Parameter
        from rclpy.task import Future

        from sma_stage.nodes._common import make_executor

        self.context = Context()
        rclpy.init(context=self.context, domain_id=domain_id)
        self.node = Node(name, context=self.context,
                         parameter_overrides=[Parameter("use_sim_time", value=use_sim_time)])
        self.executor_kind = executor_kind
        self.executor = make_executor(executor_kind, self.context)
        self.executor.add_node(self.node)
        self._clients: dict[tuple[object, str], Any] = {}
        self._stopped = Future()
        self._thread = threading.Thread(target=self._spin, name="ros-client", daemon=True)
        self._thread.start()
        _freeze_long_lived()

    def _spin(self) -> None:
        from sma_stage.nodes._common import spin_while

        spin_while(self.executor, self._stopped, self.context)

    def now_s(self) -> float:
        """The node clock [s] (simulated time with use_sim_time; 0 before the first /clock)."""
        return self.node.get_clock().now().nanoseconds * 1e-9

    def _client(self, service_type: object, name: str) -> Any:
        key = (service_type, name)
        if key not in self._clients:
            self._clients[key] = self.node.create_client(service_type, name)
        return self._clients[key]

    def wait_for_services(self, names: Iterable[str], timeout_s: float,
                          check: Callable[[], None] | None = None) -> None:
        """Wait until every Trigger service in names is offered (check() may raise meanwhile)."""
        from std_srvs.srv import Trigger

        for name in names:
            client = self._client(Trigger, name)
            wait_for(client.service_is_ready, timeout_s, f"service {name}", check, poll_s=0.05)

    def call(self, service_type: object, name: str, request: object, timeout_s: float) -> Any:
        """Call a service and return its response; InputError when nobody answers within timeout_s."""
        client = self._client(service_type, name)
        if not client.wait_for_service(timeout_sec=timeout_s):
            raise InputError(f"service {name} is not available")
        future = client.call_async(request)
        wait_for(future.done, timeout_s, f"the answer of {name}")
        if future.result() is None:
            raise InputError(f"service {name} failed: {future.exception()}")
        return future.result()

    def trigger(self, name: str, timeout_s: float = 10.0) -> tuple[bool, str]:
        """Call a std_srvs/Trigger service: (success, message)."""
        from std_srvs.srv import Trigger

        response = self.call(Trigger, name, Trigger.Request(), timeout_s)
        return bool(response.success), str(response.message)

    def trigger_async(self, name: str) -> Any:
        """Send a std_srvs/Trigger request without waiting for the answer; its rclpy Future."""
        from std_srvs.srv import Trigger

        return self._client(Trigger, name).call_async(Trigger.Request())

    def set_bool(self, name: str, value: bool, timeout_s: float = 10.0) -> tuple[bool, str]:
        """Call a std_srvs/SetBool service: (success, message)."""
        from std_srvs.srv import SetBool

        response = self.call(SetBool, name, SetBool.Request(data=value), timeout_s)
        return bool(response.success), str(response.message)

    def lifecycle(self, node_name: str, transition: str | None = None, timeout_s: float = 10.0) -> str:
        """The lifecycle state of a managed node (e.g. 'inactive'), after the transition given by its label
        ('configure', 'activate', 'deactivate', 'cleanup', 'shutdown'); InputError when the node refuses it."""
        from lifecycle_msgs.srv import ChangeState, GetState

        if transition is not None:
            request = ChangeState.Request()
            request.transition.label = transition
            if not self.call(ChangeState, f"{node_name}/change_state", request, timeout_s).success:
                raise InputError(f"{node_name} refused the lifecycle transition {transition!r}")
        return str(self.call(GetState, f"{node_name}/get_state", GetState.Request(), timeout_s).current_state.label)

    def latest(self, message_type: object, topic: str, qos: object, timeout_s: float = 5.0) -> Any:
        """The latest message on a transient-local topic (e.g. identification/report), waited for up to
        timeout_s; TimeoutError when none came."""
        received: list[Any] = []
        subscription = self.node.create_subscription(message_type, topic, received.append, qos)
        try:
            deadline = time.monotonic() + timeout_s
            while not received:
                if time.monotonic() > deadline:
                    raise TimeoutError(f"no message on {topic} within {timeout_s:g} s")
                time.sleep(0.02)
            return received[-1]
        finally:
            self.node.destroy_subscription(subscription)

    def set_parameters(self, node_name: str, values: Mapping[str, Any], timeout_s: float = 5.0) -> None:
        """Set parameters of another node atomically; InputError with its reason when refused."""
        from rcl_interfaces.srv import SetParametersAtomically
        from rclpy.parameter import Parameter

        request = SetParametersAtomically.Request(
            parameters=[Parameter(name, value=value).to_parameter_msg() for name, value in values.items()])
        result = self.call(SetParametersAtomically, f"{node_name}/set_parameters_atomically", request,
                           timeout_s).result
        if not result.successful:
            raise InputError(f"{node_name} refused the parameters: {result.reason}")

    def get_parameters(self, node_name: str, names: Iterable[str], timeout_s: float = 5.0) -> dict[str, Any]:
        """Values of parameters of another node."""
        from rcl_interfaces.srv import GetParameters
        from rclpy.parameter import parameter_value_to_python

        names = list(names)
        response = self.call(GetParameters, f"{node_name}/get_parameters", GetParameters.Request(names=names),
                             timeout_s)
        return {name: parameter_value_to_python(value) for name, value in zip(names, response.values, strict=True)}

    def close(self) -> None:
        """Stop spinning, then stop the executor, destroy the node and shut the context down."""
        try:
            self._stopped.set_result(None)
            self._thread.join(timeout=2.0)
            self.executor.shutdown(timeout_sec=2.0)
            self.node.destroy_node()
            self.context.try_shutdown()
        finally:
            _unfreeze_long_lived()

    def __enter__(self) -> RosClient:
        return self

    def __exit__(self, kind: type[BaseException] | None, error: BaseException | None,
                 traceback: TracebackType | None) -> None:
        self.close()
