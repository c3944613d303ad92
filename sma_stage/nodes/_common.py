"""What the three nodes share: parameter declaration with descriptors, QoS profiles, and a main()
that turns a bad start-up parameter into a one-line error and, on Ctrl-C/SIGTERM, stops spinning, closes the
nodes and shuts down quietly."""

from __future__ import annotations

import contextlib
import faulthandler
import gc
import math
import re
import signal
import sys
import threading
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass, fields, make_dataclass
from typing import Self

import rclpy
from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor, ParameterType
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.clock import Clock, ClockType
from rclpy.context import Context
from rclpy.exceptions import ParameterException
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import (
    DurabilityPolicy,
    HistoryPolicy,
    QoSProfile,
    ReliabilityPolicy,
    qos_profile_sensor_data,
)
from rclpy.signals import SignalHandlerOptions
from rclpy.task import Future

from sma_stage.errors import InputError
from sma_stage.identify.cancel import cancellable
from sma_stage.nodes._rclpy_internals import RCLError, parameter_overrides

# Commands: reliable, depth 10. Stage state: published reliable (a best-effort subscriber is compatible
# with it), subscribed best effort (compatible with any publisher: the simulator, a hardware bridge, a
# bag replay). Reports: transient local so a late subscriber still gets the last one.
COMMAND_QOS = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE, history=HistoryPolicy.KEEP_LAST)
STATE_PUBLISH_QOS = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE, history=HistoryPolicy.KEEP_LAST)
STATE_SUBSCRIBE_QOS = qos_profile_sensor_data
# The identification node records every message: the same policies with a deep queue against bursts.
RECORD_COMMAND_QOS = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE, history=HistoryPolicy.KEEP_LAST)
RECORD_STATE_QOS = QoSProfile(depth=1000, reliability=ReliabilityPolicy.BEST_EFFORT, history=HistoryPolicy.KEEP_LAST)
REPORT_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                        durability=DurabilityPolicy.TRANSIENT_LOCAL, history=HistoryPolicy.KEEP_LAST)

JOINT_NAME = "stage_x"


@dataclass(frozen=True)
class Param:
    """One node parameter: default value, description, range (numbers) and whether it is read-only."""

    name: str
    default: float | int | bool | str | list[str]
    description: str
    low: float | None = None
    high: float | None = None
    read_only: bool = False

    def descriptor(self) -> ParameterDescriptor:
        """The ParameterDescriptor rclpy enforces on every set."""
        descriptor = ParameterDescriptor(name=self.name, description=self.description, read_only=self.read_only)
        descriptor.type = _parameter_type(self.default)
        if self.low is not None and isinstance(self.default, float):
            descriptor.floating_point_range = [FloatingPointRange(from_value=float(self.low),
                                                                  to_value=float(self.high), step=0.0)]
        elif self.low is not None and isinstance(self.default, int) and not isinstance(self.default, bool):
            descriptor.integer_range = [IntegerRange(from_value=int(self.low), to_value=int(self.high), step=0)]
        return descriptor


def _parameter_type(value: object) -> int:
    if isinstance(value, bool):
        return ParameterType.PARAMETER_BOOL
    if isinstance(value, int):
        return ParameterType.PARAMETER_INTEGER
    if isinstance(value, float):
        return ParameterType.PARAMETER_DOUBLE
    if isinstance(value, list):
        return ParameterType.PARAMETER_STRING_ARRAY
    return ParameterType.PARAMETER_STRING


def declare_all(node: Node, params: Sequence[Param]) -> dict[str, object]:
    """Declare the parameters (values from overrides or params files); InputError naming the first bad one.
    An integer given for a double parameter (`-p time_scale:=50`, `ros2 param set ... max_current 5`) is taken
    as that double, then range-checked like any other value."""
    doubles = {param.name for param in params if _parameter_type(param.default) == ParameterType.PARAMETER_DOUBLE}
    overrides = parameter_overrides(node)
    for name in doubles & set(overrides):
        overrides[name] = _as_double(overrides[name])
    node.add_pre_set_parameters_callback(
        lambda changes: [_as_double(change) if change.name in doubles else change for change in changes])
    for param in params:
        try:
            node.declare_parameter(param.name, param.default, param.descriptor())
        except ParameterException as error:
            raise InputError(f"parameter '{param.name}' refused: {_reason(error)}") from None
    return {param.name: node.get_parameter(param.name).value for param in params}


class Settings:
    """Base of a node's settings (see settings_type): its parameters' values, each cast once to its declared type
    (string arrays as tuples), read as attributes; frozen, so `changed` gives a new one."""

    @classmethod
    def of(cls, values: Mapping[str, object]) -> Self:
        """The settings from parameter values by name (declare_all's, or a parameter event's)."""
        return cls(**{item.name: item.type(values[item.name]) for item in fields(cls)})

    def changed(self, changes: Mapping[str, object]) -> Self:
        """These settings with some values changed (by parameter name)."""
        return self.of({**asdict(self), **changes})


