"""executor:=events: a node's services and timers on rclpy's EventsExecutor (issue #38.9).

Its spin() fires a timer at most once in the pinned rclpy
(research/benchmarks/events_executor_repro.py);
spin_loop drives it with spin_once and a timeout, and keeps the loop's
subscriptions and lock its own. Real processes, real DDS.
"""

from conftest import installed_exe, spin_until
from diagnostic_msgs.msg import DiagnosticArray
import numpy as np
from sim_driver import start_sim, WALKER_ACTUATORS as ACTUATORS


def test_the_events_executor_serves_timers_and_services_and_stops_cleanly(spawn, ros_node):
    reports = []
    ros_node.create_subscription(DiagnosticArray, '/diagnostics', lambda m: reports.extend(
        s for s in m.status if 'sim_node' in s.name), 10)
    proc, driver = start_sim(spawn, ros_node, family='walker-walk-v0', command_timeout=10.0,
                             executor='events')
    driver.reset(seed=3)                        # ~/reset, a service of the node
    for action in np.zeros((5, 6)):
        _, info = driver.step(action, ACTUATORS)   # the loop: the sim's own thread
    result = driver.set_param('friction', 0.4)  # the parameter service
    assert result.successful, result.reason
    _, info = driver.step(np.zeros(6), ACTUATORS)
    assert list(info.param_values) == [0.4] and info.step == 6
    # The 1 Hz diagnostics timer, again and again (spin() fired it at most once).
    assert spin_until(ros_node, lambda: len(reports) >= 3, 20.0), reports
    code = proc.stop()                          # SIGINT: the usual clean stop
    output = proc.log_path.read_text()
    assert code == 0 and 'Traceback' not in output, output


def test_an_unknown_executor_is_refused_in_one_line(spawn):
    proc = spawn([installed_exe('sim_node'), '--ros-args', '-p', 'executor:=multi'])
    assert proc.proc.wait(120) == 1, proc.output()
    assert "SimNode: parameter executor: 'multi' is not one of single, events" in proc.output()
    assert 'Traceback' not in proc.output(), proc.output()
