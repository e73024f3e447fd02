"""
How bringup starts a node's process: ``python -m activeloc_ros.nodes.start NODE ARGS``.

A node's module loads torch, OpenCV or OpenVINO before its own stop handling
(`process.run`) is in place, which takes seconds; a Ctrl-C or SIGTERM then came out as a
KeyboardInterrupt traceback and a failed exit. Here a stop while the module loads ends the
process cleanly once the module is loaded (exit 0, a line saying so); then the node's
``main`` runs with the signal handling it always had.
"""
import importlib
import signal
import sys

STOPPED_LOADING = 'stopped (Ctrl-C or SIGTERM) while the node was loading'
OUTSIDE_HANDLING = "stopped (Ctrl-C) outside the node's own stop handling"


_stop_asked: list[int] = []     # the signals that came while the module loaded


def _stop(signum, frame):
    # no exception: one raised inside an extension's initialisation (torch's C++) can abort
    # the process or make Python end it with SIGINT however it was handled
    _stop_asked.append(signum)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if not argv or argv[0] in ('-h', '--help'):
        print(__doc__.strip())
        return 0 if argv else 2
    previous = {sig: signal.signal(sig, _stop) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        module = importlib.import_module(f'activeloc_ros.nodes.{argv[0]}_node')
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    from activeloc_ros.nodes.process import ignore_late_stops
    try:
        if _stop_asked:          # the node was never made: nothing to stop but the process
            print(STOPPED_LOADING, file=sys.stderr, flush=True)
            return 0
        sys.argv = [module.__file__, *argv[1:]]
        return module.main()
    except KeyboardInterrupt:     # a Ctrl-C before the node's own handling was in place
        print(OUTSIDE_HANDLING, file=sys.stderr, flush=True)
        return 0
    finally:
        ignore_late_stops()


if __name__ == '__main__':
    sys.exit(main())
