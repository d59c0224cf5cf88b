"""Demo: start sim_node, swap friction live, and show the robot carry on under it.

Runs sim_node (walker-walk-v0, realtime x4) in its own process, watches
/joint_states and /zeus/step over DDS, sets friction 1.0 -> 0.4 -> 1.7 with the
parameter service (what `ros2 param set` does), tries a NaN (refused), and
prints what the sim reported. The adaptation demo with trained weights replaces
this once the context and policy nodes land.
"""

import os
from pathlib import Path
import signal
import subprocess
import sys
import time

os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')

import numpy as np  # noqa: E402
from rcl_interfaces.srv import SetParameters  # noqa: E402
import rclpy  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from sensor_msgs.msg import JointState  # noqa: E402
from zeus_msgs.msg import StepInfo  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
SIM = REPO / 'install' / 'zeus_ros' / 'lib' / 'zeus_ros' / 'sim_node'
SCHEDULE = ((1.0, 3.0), (0.4, 3.0), (float('nan'), 0.0), (1.7, 3.0))


def spin_for(node, seconds):
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        rclpy.spin_once(node, timeout_sec=0.02)


def main():
    sim = subprocess.Popen([str(SIM), '--ros-args', '-p', 'family:=walker-walk-v0',
                            '-p', 'mode:=realtime', '-p', 'real_time_factor:=4.0'])
    rclpy.init()
    node = rclpy.create_node('zeus_demo')
    states, steps = [], []
    node.create_subscription(JointState, '/joint_states', states.append, 10)
    node.create_subscription(StepInfo, '/zeus/step', steps.append, 10)
    client = node.create_client(SetParameters, '/sim_node/set_parameters')
    try:
        if not client.wait_for_service(timeout_sec=30.0):
            sys.exit('sim_node did not start')
        print(f'{"friction asked":>15} {"accepted":>9} {"reported":>9} {"states/s":>9} '
              f'{"max |dq| at swap":>17}  reason')
        for value, seconds in SCHEDULE:
            before = np.array(states[-1].position) if states else None
            future = client.call_async(SetParameters.Request(
                parameters=[Parameter('friction', value=value).to_parameter_msg()]))
            rclpy.spin_until_future_complete(node, future)
            result = future.result().results[0]
            start = len(states)
            spin_for(node, seconds)
            rate = (len(states) - start) / seconds if seconds else float('nan')
            jump = (np.abs(np.array(states[start].position) - before).max()
                    if before is not None and len(states) > start else float('nan'))
            print(f'{value:>15g} {str(result.successful):>9} {steps[-1].param_values[0]:>9g} '
                  f'{rate:>9.1f} {jump:>17.4f}  {result.reason}')
        print(f'{len(states)} joint states over {steps[-1].episode + 1} episode(s); '
              f'final step {steps[-1].step}')
    finally:
        node.destroy_node()
        rclpy.shutdown()
        sim.send_signal(signal.SIGINT)
        sim.wait(10)


if __name__ == '__main__':
    main()