def settings_type(name: str, params: Sequence[Param]) -> type[Settings]:
    """A frozen dataclass of Settings with one field per parameter, named as it and typed as its default."""
    def value_type(default: object) -> type:
        return tuple if isinstance(default, list) else type(default)

    return make_dataclass(name, [(param.name, value_type(param.default)) for param in params], bases=(Settings,),
                          frozen=True)


def _as_double(parameter: Parameter) -> Parameter:
    """An INTEGER parameter as the DOUBLE of the same value; any other unchanged."""
    if parameter.type_ != Parameter.Type.INTEGER:
        return parameter
    return Parameter(parameter.name, Parameter.Type.DOUBLE, float(parameter.value))


_RCLPY_RANGE = re.compile(r"out of range Min: (\S+), Max: (\S+), value: (\S+): \S+$")


def _reason(error: ParameterException) -> str:
    """rclpy's reason for refusing a parameter, in one line (its range message reworded)."""
    text = " ".join(str(error.args[0] if error.args else error).split())
    text = text.split("Reason: ", 1)[-1]
    found = _RCLPY_RANGE.search(text)
    if found:
        low, high, value = found.groups()
        return f"{value} is outside its range {low} to {high}"
    return text


def quiet_on_shutdown(node: Node, callback: Callable[[], None]) -> Callable[[], None]:
    """A timer callback that ends quietly when Ctrl-C/SIGTERM shut the node's context down under it (a publish
    then raises, or the KeyboardInterrupt lands in the callback's I/O, and the executor logged it as FATAL);
    any other exception goes on."""
    def run() -> None:
        try:
            callback()
        except (Exception, KeyboardInterrupt):
            if node.context.ok():
                raise

    return run


def finite(value: float) -> bool:
    """True for a finite float (not NaN, not +-inf)."""
    return isinstance(value, (int, float)) and math.isfinite(value)


class ThrottledWarnings:
    """A node's warnings, each kind (key) logged at most once every period_s of steady time."""

    def __init__(self, node: Node, period_s: float = 1.0) -> None:
        self._node = node
        self._period_ns = int(period_s * 1e9)
        self._clock = Clock(clock_type=ClockType.STEADY_TIME)
        self._last_ns: dict[str, int] = {}

    def warn(self, key: str, text: str) -> None:
        """Log text unless a warning of this key was logged less than period_s ago."""
        now_ns = self._clock.now().nanoseconds
        last_ns = self._last_ns.get(key)
        if last_ns is None or now_ns - last_ns >= self._period_ns:
            self._last_ns[key] = now_ns
            self._node.get_logger().warning(text)


class _YieldToExecutor:
    """Awaited inside an rclpy coroutine callback: hands the executor one turn."""

    def __await__(self):
        yield


