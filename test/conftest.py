"""Shared fixtures: an isolated DDS domain on loopback, node processes, rclpy helpers."""

import os
from pathlib import Path
import shutil
import signal
import subprocess
import sys
import time

import pytest

from zeus_ros.ros.graph import use_free_domain

REPO = Path(__file__).resolve().parents[1]
INSTALL_BIN = REPO / 'install' / 'zeus_ros' / 'lib' / 'zeus_ros'
HELPERS = Path(__file__).resolve().parent / 'helpers'

# Discovery stays on this machine, and the suite talks on a domain of its own:
# a lock file per domain id keeps two runs on one machine from hearing each other.
os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
os.environ.setdefault('RMW_IMPLEMENTATION', 'rmw_fastrtps_cpp')
# Held for the session (zeus_ros.ros.graph: the same claim as `make demo`'s).
_DOMAIN = use_free_domain()


class NodeProcess:
    """A node (or any command) in its own process, its output kept in a log file."""

    def __init__(self, argv, log_path: Path, env=None):
        self.argv = [str(a) for a in argv]
        self.log_path = log_path
        self._log = open(log_path, 'w')
        self.proc = subprocess.Popen(
            self.argv, stdout=self._log, stderr=subprocess.STDOUT,
            env=env or os.environ.copy(), start_new_session=True)

    def alive(self) -> bool:
        return self.proc.poll() is None

    def output(self) -> str:
        self._log.flush()
        return self.log_path.read_text()

    def stop(self, timeout: float = 10.0) -> int:
        if self.alive():
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(timeout)
            except subprocess.TimeoutExpired:
                os.killpg(self.proc.pid, signal.SIGKILL)
                self.proc.wait()
        self._log.close()
        return self.proc.returncode


@pytest.fixture
def spawn(tmp_path, request):
    """Start processes that are stopped (SIGINT, then SIGKILL) after the test."""
    started = []
    request.node.spawned = started   # read by pytest_runtest_makereport on a failure

    def _spawn(argv, name='proc', env=None):
        proc = NodeProcess(argv, tmp_path / f'{name}_{len(started)}.log', env)
        started.append(proc)
        return proc

    yield _spawn
    for proc in started:
        proc.stop()


def installed_exe(name: str) -> Path:
    """Path of an executable as `ros2 run zeus_ros <name>` would find it."""
    path = INSTALL_BIN / name
    if not path.exists():
        raise FileNotFoundError(f'{path} is missing: run `make setup` (colcon build) first')
    return path


def helper_script(name: str) -> list:
    return [sys.executable, str(HELPERS / name)]


@pytest.fixture(scope='session')
def rclpy_context():
    import rclpy
    rclpy.init()
    yield
    rclpy.shutdown()


@pytest.fixture
def ros_node(rclpy_context, request):
    from rclpy.executors import SingleThreadedExecutor
    import rclpy
    name = 'test_' + ''.join(c if c.isalnum() else '_' for c in request.node.name)[:50]
    node = rclpy.create_node(name)
    # One executor for the node's life: rclpy.spin_once(node) would build a new
    # one per call, too slow to keep up with a loop running at hundreds of Hz.
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    yield node
    executor.shutdown()
    node.destroy_node()


def spin_until(node, predicate, timeout: float, period: float = 0.02):
    """Spin `node` until `predicate()` is truthy; return its last value."""
    deadline = time.monotonic() + timeout
    value = predicate()
    while not value and time.monotonic() < deadline:
        node.executor.spin_once(timeout_sec=period)
        value = predicate()
    return value


def built_once(tmp_path_factory, name: str, build) -> Path:
    """Return `build(directory)`, built once per test run even across xdist workers.

    A session or module fixture is per process: under pytest-xdist each worker
    that runs one of its tests would train its own copy (a minute of CPU each,
    on two cores shared with the other workers). Here the first worker to ask
    builds it in a directory all workers of the run share, under a file lock;
    the others wait for it and use the same files. Only for what tests read and
    never change (a trained checkpoint).
    """
    if os.environ.get('PYTEST_XDIST_WORKER') is None:    # a run in one process
        return build(tmp_path_factory.mktemp(name))
    from filelock import FileLock
    # Each worker's base temp is <the run's temp>/popen-gwN: its parent is the run's.
    shared = tmp_path_factory.getbasetemp().parent / 'built_once'
    shared.mkdir(exist_ok=True)
    done = shared / f'{name}.done'
    with FileLock(str(shared / f'{name}.lock')):
        if not done.exists():
            directory = shared / name
            shutil.rmtree(directory, ignore_errors=True)   # a build that failed half-way
            directory.mkdir()
            done.write_text(str(build(directory)))
    return Path(done.read_text())


