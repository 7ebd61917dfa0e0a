"""Why the Atom stand-in's drop rates differ from the paper's: per-image costs of the
pieces a 2017 node could have spent its time on, timed unthrottled and in the Atom
stand-in (:mod:`cryptoros.bench.standin`).

Timed per message (encrypt + decrypt, a new cipher object each, as PyCrypto was used),
on the paper's 80 KB image and on a raw 640x480 rgb8 image (921,654 B), CPU time
unthrottled and wall time in the stand-in, for each of the
paper's ciphers in CBC: PyCrypto 2.6.1 (the paper's library, ``Crypto``) when the given
interpreter has it, and pycryptodome (``Cryptodome``). Beside them: the key schedule
alone (a cipher object made for a 16-byte message), base64 of the ciphertext both ways,
and a per-byte Python conversion of the ciphertext (``list(c)`` and back), the cost of
handing bytes around as Python integers.
"""

from __future__ import annotations

import json
import subprocess

WORKER = r"""
import base64, json, os, sys, time
sys.stdout.write("READY\n"); sys.stdout.flush()
sys.stdin.readline()
# unthrottled: CPU time (the machine is shared); in the stand-in: wall time (the quota's stalls count)
if sys.argv[1] == "1":
    clock = getattr(time, "perf_counter", time.time)
else:
    clock = getattr(time, "process_time", None) or time.clock
sizes = [("image 80 KB", 79737), ("raw image 921 KB", 921654)]
key = bytes(bytearray(range(11, 35)))
libs = []
try:
    from Crypto.Cipher import AES as A1, DES3 as D1, Blowfish as B1
    libs.append(("PyCrypto 2.6.1", [("3DES", D1, 8), ("AES", A1, 16), ("Blowfish", B1, 8)]))
except Exception:
    pass
from Cryptodome.Cipher import AES as A2, DES3 as D2, Blowfish as B2
libs.append(("pycryptodome", [("3DES", D2, 8), ("AES", A2, 16), ("Blowfish", B2, 8)]))
no_aesni = sys.argv[1] == "1"
budget = float(sys.argv[2])

def timed(fn, floor=3):
    t0 = clock(); n = 0
    while n < floor or clock() - t0 < budget:
        fn(); n += 1
    return (clock() - t0) / n * 1e6

out = []
for size_name, n in sizes:
    m = os.urandom(n - n % 16 + 16)
    for lib, ciphers in libs:
        for name, mod, block in ciphers:
            extra = {"use_aesni": False} if (no_aesni and lib == "pycryptodome" and name == "AES") else {}
            iv = os.urandom(block)
            def rt(mod=mod, iv=iv, extra=extra):
                c = mod.new(key, mod.MODE_CBC, iv, **extra).encrypt(m)
                mod.new(key, mod.MODE_CBC, iv, **extra).decrypt(c)
            out.append({"what": "%s %s-CBC enc+dec" % (lib, name), "size": size_name, "us": timed(rt)})
            if size_name.startswith("image"):
                small = bytes(bytearray(16))
                out.append({"what": "%s %s key schedule + one block" % (lib, name), "size": "16 B",
                            "us": timed(lambda mod=mod, iv=iv, extra=extra: mod.new(key, mod.MODE_CBC, iv, **extra).encrypt(small), 50)})
    out.append({"what": "base64 encode + decode", "size": size_name,
                "us": timed(lambda: base64.b64decode(base64.b64encode(m)))})
    out.append({"what": "bytes -> list of ints -> bytes", "size": size_name,
                "us": timed(lambda: bytes(bytearray(list(bytearray(m)))))})
sys.stdout.write(json.dumps({"python": sys.version.split()[0], "rows": out}) + "\n"); sys.stdout.flush()
"""


def compare(python: str, stand, budget: float = 0.5, env: dict[str, str] | None = None) -> list[dict]:
    """Runs the worker under ``python`` (Python 2.7 or 3, with ``Cryptodome`` and maybe
    PyCrypto's ``Crypto``) unthrottled and in ``stand`` (an Atom stand-in): rows of
    {what, size, us, atom_us, python}."""
    def one(throttled: bool) -> list[dict]:
        proc = subprocess.Popen([python, "-c", WORKER, "1" if throttled else "0", str(budget if not throttled else budget * 4)],
                                stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, env=env)
        try:
            assert proc.stdin is not None and proc.stdout is not None
            if proc.stdout.readline().strip() != "READY":
                raise RuntimeError(f"{python}: the library worker did not start (pycryptodome missing?)")
            if throttled:
                stand.attach(proc.pid)
            out, _ = proc.communicate("go\n", timeout=1800)
            got = json.loads(out)
            return [{**r, "python": got["python"]} for r in got["rows"]]
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()

    free, atom = one(False), one(True)
    by = {(r["what"], r["size"]): r["us"] for r in atom}
    return [{**r, "atom_us": by.get((r["what"], r["size"]))} for r in free]


__all__ = ["WORKER", "compare"]
