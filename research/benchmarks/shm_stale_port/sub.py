"""The reader of the reproduction, the process trial.py SIGKILLs and restarts.

    python sub.py --status FILE [--busy]

Subscribes /shmx/data, serves /shmx/srv (std_srvs/Trigger) and publishes its
receive count on /shmx/ack at 2 Hz (its own outgoing traffic). Writes its
counters as JSON to --status at start and every 0.2 s: rx/first_rx for data,
srv/first_srv for service requests (times in seconds since the epoch). --busy
holds the GIL 80 ms of every 100 ms in a timer callback.
"""

import argparse
import json
import os
import time

import rclpy
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from std_msgs.msg import Int64
from std_srvs.srv import Trigger


def write_status(path, status):
    tmp = f'{path}.tmp'
    with open(tmp, 'w') as f:
        json.dump(status, f)
    os.replace(tmp, path)


def burn(seconds=0.08):
    end = time.perf_counter() + seconds
    while time.perf_counter() < end:
        pass


class Reader(Node):

    def __init__(self, args, started):
        super().__init__('shmx_sub')
        self.status_path = args.status
        self.status = dict(pid=os.getpid(), start=started, node_up=time.time(), rx=0,
                           first_rx=0.0, last_rx=0.0, last_seq=-1, srv=0, first_srv=0.0,
                           last_srv=0.0)
        self.ack = self.create_publisher(Int64, '/shmx/ack', 10)
        self.create_subscription(Int64, '/shmx/data', self.on_data, 10)
        self.create_service(Trigger, '/shmx/srv', self.on_request)
        self.create_timer(0.5, lambda: self.ack.publish(Int64(data=self.status['rx'])))
        self.create_timer(0.2, self.dump)
        if args.busy:
            self.create_timer(0.1, burn)
        self.dump()

    def dump(self):
        write_status(self.status_path, self.status)

    def on_data(self, msg):
        now = time.time()
        self.status['first_rx'] = self.status['first_rx'] or now
        self.status['rx'] += 1
        self.status['last_rx'] = now
        self.status['last_seq'] = msg.data

    def on_request(self, _request, response):
        now = time.time()
        self.status['first_srv'] = self.status['first_srv'] or now
        self.status['srv'] += 1
        self.status['last_srv'] = now
        response.success = True
        return response


def main():
    started = time.time()
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--status', required=True)
    parser.add_argument('--busy', action='store_true')
    args = parser.parse_args()
    rclpy.init()
    try:
        rclpy.spin(Reader(args, started))
    except (KeyboardInterrupt, ExternalShutdownException):
        pass


if __name__ == '__main__':
    main()
