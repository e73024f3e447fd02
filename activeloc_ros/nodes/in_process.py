"""bringup --in-process: every node of the graph in one context and one executor."""
import importlib
import threading

from activeloc_ros.graph_plan import graph_nodes, node_arguments
from activeloc_ros.supervisor import STOP_DEADLINE_S


class InProcessGraph:
    """All nodes in one context and one multi-threaded executor."""

    def __init__(self, args, context):
        from rclpy.executors import MultiThreadedExecutor
        self.context = context
        self.executor = MultiThreadedExecutor(num_threads=4, context=context)
        self.nodes = {}
        for name in graph_nodes(args):
            module = importlib.import_module(f'activeloc_ros.nodes.{name}_node')
            node_class = getattr(module, f'{name.capitalize()}Node')
            self.nodes[name] = node_class(context=context, cli_args=node_arguments(name, args))
            self.executor.add_node(self.nodes[name])
        self.halt = threading.Event()
        self.crashed: BaseException | None = None    # what ended the executor's thread
        self.thread = threading.Thread(target=self._spin, daemon=True)
        self.thread.start()

    def _spin(self):
        from rclpy.executors import ExternalShutdownException
        try:
            while not self.halt.is_set() and self.context.ok():
                self.executor.spin_once(timeout_sec=0.05)
        except ExternalShutdownException:
            pass
        except BaseException as exc:      # a callback's exception ends every node's spin
            self.crashed = exc

    def failure(self) -> str | None:
        """
        Why the graph cannot go on, as a node process's exit code says it: a node that
        gave up (a camera stream that failed, an arm link down for give_up_timeout), or a
        callback that raised.
        """
        if self.crashed is not None:
            return f'a node callback raised {type(self.crashed).__name__}: {self.crashed}'
        for name, node in self.nodes.items():
            if getattr(node, 'failure', None):
                return f'{name}: {node.failure}'
        return None

    def camera_finished(self) -> bool:
        return next(iter(self.nodes.values())).finished    # the camera or the sim

    def stop(self):
        """The controller and the arm stop on purpose while the executor still runs them."""
        for name in ('controller', 'arm'):
            if name in self.nodes:
                self.nodes[name].stop_on_purpose()
        self.halt.set()
        self.thread.join(timeout=STOP_DEADLINE_S)
        self.executor.shutdown(timeout_sec=STOP_DEADLINE_S)
        for node in self.nodes.values():
            node.destroy_node()
