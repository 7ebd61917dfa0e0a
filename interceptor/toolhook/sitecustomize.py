"""A refusal by cryptoros ends a stock ROS tool with one line, not a traceback.

``cryptoros run`` and ``cryptoros env`` put this directory first on ``PYTHONPATH`` for
the nodes and tools they start, so Python loads this file at start-up. Some tools let a
master's error escape as an exception: ros_comm 1.15's ``rosparam set`` catches no
``rosgraph.masterapi.Error`` (a plain rosmaster never refuses a write), so a write
cryptoros refuses would end in a traceback whose last line is the refusal. This hook
prints such an uncaught error as the tools print their own errors, ``ERROR: denied by
cryptoros: <reason>`` (exit status 1, as any uncaught exception); every other exception
is reported as before. ``rosnode kill`` ignores the node's answer to ``shutdown`` and
prints ``killed`` whatever it was: when ``rosnode`` is imported, its ``kill_nodes`` is
wrapped so that a node whose ``shutdown`` cryptoros refused is reported as not killed
(``ERROR: Failed to kill``, exit status 1) after the refusal's line, and its cleanup goes
on past a node whose unregistration cryptoros refuses (another robot's node: one line
each). ``rosservice`` reads a refused probe of a service as a service of
no type: it says the refusal instead (one line). rospy logs a refused registration as ``[FATAL]`` and carries on, which a node may
want but leaves ``rostopic`` echoing nothing or saying it published (exit status 0): in
``rostopic`` such a refusal is one ``ERROR:`` line, and the tool ends (exit status 1). It
then runs the installation's own ``sitecustomize`` (Debian ships one), which this file
would otherwise hide.

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


def _shutdown(module, name):
    """(code, message) of node ``name``'s answer to ``shutdown``, or None when it could
    not be asked (gone, or it went down while answering)."""
    from xmlrpc.client import ServerProxy

    try:
        uri = module.rosgraph.Master(module.ID).lookupNode(name)
        code, message, _value = ServerProxy(uri).shutdown(module.ID, "user request")
    except Exception:
        return None
    return code, str(message)


def _patch_rosnode(module):
    original = module.kill_nodes

    def kill_nodes(node_names):
        success, fail, unasked = [], [], []
        for name in node_names:
            answer = _shutdown(module, name)
            if answer is None:
                unasked.append(name)  # rosnode's own way: looked up again, its failure reported
            elif answer[0] != 1 and _REFUSED in answer[1]:
                sys.stderr.write(f"ERROR: {answer[1]}\n")
                fail.append(name)
            else:  # shut down (or an error rosnode itself would not report)
                success.append(name)
        if unasked:
            more_success, more_fail = original(unasked)
            success += more_success
            fail += more_fail
        return success, fail

    module.kill_nodes = kill_nodes
    cleanup = module.cleanup_master_blacklist

    def cleanup_master_blacklist(master, blacklist):
        for name in blacklist:  # one at a time: a refusal stops only its own node's
            try:
                cleanup(master, [name])
            except Exception as exc:
                if _REFUSED not in str(exc):
                    raise
                sys.stderr.write(f"ERROR: {name}: {exc}\n")

    module.cleanup_master_blacklist = cleanup_master_blacklist


def _patch_registration(module):
    """In ``rostopic``, a registration cryptoros refuses ends the tool: one line, rospy
    shut down (what it registered is unregistered), exit status 1."""
    logfatal = module.logfatal

    def refusal_ends_the_tool(message, *args, **kwargs):
        if _REFUSED not in str(message):
            return logfatal(message, *args, **kwargs)
        sys.stderr.write(f"ERROR: {message}\n")
        sys.stderr.flush()
        try:
            from rospy.core import signal_shutdown

            signal_shutdown("denied by cryptoros")
        finally:
            os._exit(1)

    module.logfatal = refusal_ends_the_tool


def _patch_rosservice(module):
    """``rosservice call/type/info`` learn a service's type from a probe of it; a probe
    cryptoros refuses answers an error header, which rosservice reads as a service of no
    type (``Unable to determine type of service``, ``Unknown service``): it is reported as
    the refusal instead, one ``ERROR:`` line (rosservice's own for its errors)."""
    probe = module.get_service_headers

    def get_service_headers(service_name, service_uri):
        header = probe(service_name, service_uri)
        error = header.get("error", "")
        if _REFUSED in error:
            hint = "" if "cryptoros denials" in error else " (cryptoros denials says what to grant)"
            raise module.ROSServiceException(f"service [{service_name}]: {error}{hint}")
        return header

    module.get_service_headers = get_service_headers


#: module -> what wraps it once loaded
_PATCHES = {"rosnode": _patch_rosnode, "rosservice": _patch_rosservice}
if os.path.basename(sys.argv[0] if sys.argv else "") == "rostopic":
    _PATCHES["rospy.impl.registration"] = _patch_registration


class _PatchOnImport:
    """A finder that lets the modules of :data:`_PATCHES` load as usual, then wraps them."""

    def find_spec(self, fullname, path=None, target=None):
        patch = _PATCHES.get(fullname)
        if patch is None:
            return None
        spec = importlib.machinery.PathFinder.find_spec(fullname, path)
        if spec is None or spec.loader is None:
            return None
        loader = spec.loader
        run = loader.exec_module

        def exec_module(module):
            run(module)
            try:
                patch(module)
            except AttributeError:  # another version than ros_comm 1.15's: left as it is
                pass

        loader.exec_module = exec_module
        return spec


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
sys.meta_path.insert(0, _PatchOnImport())
_run_next_sitecustomize()
