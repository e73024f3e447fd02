"""
Print the messages of a topic, as `ros2 topic echo` does (for installs without ros2cli).

    python -m activeloc_ros.echo /surprise_map
    python -m activeloc_ros.echo /action_location --count 5 --timeout 30
"""
import argparse
import sys
import time

import numpy as np

from activeloc_ros.checks import argument, non_negative
from activeloc_ros.nodes.messages import message_class


def format_message(msg) -> str:
    """A readable text of a message; a Float32MultiArray with 2 dims prints as a grid."""
    if type(msg).__name__ == 'Float32MultiArray' and len(msg.layout.dim) == 2:
        rows, cols = msg.layout.dim[0].size, msg.layout.dim[1].size
        grid = np.asarray(msg.data, dtype=np.float32).reshape(rows, cols)
        body = np.array2string(grid, precision=4, suppress_small=True, max_line_width=200)
        return f'{rows}x{cols} map, sum {grid.sum():.3f}, peak {grid.max():.4f} at ' \
               f'{np.unravel_index(grid.argmax(), grid.shape)}\n{body}'
    text = []
    for name in msg.get_fields_and_field_types():
        value = getattr(msg, name)
        if isinstance(value, (bytes, bytearray)) or (hasattr(value, '__len__')
                                                     and len(value) > 32):
            value = f'<{len(value)} values>'
        text.append(f'{name}: {value}')
    return '\n'.join(text)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog='python -m activeloc_ros.echo', description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument('topic', help='topic name; a relative one (surprise_map) is resolved '
                        'in the root namespace, as ros2 topic echo does')
    parser.add_argument('--count', type=argument(non_negative, int), default=0,
                        help='exit after N messages (0: never)')
    parser.add_argument('--timeout', type=argument(non_negative), default=0.0,
                        help='exit with code 1 if the topic has not appeared/answered by then '
                             '(seconds; 0: wait for ever)')
    args = parser.parse_args(argv)
    import rclpy
    from rclpy.executors import ExternalShutdownException
    from rclpy.qos import QoSProfile
    from activeloc_ros.nodes.qos import offered_reliability
    rclpy.init()
    node = rclpy.create_node('echo')
    start, received, sub = time.monotonic(), 0, None
    try:
        try:
            topic = node.resolve_topic_name(args.topic)
        except RuntimeError as exc:     # rcl's verdict on the name
            print(f'error: {args.topic!r} is no topic name: {exc}', file=sys.stderr)
            return 2
        while rclpy.ok() and (not args.count or received < args.count):
            if sub is None:
                types = dict(node.get_topic_names_and_types()).get(topic)
                if types:
                    def show(msg):
                        nonlocal received
                        received += 1
                        print(format_message(msg), '\n---', flush=True)
                    # a best-effort publisher (a camera driver) is heard only best effort
                    qos = QoSProfile(depth=10, reliability=offered_reliability(node, topic))
                    sub = node.create_subscription(message_class(types[0]), topic, show, qos)
            rclpy.spin_once(node, timeout_sec=0.1)
            if args.timeout and not received and time.monotonic() - start > args.timeout:
                print(f'no message on {topic} within {args.timeout:g} s', file=sys.stderr)
                return 1
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == '__main__':
    sys.exit(main())
