"""CalibratorNode under rclpy: runs under ``colcon test`` on ROS 2 Jazzy, skipped without it.

One rclpy context for the module (init / try_shutdown once, as tf2_ros_py's
test_listener_and_broadcaster.py does). The node and a helper node spin on a
MultiThreadedExecutor in a background thread, as ``main`` spins the node; the test thread
publishes, calls services and waits on conditions with a timeout.
"""
from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

rclpy = pytest.importorskip('rclpy')
tf2_ros = pytest.importorskip('tf2_ros')
pytest.importorskip('sensor_msgs.msg')
pytest.importorskip('nav_msgs.msg')
pytest.importorskip('geometry_msgs.msg')
pytest.importorskip('diagnostic_msgs.msg')
pytest.importorskip('std_srvs.srv')
pytest.importorskip('tf2_msgs.msg')

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus  # noqa: E402
from geometry_msgs.msg import TransformStamped  # noqa: E402
from nav_msgs.msg import Odometry  # noqa: E402
from rclpy.executors import MultiThreadedExecutor, SingleThreadedExecutor  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy  # noqa: E402
from rclpy.time import Time  # noqa: E402
from rosbags.highlevel import AnyReader  # noqa: E402
from sensor_msgs.msg import NavSatFix, PointCloud2  # noqa: E402
from std_srvs.srv import Trigger  # noqa: E402
from tf2_msgs.msg import TFMessage  # noqa: E402

from radar_calib_ros.config import read_params_file  # noqa: E402
from radar_calib_ros.errors import ConfigError  # noqa: E402
from radar_calib_ros.io import messages as msgs  # noqa: E402
from radar_calib_ros.node import LATCHED_QOS, CalibratorNode, wait_for_callbacks  # noqa: E402
from radar_calib_ros.result import load_result  # noqa: E402

#: The short simulated drive the node calibrates on (the same one test_live uses).
SIM_SCENARIO = 'baseline'
SIM_SEED = 3
SIM_DURATION_S = 120.0
TIMEOUT_S = 600.0  # the pipeline on a few minutes of data, on a slow CI machine

_ROS_TYPES = {msgs.POINTCLOUD2: ('radar_topic', PointCloud2),
              msgs.NAVSATFIX: ('navsat_topic', NavSatFix),
              msgs.ODOMETRY: ('odom_topic', Odometry)}


@pytest.fixture(scope='module', autouse=True)
def ros_context() -> Iterator[None]:
    rclpy.init()
    yield
    rclpy.try_shutdown()


