"""``ros2 run radar_calib_ros calibrator``: the ROS 2 node, a thin rclpy adapter.

The only module that imports rclpy. Every decision lives in :mod:`radar_calib_ros.live`
(tested without ROS); this module declares the parameters, wires topics and services to a
:class:`~radar_calib_ros.live.LiveCalibrator` and turns its plain outputs into messages.

Written against ROS 2 Jazzy (rclpy 7.1, ros2/rclpy branch jazzy; tf2_ros_py of
ros2/geometry2 jazzy). See CONTRACT.md for the topics, services and parameters.
"""
from __future__ import annotations

import gc
import signal
import threading
import time
from typing import Any

from builtin_interfaces.msg import Time as TimeMsg
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import TransformStamped
from nav_msgs.msg import Odometry
from rcl_interfaces.msg import (
    FloatingPointRange, IntegerRange, ParameterDescriptor, SetParametersResult)
import rclpy
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup, ReentrantCallbackGroup
from rclpy.exceptions import ParameterException
from rclpy.executors import ExternalShutdownException, MultiThreadedExecutor
import rclpy.logging
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.signals import SignalHandlerOptions
from sensor_msgs.msg import NavSatFix, PointCloud2
from std_srvs.srv import Trigger
from tf2_msgs.msg import TFMessage

from radar_calib_ros.config import CalibConfig, ParameterSpec, QosConfig, parameter_specs
from radar_calib_ros.errors import ConfigError
from radar_calib_ros.live import (
    DiagnosticStatusOutput, LiveCalibrator, LogForwarder, TransformOutput, TriggerOutcome)

__all__ = ['CalibratorNode', 'NODE_NAME', 'main', 'wait_for_callbacks']

NODE_NAME = 'calibrator'

#: Latched outputs (CONTRACT.md): a subscriber that connects later still gets the last one.
LATCHED_QOS = QoSProfile(depth=1, history=HistoryPolicy.KEEP_LAST,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL,
                         reliability=ReliabilityPolicy.RELIABLE)

#: The QoS of tf2_ros.StaticTransformBroadcaster (geometry2 jazzy,
#: tf2_ros_py/tf2_ros/static_transform_broadcaster.py: depth 1, TRANSIENT_LOCAL, KEEP_LAST,
#: reliability left at its RELIABLE default). We publish TFMessage on /tf_static ourselves
#: because that class keeps the first transform per child_frame_id and ignores later ones
#: (ros2/geometry2#704): a recalibration in the same process would never reach tf2.
TF_STATIC_QOS = QoSProfile(depth=1, history=HistoryPolicy.KEEP_LAST,
                           durability=DurabilityPolicy.TRANSIENT_LOCAL,
                           reliability=ReliabilityPolicy.RELIABLE)

#: Worker threads of the executor: subscriptions (one mutually exclusive group), a running
#: calibration, a second ~/calibrate call to refuse, and ~/save_recording.
EXECUTOR_THREADS = 4

#: How long Ctrl-C waits for a cancelled calibration to reach its next stage and answer.
SHUTDOWN_WAIT_S = 10.0

#: Period of the /diagnostics update (diagnostic_updater's default is 1 s as well).
DIAGNOSTICS_PERIOD_S = 1.0

_LEVELS = {'OK': DiagnosticStatus.OK, 'WARN': DiagnosticStatus.WARN,
           'ERROR': DiagnosticStatus.ERROR}


def input_qos(qos: QosConfig) -> QoSProfile:
    """Subscription QoS of the inputs.

    Default: the sensor-data profile (``rclpy.qos.qos_profile_sensor_data``: best effort,
    volatile, keep last), whose depth of 5 is replaced by ``qos.depth`` so that a burst
    while a calibration holds the interpreter is not lost; a best-effort subscriber
    matches reliable and best-effort publishers. ``qos.reliable`` asks for reliable
    delivery instead (it then matches reliable publishers only), the switch
    demo_nodes_py ``topics/talker_qos.py`` (ros2/demos jazzy) makes.
    """
    reliability = ReliabilityPolicy.RELIABLE if qos.reliable else ReliabilityPolicy.BEST_EFFORT
    return QoSProfile(depth=qos.depth, history=HistoryPolicy.KEEP_LAST,
                      reliability=reliability, durability=DurabilityPolicy.VOLATILE)


