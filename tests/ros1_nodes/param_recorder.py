#!/usr/bin/python3
"""A recording proxy in front of rosmaster: every parameter call (inside multicalls too)
is forwarded and appended to OUT as one JSON line [method, caller_id, key].

  param_recorder.py UPSTREAM_URI PORT OUT     prints READY once it listens

How cryptoros/policy/infrastructure.py's default-readable list was measured
(docs/stock-tools.md); tests/system/test_stock_tools.py runs it again."""
import json, sys, threading, xmlrpc.client
from socketserver import ThreadingMixIn
from xmlrpc.server import SimpleXMLRPCServer, SimpleXMLRPCRequestHandler

PARAM = {"getParam", "hasParam", "searchParam", "subscribeParam", "unsubscribeParam", "setParam", "deleteParam", "getParamNames"}
upstream, port, out = sys.argv[1], int(sys.argv[2]), sys.argv[3]
lock = threading.Lock()

def note(method, params):
    if method in PARAM:
        key = params[2] if method in ("subscribeParam", "unsubscribeParam") else (params[1] if len(params) > 1 else "")
        with lock, open(out, "a") as f:
            f.write(json.dumps([method, params[0], key]) + "\n")

class S(ThreadingMixIn, SimpleXMLRPCServer):
    daemon_threads = True

class H(SimpleXMLRPCRequestHandler):
    rpc_paths = ()

srv = S(("127.0.0.1", port), requestHandler=H, logRequests=False, allow_none=True)
def dispatch(method, params):
    proxy = xmlrpc.client.ServerProxy(upstream, allow_none=True)
    if method == "system.multicall":
        for c in params[0]:
            note(c["methodName"], c["params"])
        return getattr(proxy, "system.multicall")(params[0])
    note(method, params)
    return getattr(proxy, method)(*params)
srv._dispatch = dispatch
print("READY", flush=True)
srv.serve_forever()