@pytest.fixture(scope='module')
def sim_bag(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from radar_calib_ros.sim import simulate

    path = tmp_path_factory.mktemp('sim') / 'drive'
    simulate(path, seed=SIM_SEED, duration_s=SIM_DURATION_S, scenario=SIM_SCENARIO)
    return path


def wait_for(condition: Callable[[], bool], timeout_s: float = 20.0) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if condition():
            return True
        time.sleep(0.02)
    return condition()


class Harness:
    """The node and a helper node (publishers, clients, late subscribers) spinning."""

    def __init__(self, tmp_path: Path, params_file: Path | None = None,
                 **params: Any) -> None:
        values: dict[str, Any] = read_params_file(params_file) if params_file else {}
        values.update({'output.path': str(tmp_path / 'result.yaml'),
                       'output.recording_dir': str(tmp_path / 'recordings'),
                       # reliable and deep: the test publishes faster than a radar
                       'qos.reliable': True, 'qos.depth': 10000})
        values.update(params)
        self.node = CalibratorNode(parameter_overrides=[Parameter(name, value=value)
                                                        for name, value in values.items()])
        self.helper = rclpy.create_node('calibrator_test_helper')
        self.executor = MultiThreadedExecutor(num_threads=4)
        self.executor.add_node(self.node)
        self.executor.add_node(self.helper)
        self.thread = threading.Thread(target=self.executor.spin, daemon=True)
        self.thread.start()

    def close(self) -> None:
        self.executor.shutdown()
        self.thread.join(10.0)
        self.node.shutdown()
        self.helper.destroy_node()

    def call(self, service: str, timeout_s: float = TIMEOUT_S) -> Any:
        client = self.helper.create_client(Trigger, f'/calibrator/{service}')
        assert client.wait_for_service(timeout_sec=10.0)
        future = client.call_async(Trigger.Request())
        assert wait_for(future.done, timeout_s), f'{service} did not answer'
        self.helper.destroy_client(client)
        return future.result()

    def latest(self, msg_type: Any, topic: str, qos: Any = LATCHED_QOS,
               timeout_s: float = 10.0) -> Any:
        """First message a NEW subscriber receives (latched topics only)."""
        received: list[Any] = []
        subscription = self.helper.create_subscription(msg_type, topic, received.append, qos)
        try:
            wait_for(lambda: bool(received), timeout_s)
        finally:
            self.helper.destroy_subscription(subscription)
        return received[0] if received else None

    def play(self, bag: Path) -> int:
        """Publish the bag's messages (raw CDR) on the node's topics, with flow control."""
        qos = QoSProfile(depth=10000, history=HistoryPolicy.KEEP_LAST,
                         reliability=ReliabilityPolicy.RELIABLE)
        config = self.node.live.config
        publishers: dict[str, Any] = {}
        sent = 0
        with AnyReader([bag]) as reader:
            connections = [c for c in reader.connections if c.msgtype in _ROS_TYPES]
            for connection in connections:
                topic_param, ros_type = _ROS_TYPES[connection.msgtype]
                publishers[connection.topic] = self.helper.create_publisher(
                    ros_type, getattr(config, topic_param), qos)
            assert wait_for(lambda: all(p.get_subscription_count() > 0
                                        for p in publishers.values()))
            for connection, _, rawdata in reader.messages(connections=connections):
                publishers[connection.topic].publish(bytes(rawdata))
                sent += 1
                if sent % 500 == 0:
                    assert wait_for(lambda: self.received() >= sent - 200, 60.0)
        assert wait_for(lambda: self.received() >= sent, 60.0)
        return sent

    def received(self) -> int:
        counters = self.node.live.counters
        return counters['received.radar'] + counters['received.navsat'] + \
            counters['received.odom']


def test_calibrate_publish_latched_and_republish_after_restart(tmp_path: Path,
                                                               sim_bag: Path) -> None:
    harness = Harness(tmp_path, sim_bag / 'params.yaml')
    try:
        sent = harness.play(sim_bag)
        assert harness.received() == sent
        counters = harness.node.live.counters
        assert not [k for k in counters if k.startswith('rejected.radar.')
                    or k.endswith('internal_error')]

        response = harness.call('calibrate')
        assert response.success, response.message
        assert response.message.startswith('calibrated radar in utm')

        # subscribers created only now still get the latched outputs
        calibration = harness.latest(TransformStamped, '/calibrator/calibration')
        assert calibration is not None
        assert (calibration.header.frame_id, calibration.child_frame_id) == ('utm', 'radar')
        saved = load_result(tmp_path / 'result.yaml')
        t = calibration.transform.translation
        assert [t.x, t.y, t.z] == pytest.approx(saved['translation'], abs=1e-9)
        q = calibration.transform.rotation
        assert [q.x, q.y, q.z, q.w] == pytest.approx(saved['quaternion_xyzw'], abs=1e-9)

        buffer = tf2_ros.Buffer()
        listener = tf2_ros.TransformListener(buffer, harness.helper)
        try:
            assert wait_for(lambda: buffer.can_transform('utm', 'radar', Time()))
            looked_up = buffer.lookup_transform('utm', 'radar', Time())
            assert looked_up.transform.translation.x == pytest.approx(t.x, abs=1e-9)
            assert looked_up.transform.rotation.w == pytest.approx(q.w, abs=1e-12)
        finally:
            harness.helper.destroy_subscription(listener.tf_sub)
            harness.helper.destroy_subscription(listener.tf_static_sub)

        diagnostics = harness.latest(DiagnosticArray, '/diagnostics')
        assert diagnostics is not None
        names = {status.name: status for status in diagnostics.status}
        status = names['/calibrator: calibration']
        assert status.level in (DiagnosticStatus.OK, DiagnosticStatus.WARN)
        assert 'quality.inlier_ratio' in {value.key for value in status.values}

        saved_bag = harness.call('save_recording')
        assert saved_bag.success, saved_bag.message
        assert harness.call('reset').success
        assert harness.node.live.buffer_stats()['radar_frames'] == 0
    finally:
        harness.close()

    restarted = Harness(tmp_path, sim_bag / 'params.yaml')
    try:
        again = restarted.latest(TransformStamped, '/calibrator/calibration')
        assert again is not None
        assert again.transform.translation.x == pytest.approx(t.x, abs=1e-9)
        assert again.transform.rotation.z == pytest.approx(q.z, abs=1e-12)
        static = restarted.latest(TFMessage, '/tf_static')
        assert static is not None and [s.child_frame_id for s in static.transforms] == ['radar']
        # an empty buffer cannot calibrate: the reason, and the old calibration stays
        failed = restarted.call('calibrate')
        assert not failed.success and 'no radar frame' in failed.message
        assert load_result(tmp_path / 'result.yaml')['translation'] == saved['translation']
    finally:
        restarted.close()


def test_a_second_calibrate_call_is_refused_while_one_runs(tmp_path: Path) -> None:
    harness = Harness(tmp_path)
    gate, started = threading.Event(), threading.Event()

    def slow_run(recording: Any, config: Any, progress: Any = None) -> Any:
        started.set()
        gate.wait(30.0)
        raise ConfigError('stopped by the test')

    harness.node.live._run = slow_run  # noqa: SLF001 - no pipeline needed here
    _feed_small_buffer(harness)
    try:
        client = harness.helper.create_client(Trigger, '/calibrator/calibrate')
        assert client.wait_for_service(timeout_sec=10.0)
        first = client.call_async(Trigger.Request())
        assert started.wait(30.0)
        second = harness.call('calibrate', timeout_s=30.0)
        assert not second.success and 'already running' in second.message
        # subscriptions and other services keep working meanwhile
        assert harness.call('reset', timeout_s=30.0).success
        gate.set()
        assert wait_for(first.done, 30.0)
        assert not first.result().success
    finally:
        gate.set()
        harness.close()


def _feed_small_buffer(harness: Harness) -> None:
    """Radar frames and a few fixes, handed to the node's logic directly (rosbags messages;
    the decoders read rclpy ones the same way): a buffer that builds into a Recording."""
    store = msgs.get_typestore()
    t0 = 1_720_000_000 * 10**9
    for i in range(10):
        stamp = t0 + i * 100_000_000
        harness.node.live.on_radar(msgs.encode_pointcloud(
            store, stamp, 'radar', np.full((2, 3), 10.0), np.ones(2)))
        harness.node.live.on_navsat(msgs.encode_navsatfix(
            store, stamp, 'gnss', 48.0 + 1e-6 * i, 11.0, 500.0))


def test_shutdown_during_a_calibration_answers_the_caller_first(tmp_path: Path) -> None:
    """main's Ctrl-C path: cancel, stop the executor, wait for the callbacks, destroy."""
    harness = Harness(tmp_path)
    started = threading.Event()

    def stage_loop(recording: Any, config: Any, progress: Any = None) -> Any:
        started.set()
        for _ in range(1000):  # a long calibration that checks for cancellation per stage
            progress('stage', 0.5)
            time.sleep(0.01)
        raise AssertionError('the calibration was not cancelled')

    harness.node.live._run = stage_loop  # noqa: SLF001 - no pipeline needed here
    _feed_small_buffer(harness)
    try:
        client = harness.helper.create_client(Trigger, '/calibrator/calibrate')
        assert client.wait_for_service(timeout_sec=10.0)
        answer = client.call_async(Trigger.Request())
        assert started.wait(30.0)
        harness.node.live.cancel()
        harness.executor.shutdown()
        # the executor's threads keep running the callback; the helper node needs a spinner
        # of its own to receive the answer
        spinner = SingleThreadedExecutor()
        spinner.add_node(harness.helper)
        thread = threading.Thread(target=spinner.spin, daemon=True)
        thread.start()
        try:
            assert wait_for_callbacks(harness.node, harness.executor, timeout_s=10.0)
            assert not harness.node.live.calibrating
            assert wait_for(answer.done, 10.0)
            assert not answer.result().success
            assert 'shutting down' in answer.result().message
        finally:
            spinner.shutdown()
            thread.join(10.0)
    finally:
        harness.close()


@pytest.mark.parametrize('name, value', [('vehicle.length', 100.0),
                                         ('buffer.max_duration', 600),
                                         ('ground.targets', 'trees'),
                                         ('vehicle.lenght', 4.5)])
def test_wrong_parameter_overrides_make_construction_raise(tmp_path: Path, name: str,
                                                           value: Any) -> None:
    with pytest.raises(ConfigError, match=name.replace('.', r'\.')):
        CalibratorNode(parameter_overrides=[
            Parameter('output.path', value=str(tmp_path / 'result.yaml')),
            Parameter(name, value=value)])


def test_parameter_set_is_validated_and_applied(tmp_path: Path) -> None:
    node = CalibratorNode(parameter_overrides=[
        Parameter('output.path', value=str(tmp_path / 'result.yaml'))])
    try:
        refused = node.set_parameters([Parameter('vehicle.length', value=100.0),
                                       Parameter('ground.targets', value='trees'),
                                       Parameter('radar_topic', value='other/points')])
        assert [r.successful for r in refused] == [False, False, False]
        assert 'ground.targets' in refused[1].reason
        assert node.live.config.vehicle.length == pytest.approx(4.9)
        accepted = node.set_parameters([Parameter('buffer.max_duration', value=600.0)])
        assert accepted[0].successful
        assert node.live.config.buffer.max_duration == 600.0
        descriptor = node.describe_parameter('vehicle.length')
        assert descriptor.floating_point_range[0].to_value == pytest.approx(25.0)
        assert node.describe_parameter('radar_topic').read_only
    finally:
        node.shutdown()


def test_the_pipelines_warnings_go_to_the_nodes_log_while_it_lives(tmp_path: Path) -> None:
    import logging

    from radar_calib_ros.live import LogForwarder

    def forwarders() -> int:
        return sum(isinstance(h, LogForwarder)
                   for h in logging.getLogger('radar_calib_ros').handlers)

    before = forwarders()
    node = CalibratorNode(parameter_overrides=[
        Parameter('output.path', value=str(tmp_path / 'result.yaml'))])
    try:
        assert forwarders() == before + 1
        # through rclpy's logger: no error for a warning from a stage
        logging.getLogger('radar_calib_ros.pipeline').warning('a stage warns')
    finally:
        node.shutdown()
    assert forwarders() == before


def test_result_file_loads_as_parameters_of_another_node(tmp_path: Path) -> None:
    """result.yaml is a parameters file other nodes take (CONTRACT.md): a node that declares
    its parameters from it starts, with empty advice too (an empty list has no type)."""
    from radar_calib_ros.io.geo import LocalFrame
    from radar_calib_ros.result import calibration_dict, write_result_yaml
    from radar_calib_ros.types import Extrinsics

    cal = calibration_dict(Extrinsics(np.eye(3), np.array([1.0, 2.0, 480.0])),
                           LocalFrame.at(48.4, 9.99),
                           quality={'inlier_ratio': 0.7, 'advice': [],
                                    'sigma': {'translation_m': 0.05}})
    path = tmp_path / 'result.yaml'
    write_result_yaml(path, cal)
    context = rclpy.Context()
    rclpy.init(args=['--ros-args', '--params-file', str(path)], context=context)
    try:
        node = rclpy.create_node('result_reader', context=context,
                                 automatically_declare_parameters_from_overrides=True)
        try:
            translation = node.get_parameter('calibration.translation').value
            assert list(translation) == pytest.approx(cal['translation'])
            assert node.get_parameter('calibration.quality.sigma.translation_m').value == 0.05
        finally:
            node.destroy_node()
    finally:
        rclpy.try_shutdown(context=context)
