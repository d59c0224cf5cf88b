"""Echo zeus_msgs messages and answer the Reset service, in a process of its own."""

import rclpy
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from zeus_msgs.msg import Context, StepInfo
from zeus_msgs.srv import Reset


class EchoNode(Node):

    def __init__(self):
        super().__init__('zeus_echo')
        self.context_pub = self.create_publisher(Context, 'echo/context_out', 10)
        self.step_pub = self.create_publisher(StepInfo, 'echo/step_out', 10)
        self.create_subscription(Context, 'echo/context_in', self.context_pub.publish, 10)
        self.create_subscription(StepInfo, 'echo/step_in', self.step_pub.publish, 10)
        self.create_service(Reset, 'echo/reset', self.reset_callback)

    def reset_callback(self, request, response):
        pairs = ','.join(f'{n}={v!r}' for n, v in
                         zip(request.param_names, request.param_values, strict=True))
        response.success = request.seed >= 0
        response.message = f'seed={request.seed};{pairs}'
        return response


def run(make_node) -> None:
    """Spin the node `make_node()` builds until SIGINT, then close it (other helpers use it)."""
    rclpy.init()
    node = make_node()
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


if __name__ == '__main__':
    run(EchoNode)