def parameter_descriptor(spec: ParameterSpec) -> ParameterDescriptor:
    """ROS parameter descriptor of one of our parameters (config.parameter_specs).

    rclpy checks the type and the ranges itself, at declaration (so against a params file
    too) and on every later set (rclpy/node.py ``_apply_descriptor``); ranges include
    their bounds. Choices go into ``additional_constraints`` and are checked by
    ``CalibConfig.from_mapping`` in the set-parameters callback.
    """
    descriptor = ParameterDescriptor(description=spec.doc, read_only=spec.read_only)
    if spec.lo is not None and spec.hi is not None:
        if spec.type is float:
            descriptor.floating_point_range = [FloatingPointRange(
                from_value=float(spec.lo), to_value=float(spec.hi), step=0.0)]
        elif spec.type is int:
            descriptor.integer_range = [IntegerRange(
                from_value=int(spec.lo), to_value=int(spec.hi), step=1)]
    if spec.choices:
        descriptor.additional_constraints = 'one of: ' + ', '.join(map(str, spec.choices))
    return descriptor


class CalibratorNode(Node):
    """The calibrator node.

    Parameters
    ----------
    node_name : str, default='calibrator'
    **kwargs
        Passed to ``rclpy.node.Node`` (``namespace``, ``parameter_overrides``, ``context``,
        ``cli_args``, ...).

    Raises
    ------
    ConfigError
        A parameter (from a params file, the command line or ``parameter_overrides``) has
        the wrong type or is out of range; the message names it.
    """

    def __init__(self, node_name: str = NODE_NAME, **kwargs: Any) -> None:
        super().__init__(node_name, **kwargs)
        self._specs = {spec.name: spec for spec in parameter_specs()}
        try:
            self._config = self._declare_parameters()
        except ConfigError:
            self.destroy_node()
            raise
        self._config_lock = threading.Lock()
        clock = self.get_clock()
        self._live = LiveCalibrator(self._config, log=self._log,
                                    now_ns=lambda: clock.now().nanoseconds,
                                    name=self.get_fully_qualified_name())
        # the stages' own warnings (Python logging) into this node's log, not bare stderr
        self._log_forwarder = LogForwarder(self._log).install()

        self._calibration_pub = self.create_publisher(TransformStamped, '~/calibration',
                                                      LATCHED_QOS)
        self._tf_static_pub = self.create_publisher(TFMessage, '/tf_static', TF_STATIC_QOS)
        self._diagnostics_pub = self.create_publisher(DiagnosticArray, '/diagnostics',
                                                      LATCHED_QOS)

        # Subscriptions, ~/reset and the diagnostics timer share the node's default
        # (mutually exclusive) group: messages are handled one at a time, in order.
        qos = input_qos(self._config.qos)
        self.create_subscription(PointCloud2, self._config.radar_topic, self._live.on_radar,
                                 qos)
        self.create_subscription(NavSatFix, self._config.navsat_topic, self._live.on_navsat,
                                 qos)
        self.create_subscription(Odometry, self._config.odom_topic, self._live.on_odometry,
                                 qos)
        # Reentrant: a second ~/calibrate call must run (and be refused by LiveCalibrator)
        # while the first is still working, not wait in a queue behind it.
        self._calibrate_group = ReentrantCallbackGroup()
        self.create_service(Trigger, '~/calibrate', self._on_calibrate,
                            callback_group=self._calibrate_group)
        self._save_group = MutuallyExclusiveCallbackGroup()
        self.create_service(Trigger, '~/save_recording', self._on_save_recording,
                            callback_group=self._save_group)
        self.create_service(Trigger, '~/reset', self._on_reset)
        self._diagnostics_timer = self.create_timer(DIAGNOSTICS_PERIOD_S,
                                                    self._publish_diagnostics)

        # Registered after declaring: rclpy calls them for declarations too.
        self.add_on_set_parameters_callback(self._validate_parameters)
        self.add_post_set_parameters_callback(self._apply_parameters)

        transform = self._live.load_result_file()
        if transform is not None:
            self._publish_transform(transform)
        self._publish_diagnostics()
        self._log('info', f'listening to {self.resolve_topic_name(self._config.radar_topic)}, '
                  f'{self.resolve_topic_name(self._config.navsat_topic)} and '
                  f'{self.resolve_topic_name(self._config.odom_topic)} '
                  f'({"reliable" if self._config.qos.reliable else "best effort"}); call '
                  f'{self.get_fully_qualified_name()}/calibrate when the vehicle has passed')

    @property
    def live(self) -> LiveCalibrator:
        """The ROS-free logic behind this node."""
        return self._live

    # parameters -------------------------------------------------------------------------
    def _declare_parameters(self) -> CalibConfig:
        values: dict[str, Any] = {}
        for spec in self._specs.values():
            try:
                parameter = self.declare_parameter(spec.name, spec.default,
                                                   parameter_descriptor(spec))
            except ParameterException as err:
                # InvalidParameterValueException (out of range) and
                # InvalidParameterTypeException (e.g. 600 for a double: write 600.0)
                raise ConfigError(f'parameter {spec.name!r}: {err}') from err
            values[spec.name] = parameter.value
        self._check_unknown_overrides()
        return CalibConfig.from_mapping(values)

    def _check_unknown_overrides(self) -> None:
        """A misspelt parameter of ours (``vehicle.lenght``) is an error, as in the offline
        tool; other unknown names (parameters of other nodes under ``/**``) are ignored, as
        ROS does, with a warning.

        rclpy keeps the overrides of params files and ``parameter_overrides`` in
        ``Node._parameter_overrides`` (rclpy/node.py, jazzy) and offers no public getter.
        """
        overrides = getattr(self, '_parameter_overrides', {}) or {}
        unknown = sorted(name for name in overrides
                         if name not in self._specs and not self.has_parameter(name))
        sections = {name.split('.', 1)[0] for name in self._specs}
        ours = [name for name in unknown if name.split('.', 1)[0] in sections]
        if ours:
            raise ConfigError(f'unknown parameter {ours[0]!r}'
                              + (f' (and {len(ours) - 1} more)' if len(ours) > 1 else ''))
        if unknown:
            self._log('warn', f'ignoring parameters this node does not have: {unknown}')

    def _merged(self, parameters: list[Parameter]) -> dict[str, Any] | None:
        """Our current values with the given ones applied; None when none is ours (parameters
        such as use_sim_time belong to rclpy and are not ours to refuse)."""
        ours = {p.name: p.value for p in parameters if p.name in self._specs}
        if not ours:
            return None
        values = self._config.to_flat()
        values.update(ours)
        return values

    def _validate_parameters(self, parameters: list[Parameter]) -> SetParametersResult:
        """on-set-parameters callback: refuse a wrong value with the reason."""
        values = self._merged(parameters)
        if values is not None:
            try:
                CalibConfig.from_mapping(values)
            except ConfigError as err:
                return SetParametersResult(successful=False, reason=str(err))
        return SetParametersResult(successful=True)

    def _apply_parameters(self, parameters: list[Parameter]) -> None:
        """post-set-parameters callback: the next message and calibration use them."""
        values = self._merged(parameters)
        if values is None:
            return
        with self._config_lock:
            self._config = CalibConfig.from_mapping(values)
            self._live.update_config(self._config)
        changed = ', '.join(f'{p.name}={p.value!r}' for p in parameters
                            if p.name in self._specs)
        self._log('info', f'parameters changed: {changed}')

    # services ---------------------------------------------------------------------------
    def _on_calibrate(self, request: Trigger.Request,
                      response: Trigger.Response) -> Trigger.Response:
        outcome = self._live.calibrate()
        if outcome.transform is not None:
            self._publish_transform(outcome.transform)
        self._publish_diagnostics()
        return _answer(response, outcome)

    def _on_reset(self, request: Trigger.Request,
                  response: Trigger.Response) -> Trigger.Response:
        return _answer(response, self._live.reset())

    def _on_save_recording(self, request: Trigger.Request,
                           response: Trigger.Response) -> Trigger.Response:
        return _answer(response, self._live.save_recording())

    # outputs ----------------------------------------------------------------------------
    def _publish_transform(self, transform: TransformOutput) -> None:
        msg = transform_msg(transform)
        self._calibration_pub.publish(msg)
        self._tf_static_pub.publish(TFMessage(transforms=[msg]))

    def _publish_diagnostics(self) -> None:
        array = DiagnosticArray()
        array.header.stamp = self.get_clock().now().to_msg()
        array.status = [status_msg(status) for status in self._live.diagnostics()]
        self._diagnostics_pub.publish(array)

    def _log(self, severity: str, message: str) -> None:
        # One call site per severity: rclpy's logger keys its per-call-site state on the
        # caller's line and raises "Logger severity cannot be changed between calls" if one
        # line logs with two severities (rclpy/impl/rcutils_logger.py, jazzy).
        logger = self.get_logger()
        if severity == 'debug':
            logger.debug(message)
        elif severity == 'info':
            logger.info(message)
        elif severity == 'warn':
            logger.warning(message)
        elif severity == 'error':
            logger.error(message)
        else:
            logger.fatal(message)

    def shutdown(self) -> None:
        """Ask a running calibration to stop at its next stage, then destroy the node."""
        self._live.cancel()
        self.destroy_node()

    def destroy_node(self) -> None:
        forwarder = getattr(self, '_log_forwarder', None)
        if forwarder is not None:
            forwarder.remove()
        super().destroy_node()