@pytest.fixture(scope='session')
def small_checkpoint(tmp_path_factory):
    """Train a small walker-walk-v0 checkpoint: a few hundred real training steps."""
    def build(directory):
        out = directory / 'run'
        subprocess.run([sys.executable, '-m', 'zeus_ros.learning_tools.train',
                        '--family', 'walker-walk-v0',
                        '--steps', '300', '--out', str(out), '--eval-every', '0',
                        '--checkpoint-every', '300', '--quiet'], check=True, cwd=REPO)
        return out / 'checkpoint'
    return built_once(tmp_path_factory, 'small_checkpoint', build)


def train_tiny(out: Path, family: str, method: str, steps: int = 120) -> Path:
    """Train a tiny checkpoint a few real steps (small networks, one thread); return it."""
    subprocess.run([sys.executable, '-m', 'zeus_ros.learning_tools.train', '--family', family,
                    '--method', method, '--steps', str(steps), '--out', str(out),
                    '--eval-every', '0', '--checkpoint-every', str(steps), '--quiet',
                    '--set', f'init_steps={min(100, steps - 20)}', 'hidden_dim=32',
                    'num_threads=1', 'batch_size_per_task=4', 'replay_capacity=2000'],
                   check=True, cwd=REPO, capture_output=True)
    return out / 'checkpoint'


def tiny_checkpoints(tmp_path_factory, family: str):
    """Return get(method): a tiny checkpoint of that method on `family`, trained once."""
    made = {}

    def get(method):
        if method not in made:
            made[method] = built_once(tmp_path_factory, f'tiny-{family}-{method}',
                                      lambda directory: train_tiny(directory / 'run', family,
                                                                   method))
        return made[method]
    return get


# Fixtures that start processes or a DDS participant: a test using any of them
# (directly or through another fixture) is a `ros` test, and so is every test of
# a module that declares `pytestmark = pytest.mark.ros` (it starts its own
# processes); every other test is a `unit` test.
_ROS_FIXTURES = frozenset({'spawn', 'ros_node', 'rclpy_context', 'small_checkpoint'})


# `make test-quick`: beside the unit tests, one test per module that starts real
# processes, each among the module's quicker ones (a few seconds to half a minute
# on a quiet machine), so that every module runs once through real nodes, DDS
# and the tools' entry points in a few minutes. Left out: test_ray_cluster.py and
# test_sweep.py, whose one real-process test each runs a whole sweep (minutes).
QUICK = (
    'test_adaptation.py::test_sac_report_has_no_context_sections',
    'test_camera.py::test_camera_node_publishes_frames_over_dds_at_the_rate',
    'test_check_parity.py::test_the_shipped_weights_are_identical_through_ros_and_a_mismatch_is_found',
    'test_closed_loop.py::test_ros_episode_return_equals_in_process_eval[shipped_walker_weights]',
    'test_composed.py::test_a_signal_stops_all_three_cleanly[2]',
    'test_controller_robustness.py::test_stray_joint_states_are_ignored_and_control_goes_on',
    'test_demo.py::test_the_readme_figures_are_what_make_demo_prints',
    'test_discovery.py::test_a_node_starts_with_the_profile_unless_the_user_names_one',
    'test_executor.py::test_the_events_executor_serves_timers_and_services_and_stops_cleanly',
    'test_foxglove.py::test_a_real_client_receives_every_channel_with_its_values',
    'test_interfaces.py::test_reset_service_round_trip',
    'test_metadata_fuzz.py::test_controllers_started_on_a_bad_file_exit_with_one_line',
    'test_onnx.py::test_onnx_controllers_run_the_in_process_onnx_episode',
    'test_orphans.py::test_a_second_sim_node_on_the_graph_is_refused',
    'test_own_graph.py::test_a_clean_lockstep_start_logs_no_warning',
    'test_pause_step.py::test_pause_stops_the_sim_step_takes_exactly_n_and_resume_runs_on[lockstep]',
    'test_recording.py::test_recorder_stores_what_the_publishers_offer',
    'test_recording_video.py::test_video_shows_the_robot_with_true_and_decoded_parameter',
    'test_ros_robustness_shutdown.py::test_a_running_node_stops_quietly_on_every_signal_pattern[sim_node]',
    'test_ros_robustness_sim.py::test_an_empty_reset_request_keeps_the_stream_and_names_its_episode',
    'test_sawyer_node.py::test_lockstep_with_live_goal_swaps_equals_the_in_process_episode',
    'test_set_param.py::test_a_live_swap_and_a_refusal_through_a_running_sim',
    'test_sim_node.py::test_live_friction_swap_is_continuous_and_reported',
    'test_soak.py::test_a_stop_signal_ends_the_soak_and_its_nodes',
    'test_swap_live.py::test_lockstep_queues_swaps_until_its_steps_and_a_reset_value_supersedes_them',
    'test_swap_services.py::test_200_concurrent_parameter_sets_are_all_answered',
    'test_workspace.py::test_config_yaml_is_what_the_sim_node_runs_with',
    'test_zero_shot_swap.py::test_live_swap_moves_latent_and_estimate[cheetah-torso-length]',
)