class WorkerService:
    """A service of `owner` whose callback runs in a thread per request, so a long callback (a fit) leaves
    the owner's executor free to record, and a second request is answered (e.g. refused) at once.

    The service is offered under the owner's private name (`~/<name>`) by a hidden helper node in the
    owner's context, spun by a private SingleThreadedExecutor; the callback thread wakes it through a
    guard condition when it ends. rclpy's MultiThreadedExecutor is not used: it stalls timers for up to
    seconds (ros2/rclpy#1223)."""

    def __init__(self, owner: Node, service_type: type, name: str, callback: Callable) -> None:
        self._callback = callback
        self.cancel = threading.Event()  # set by close(): a running callback's fit raises Cancelled
        # Not the process's arguments: `-r __node:=X` (ros2 launch's name, ros2 run's remap) would give it the
        # owner's name, and the graph would hold two nodes of that name.
        self._node = Node(f"_{owner.get_name()}_{name}_worker", namespace=owner.get_namespace(),
                          context=owner.context, start_parameter_services=False, use_global_arguments=False)
        # Reentrant: a request is served while another one's callback runs, and the wake-up gets through.
        concurrent = ReentrantCallbackGroup()
        self._wake = self._node.create_guard_condition(lambda: None, callback_group=concurrent)
        self._node.create_service(service_type, f"{owner.get_fully_qualified_name()}/{name}", self._serve,
                                  callback_group=concurrent)
        self._owner_context = owner.context
        self._executor = SingleThreadedExecutor(context=owner.context)
        self._executor.add_node(self._node)
        self._thread: threading.Thread | None = threading.Thread(target=self._spin, name=f"{name}-service",
                                                                 daemon=True)
        self._calls: list[threading.Thread] = []
        self._wake_lock = threading.Lock()  # a call ending as close() destroys the node must not wake it then
        self._closed = False
        self._thread.start()

    async def _serve(self, request: object, response: object) -> object:
        done = threading.Event()
        outcome: dict[str, object] = {}

        def work() -> None:
            try:
                with cancellable(self.cancel):
                    outcome["response"] = self._callback(request, response)
            except BaseException as error:  # noqa: BLE001 -- raised again in the executor
                outcome["error"] = error
            finally:
                done.set()
                with self._wake_lock:
                    if not self._closed:
                        self._wake.trigger()

        call = threading.Thread(target=work, name=f"{self._node.get_name()}-call", daemon=True)
        self._calls = [*(running for running in self._calls if running.is_alive()), call]
        call.start()
        while not done.is_set():
            await _YieldToExecutor()
        if "error" in outcome:
            if self.cancel.is_set():  # closing: the call was cancelled, the caller gets the default answer
                return response
            raise outcome["error"]
        return outcome["response"]

    def run_in_background(self, work: Callable[[], None]) -> None:
        """Run work in a thread of its own as a call of this service is run (close() cancels and waits for it); an
        error in it is the caller's to catch."""

        def call() -> None:
            with cancellable(self.cancel):
                work()

        thread = threading.Thread(target=call, name=f"{self._node.get_name()}-background", daemon=True)
        self._calls = [*(running for running in self._calls if running.is_alive()), thread]
        thread.start()

    def _spin(self) -> None:
        try:
            self._executor.spin()
        except ExternalShutdownException:
            pass
        except RCLError:
            if self._owner_context.ok():
                raise  # not the shutdown race: rcl refused the wait set for another reason

    def close(self, timeout_s: float = 5.0) -> None:
        """Stop serving: cancel a running callback (sma_stage.identify.cancel) and wait up to timeout_s for it to
        answer, then destroy the helper node; idempotent."""
        if self._thread is None:
            return
        self.cancel.set()
        for call in self._calls:
            call.join(timeout=timeout_s)
        self._executor.shutdown(timeout_sec=timeout_s)
        self._thread.join(timeout=timeout_s)
        self._thread = None
        with self._wake_lock:
            self._closed = True
        self._node.destroy_node()


EXECUTORS = ("events", "single")
SPIN_SLICE_S = 0.1  # the spin loop looks at a stop request (and the context) this often [s]
TEARDOWN_LIMIT_S = 8.0  # a process still there this long after a stop request dumps its threads and exits 1


class StopRequest:
    """SIGINT and SIGTERM for a node process, in place of rclpy's handlers (which shut the context down from
    another thread at once, under running callbacks: publishes then fail, the last log lines cannot reach
    /rosout, and a KeyboardInterrupt can land inside a callback).

    While the nodes are built (`starting`), a signal raises KeyboardInterrupt, so a long start (a first,
    uncached compile of the simulator, a connection) ends at once. While they spin, it only asks the spin loop
    to end: no callback is interrupted, and the nodes then close with their context still valid. While they
    close, further signals are ignored: a close is bounded by the instruments' timeouts and by
    TEARDOWN_LIMIT_S."""

    def __init__(self) -> None:
        self.phase = "starting"
        self.signal_name: str | None = None
        self._previous: dict[int, object] = {}
        self.stopped = Future()  # done once a signal asked the spin loop to end: spin_while's
        self._signalled = threading.Event()

    def install(self) -> None:
        """Handle SIGINT and SIGTERM in this process (main thread only)."""
        for number in (signal.SIGINT, signal.SIGTERM):
            self._previous[number] = signal.signal(number, self._on_signal)
        threading.Thread(target=self._complete_on_signal, name="stop-request", daemon=True).start()

    def restore(self) -> None:
        """Give SIGINT and SIGTERM back their previous handlers."""
        for number, handler in self._previous.items():
            signal.signal(number, handler)
        self._previous.clear()
        self._signalled.set()

    def _on_signal(self, number: int, frame: object) -> None:
        self.signal_name = self.signal_name or signal.Signals(number).name
        if self.phase == "starting":
            raise KeyboardInterrupt
        if self.phase == "spinning":
            self.phase = "stopping"  # before the Event: a second signal inside set() must not take its lock again
            self._signalled.set()

    def _complete_on_signal(self) -> None:
        """Complete `stopped` from a thread of its own: its done callbacks (the executor's stop) take locks that
        the main thread, which runs signal handlers, may hold when the signal lands."""
        self._signalled.wait()
        self.stopped.set_result(self.signal_name)


class StartedNodes:
    """The nodes whose handles exist in this process's run_nodes, noted by each node as soon as it has one
    (`note_started`): a stop that interrupts a constructor leaves a node that was never returned, and a node
    left undestroyed when the context shuts down aborts the process at exit ("terminate called without an
    active exception")."""

    nodes: list[Node] | None = None