def _answer(response: Trigger.Response, outcome: TriggerOutcome) -> Trigger.Response:
    """A Trigger response carrying a service outcome of the live logic."""
    response.success = outcome.success
    response.message = outcome.message
    return response


def transform_msg(transform: TransformOutput) -> TransformStamped:
    """geometry_msgs/TransformStamped of a TransformOutput."""
    msg = TransformStamped()
    sec, nanosec = divmod(int(transform.stamp_ns), 1_000_000_000)
    msg.header.stamp = TimeMsg(sec=sec, nanosec=nanosec)
    msg.header.frame_id = transform.parent_frame
    msg.child_frame_id = transform.child_frame
    t = msg.transform.translation
    t.x, t.y, t.z = transform.translation_m
    r = msg.transform.rotation
    r.x, r.y, r.z, r.w = transform.quaternion_xyzw
    return msg


def status_msg(status: DiagnosticStatusOutput) -> DiagnosticStatus:
    """diagnostic_msgs/DiagnosticStatus of a DiagnosticStatusOutput (the level constants of
    the message are used: ``byte`` fields are ``bytes`` in rclpy)."""
    return DiagnosticStatus(level=_LEVELS[status.level], name=status.name,
                            message=status.message, hardware_id=status.hardware_id,
                            values=[KeyValue(key=k, value=v) for k, v in status.values])


