"""The long-running writer of the reproduction; trial.py starts it.

    python pub.py --status FILE [--rate 200] [--srv-period 0.5]

Publishes /shmx/data (std_msgs/Int64, a sequence number) at --rate Hz, calls
the service /shmx/srv (std_srvs/Trigger) every --srv-period seconds once a
server is there, and counts what sub.py publishes on /shmx/ack. Writes its
counters as JSON to --status every 0.2 s.
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


class Writer(Node):

    def __init__(self, args):
        super().__init__('shmx_pub')
        self.status_path = args.status
        self.status = dict(pid=os.getpid(), start=time.time(), rate=args.rate, sent=0,
                           req=0, resp=0, last_resp=0.0, acks=0, last_ack=0.0,
                           last_ack_val=-1)
        self.pub = self.create_publisher(Int64, '/shmx/data', 10)
        self.client = self.create_client(Trigger, '/shmx/srv')
        self.create_subscription(Int64, '/shmx/ack', self.on_ack, 10)
        self.create_timer(1.0 / args.rate, self.publish_next)
        self.create_timer(args.srv_period, self.call)
        self.create_timer(0.2, lambda: write_status(self.status_path, self.status))

    def publish_next(self):
        self.status['sent'] += 1
        self.pub.publish(Int64(data=self.status['sent']))

    def call(self):
        if self.client.service_is_ready():
            self.status['req'] += 1
            self.client.call_async(Trigger.Request()).add_done_callback(self.on_response)

    def on_response(self, _future):
        self.status['resp'] += 1
        self.status['last_resp'] = time.time()

    def on_ack(self, msg):
        self.status['acks'] += 1
        self.status['last_ack'] = time.time()
        self.status['last_ack_val'] = msg.data


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--status', required=True)
    parser.add_argument('--rate', type=float, default=200.0)
    parser.add_argument('--srv-period', type=float, default=0.5)
    args = parser.parse_args()
    rclpy.init()
    try:
        rclpy.spin(Writer(args))
    except (KeyboardInterrupt, ExternalShutdownException):
        pass


if __name__ == '__main__':
    main()
