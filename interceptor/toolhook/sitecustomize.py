"""A refusal by cryptoros ends a stock ROS tool with one line, not a traceback.

``cryptoros run`` and ``cryptoros env`` put this directory first on ``PYTHONPATH`` for
the nodes and tools they start, so Python loads this file at start-up. Some tools let a
master's error escape as an exception: ros_comm 1.15's ``rosparam set`` catches no
``rosgraph.masterapi.Error`` (a plain rosmaster never refuses a write), so a write
cryptoros refuses would end in a traceback whose last line is the refusal. This hook
prints such an uncaught error as the tools print their own errors, ``ERROR: denied by
cryptoros: <reason>`` (exit status 1, as any uncaught exception); every other exception
is reported as before. It then runs the installation's own ``sitecustomize`` (Debian
ships one), which this file would otherwise hide.

Standalone on purpose: the tools run under the system's Python, without cryptoros.
"""

import importlib.machinery
import importlib.util
import os
import sys

_REFUSED = "denied by cryptoros"
_previous_hook = sys.excepthook


def _one_line_refusal(kind, value, tb):
    if _REFUSED in str(value) and not issubclass(kind, (SyntaxError, KeyboardInterrupt)):
        sys.stderr.write(f"ERROR: {value}\n")
        sys.stderr.flush()
        return
    _previous_hook(kind, value, tb)


def _run_next_sitecustomize():
    here = os.path.dirname(os.path.abspath(__file__))
    rest = [p for p in sys.path if os.path.abspath(p or os.curdir) != here]
    spec = importlib.machinery.PathFinder.find_spec("sitecustomize", rest)
    if spec is None or spec.loader is None:
        return
    module = importlib.util.module_from_spec(spec)
    try:
        spec.loader.exec_module(module)
    except Exception as exc:  # as site.py treats a failing sitecustomize: reported, not fatal
        sys.stderr.write(f"Error in sitecustomize; set PYTHONVERBOSE for traceback:\n{type(exc).__name__}: {exc}\n")


sys.excepthook = _one_line_refusal
_run_next_sitecustomize()