def main(args: list[str] | None = None) -> int:
    """Entry point of ``ros2 run radar_calib_ros calibrator``.

    Exit code 0 on Ctrl-C (SIGINT), SIGTERM or an external shutdown, 2 when a parameter is
    wrong (logged as fatal, naming it). The shutdown follows ros2/demos jazzy
    ``demo_nodes_py`` (catch ``KeyboardInterrupt`` and ``ExternalShutdownException``, then
    ``destroy_node()`` and the idempotent ``rclpy.try_shutdown()``) with one difference:
    rclpy installs no signal handler. Its handler shuts the context down at once, under a
    ~/calibrate callback still running on another thread, whose diagnostics, log and
    answer then fail ("publisher's context is invalid") at exit. Here a signal is a
    ``KeyboardInterrupt`` in the spinning thread (raised when the executor's wait returns:
    within the 1 s diagnostics period); the calibration is cancelled and its callback
    answers on a valid context before the node and the context go.
    """
    rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    signal.signal(signal.SIGTERM, _interrupt)
    try:
        node = CalibratorNode()
    except ConfigError as err:
        rclpy.logging.get_logger(NODE_NAME).fatal(f'cannot start: {err}')
        rclpy.try_shutdown()
        return 2
    # Everything imported so far (rclpy, numpy, scipy, pyproj: ~100,000 objects) lives as
    # long as the process; freezing it keeps Python's full garbage collections, which stop
    # every callback, short (bench/bench_node.py measured ~70 ms per full collection for
    # such a heap). Objects are still freed by reference counting.
    gc.freeze()
    executor = MultiThreadedExecutor(num_threads=EXECUTOR_THREADS)
    executor.add_node(node)
    try:
        executor.spin()
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.live.cancel()
        executor.shutdown()
        wait_for_callbacks(node, executor)
        node.shutdown()
        rclpy.try_shutdown()
    return 0


def _interrupt(signum: int, frame: Any) -> None:
    """SIGTERM handler: stop as on Ctrl-C (Python raises KeyboardInterrupt for SIGINT)."""
    raise KeyboardInterrupt


def wait_for_callbacks(node: CalibratorNode, executor: MultiThreadedExecutor,
                       timeout_s: float = SHUTDOWN_WAIT_S) -> bool:
    """Wait until the callbacks still running on the executor's threads have answered.

    rclpy jazzy's ``Executor.shutdown`` does not wait for them (its wait is skipped once
    ``_is_shutdown`` is set, rclpy 7.1.3 executors.py), and a Ctrl-C during a calibration
    left the ~/calibrate callback running: destroying the node under it made the answer
    fail with "cannot use Destroyable because destruction was requested", printed at exit.
    The calibration was cancelled before, so it stops at its next stage; the thread pool
    (``MultiThreadedExecutor._executor``, no public accessor) is joined only once it has,
    so a stage that overruns ``timeout_s`` cannot hang the exit.

    Returns
    -------
    bool
        True when every callback has finished.
    """
    deadline = time.monotonic() + timeout_s
    while node.live.calibrating and time.monotonic() < deadline:
        time.sleep(0.05)
    if node.live.calibrating:
        node.get_logger().warning(f'a calibration is still running after {timeout_s:.0f} s; '
                                  'exiting without its answer')
        return False
    pool = getattr(executor, '_executor', None)
    if pool is not None:
        # the answers of the callbacks that just returned are sent from these threads
        pool.shutdown(wait=True)
    return True


if __name__ == '__main__':
    raise SystemExit(main())