def pytest_collection_modifyitems(config, items):
    """Mark each test `ros` or `unit` (`pytest -m unit` runs the ROS-free ones).

    An `alone` test (timing assertions) also joins one xdist group: a parallel
    run that does not leave them out (`make test` runs them in a pass of their
    own) at least runs them one after another, on one worker (--dist loadgroup).
    """
    quick = {f'test/{name}' for name in QUICK}
    for item in items:
        if item.nodeid in quick:
            item.add_marker('quick')
            quick.discard(item.nodeid)
        if item.get_closest_marker('alone') is not None:
            item.add_marker(pytest.mark.xdist_group('alone'))
        if item.get_closest_marker('ros') is not None:
            continue
        uses = set(getattr(item, 'fixturenames', ()))
        item.add_marker('ros' if uses & _ROS_FIXTURES else 'unit')
    # A renamed test would leave its module out of `make test-quick` unnoticed:
    # where whole modules were collected, each QUICK name must have been found.
    whole = not (config.getoption('keyword') or config.getoption('deselect')
                 or any('::' in arg for arg in config.args))
    collected = {item.nodeid.split('::')[0] for item in items}
    missing = sorted(name for name in quick if name.split('::')[0] in collected)
    if whole and missing:
        raise pytest.UsageError(f'conftest.QUICK names tests that do not exist: {missing}')


def _stack_dump(pid: int, label: str) -> str:
    """Every thread's stack of a process, Python and native frames (py-spy), as text."""
    py_spy = shutil.which('py-spy') or str(Path(sys.executable).parent / 'py-spy')
    if not Path(py_spy).exists():
        return f'--- {label} (pid {pid}): py-spy not installed, no stacks\n'
    text = _run_for_text([py_spy, 'dump', '--native', '--pid', str(pid)])
    # py-spy shows only the threads running Python; the middleware's own threads
    # (Fast DDS receive, event and SHM watchdog threads) take a native debugger.
    gdb = shutil.which('gdb')
    if gdb:
        text += '--- all threads, native (gdb) ---\n' + _run_for_text(
            [gdb, '-p', str(pid), '-batch', '-nx', '-ex', 'set pagination off',
             '-ex', 'thread apply all bt'])
    return f'--- {label} (pid {pid}) ---\n{text}\n'


def _graph_view(node) -> str:
    """Describe the test node's graph: per subscription, the matched and discovered writers.

    A writer that is discovered but not matched, or matched but silent, says
    more about a lost message than any stack.
    """
    lines = ["--- the test node's view of the graph ---"]
    for sub in node.subscriptions:
        lines.append(f'{sub.topic_name}: {sub.get_publisher_count()} matched publisher(s)')
        for info in node.get_publishers_info_by_topic(sub.topic_name):
            gid = ''.join(f'{b:02x}' for b in info.endpoint_gid[:16])
            lines.append(f'    discovered: {info.node_namespace}/{info.node_name} gid {gid} '
                         f'{info.qos_profile.reliability.name}')
    return '\n'.join(lines) + '\n'


def _run_for_text(argv) -> str:
    try:
        done = subprocess.run(argv, capture_output=True, text=True, timeout=60)
        return done.stdout + done.stderr
    except subprocess.TimeoutExpired:
        return f'{argv[0]} timed out\n'


@pytest.hookimpl(wrapper=True)
def pytest_runtest_makereport(item, call):
    """On a failed test, dump the stacks of its processes and of pytest itself.

    This runs after the test body and before its fixtures are torn down: the
    nodes are still in the state the test failed in (a blocked publish, a stuck
    wait), and the test's own rclpy node still exists. The dump goes to the
    test's tmp directory and into the report (shown with the failure).
    """
    report = yield
    spawned = getattr(item, 'spawned', None)
    if report.when == 'call' and report.failed and spawned:
        # The graph first: the dumps take seconds, and stop each process a while.
        node = getattr(item, 'funcargs', {}).get('ros_node')
        dumps = [_graph_view(node)] if node is not None else []
        dumps += [_stack_dump(proc.proc.pid, Path(proc.log_path).stem)
                  for proc in spawned if proc.alive()]
        dumps.append(_stack_dump(os.getpid(), 'pytest (this process)'))
        text = ''.join(dumps)
        path = Path(spawned[0].log_path).parent / 'stacks_at_failure.txt'
        path.write_text(text)
        report.sections.append(('stacks at failure', f'(also in {path})\n{text}'))
    return report