def note_started(node: Node) -> None:
    """Called by each node right after Node.__init__: run_nodes then destroys it however its start ends."""
    if StartedNodes.nodes is not None:
        StartedNodes.nodes.append(node)


def run_node(make_node: Callable[..., Node], args: Sequence[str] | None = None, executor_kind: str = "events") -> int:
    """Init rclpy, build the node, spin until Ctrl-C/SIGTERM, close and shut down; 2 and one line for bad
    parameters.

    executor_kind "events": rclpy's EventsExecutor (C++; a third to a half of the SingleThreadedExecutor's
    CPU per message, bench/README.md), "single": the SingleThreadedExecutor.
    """
    return run_nodes([make_node], args, executor_kind)


def run_nodes(makers: Sequence[Callable[..., Node]], args: Sequence[str] | None = None,
              executor_kind: str = "events") -> int:
    """run_node for several nodes in one process and one executor (built in order, closed and destroyed in
    reverse), as a C++ component container holds them; each takes its own section of a parameter file by its
    name. On SIGINT/SIGTERM (StopRequest) the executor stops taking callbacks, then each node's close() runs
    on a valid context, then the nodes are destroyed and the context shut down."""
    try:
        rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    except Exception as error:  # noqa: BLE001 -- rcl reports a bad --ros-args or params file this way
        print(f"error: cannot start ROS: {' '.join(str(error).split())}", file=sys.stderr)
        return 2
    stop = StopRequest()
    stop.install()
    nodes: list[Node] = []
    StartedNodes.nodes = []
    executor = None
    building = makers[0]
    status = 0
    try:
        executor = make_executor(executor_kind)
        for building in makers:
            nodes.append(building())
            executor.add_node(nodes[-1])
        gc.collect()
        gc.freeze()  # what start-up built lives on: the collector's passes stop walking it
        stop.phase = "spinning"
        spin_while(executor, stop.stopped)
    except (InputError, ParameterException) as error:
        name = getattr(building, "NODE_NAME", "sma_stage")
        rclpy.logging.get_logger(name).error(f"cannot start: {' '.join(str(error).split())}")
        status = 2
    except KeyboardInterrupt:
        pass
    finally:
        stop.phase = "closing"
        faulthandler.dump_traceback_later(TEARDOWN_LIMIT_S, exit=True)
        unfinished = [node for node in StartedNodes.nodes if all(node is not built for built in nodes)]
        StartedNodes.nodes = None
        close_all(nodes, executor, unfinished)
        stop.restore()
    return status


def close_all(nodes: Sequence[Node], executor: object | None, unfinished: Sequence[Node] = ()) -> None:
    """Close the nodes (their close(), on a context still valid), stop the executor, destroy the nodes in
    reverse order and shut the context down. `unfinished`: nodes a stop interrupted in their constructor, closed
    as far as they got and destroyed first."""
    for node in unfinished:
        with contextlib.suppress(Exception):  # a half-built node's close() meets attributes not yet set
            getattr(node, "close", lambda: None)()
        node.destroy_node()
    for node in reversed(nodes):
        close = getattr(node, "close", None)
        if close is not None:
            close()
    if executor is not None:
        executor.shutdown(timeout_sec=1.0)
    for node in reversed(nodes):
        node.destroy_node()
    rclpy.try_shutdown()


def make_executor(kind: str, context: Context | None = None) -> object:
    """An executor of the kind named in EXECUTORS, on context (the default context when None)."""
    if kind == "single":
        return SingleThreadedExecutor(context=context)
    if kind == "events":
        from rclpy.experimental import EventsExecutor

        return EventsExecutor(context=context)
    raise InputError(f"executor must be one of {', '.join(EXECUTORS)}, got {kind!r}")


def spin_while(executor: object, stopped: Future, context: Context | None = None) -> None:
    """Spin executor until `stopped` is done or its context (the default context when None) is shut down,
    looking at both every SPIN_SLICE_S.

    The EventsExecutor is spun until `stopped` itself: its timeout is looked at only when its queue runs empty
    (rclpy 7.1's EventsQueue::RunUntil), which a flood of messages can keep from happening for ever; the future's
    completion stops it whatever the queue holds."""
    while not stopped.done() and rclpy.ok(context=context):
        if isinstance(executor, SingleThreadedExecutor):
            executor.spin_once(timeout_sec=SPIN_SLICE_S)
        else:  # EventsExecutor.spin() busy-waits in rclpy 7.1.x; this call does not
            executor.spin_until_future_complete(stopped, timeout_sec=SPIN_SLICE_S)


def exit_with(code: int) -> None:
    """Leave the process with code when it is not 0 (entry points return None on success)."""
    if code:
        sys.exit(code)
