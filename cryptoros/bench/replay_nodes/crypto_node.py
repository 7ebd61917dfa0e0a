#!/usr/bin/python3
"""Seed 002's encrypting or decrypting rospy node (run by Debian's python3 with
pycryptodome, the maintained PyCrypto line).

argv: ROLE (enc|dec) SENSOR (laser|image) CIPHER STATS_JSON NO_AESNI (0|1) IMAGE (compressed|raw)

enc: subscribes to the sensor's topic with its real type (rospy deserializes it, as the
paper's node got it), serializes it, encrypts the bytes with a cipher object made for
this message (PyCrypto's usage: ``new(key, mode, iv)`` per message, so each message
pays the key schedule) and publishes them as std_msgs/UInt8MultiArray on TOPIC_enc.
dec: subscribes to TOPIC_enc, decrypts, checks the padding or tag and deserializes the
sensor message again. Both queues hold one message, as the paper's nodes did
(TCPROS with a queue of one: a message that arrives while the node is busy replaces the
one waiting).

Ciphers: plain (copy, no cipher: the pipeline's own cost), 3des, aes, blowfish (CBC, one
24-byte key for all three, IV 8 B or 16 B: the paper's footnote; AES with a 24-byte
key is AES-192), aes-gcm (AES-128-GCM), chacha20 (ChaCha20-Poly1305), both with a
12-byte nonce. NO_AESNI=1 turns pycryptodome's AES-NI and CLMUL paths off (the Atom
D525 has neither).

The node prints READY when it is subscribed (and, for enc, when its decrypting peer is
connected), samples its own CPU time and its connections' byte counters 4 times a
second, and writes STATS_JSON (every sample, each processed message's wall time and the
time spent in each stage) when it gets SIGTERM or SIGINT.
"""
import io
import json
import os
import signal
import sys
import threading
import time

import rospy
from sensor_msgs.msg import CompressedImage, Image, LaserScan
from std_msgs.msg import UInt8MultiArray

role, sensor, cipher_name, stats_path, no_aesni = sys.argv[1], sys.argv[2], sys.argv[3], sys.argv[4], sys.argv[5] == "1"
image_kind = sys.argv[6] if len(sys.argv) > 6 else "compressed"
TOPICS = {"laser": ("/scan", LaserScan), "image": ("/camera/image", CompressedImage if image_kind == "compressed" else Image)}
topic, msg_type = TOPICS[sensor]

KEY = bytes(range(11, 11 + 24))  # the paper: one 24-byte key for the three ciphers
KEY32 = bytes(range(41, 41 + 32))


def make_cipher():
    """(encrypt(bytes) -> bytes, decrypt(bytes) -> bytes): a new cipher object per message."""
    from Cryptodome.Util.Padding import pad, unpad
    urandom = os.urandom
    if cipher_name == "plain":
        return (lambda m: bytes(m)), (lambda c: bytes(c))
    if cipher_name in ("3des", "aes", "blowfish"):
        from Cryptodome.Cipher import AES, DES3, Blowfish
        mod, block = {"3des": (DES3, 8), "aes": (AES, 16), "blowfish": (Blowfish, 8)}[cipher_name]
        extra = {"use_aesni": False} if (no_aesni and mod is AES) else {}

        def enc(m):
            iv = urandom(block)
            return iv + mod.new(KEY, mod.MODE_CBC, iv, **extra).encrypt(pad(m, block))

        def dec(c):
            return unpad(mod.new(KEY, mod.MODE_CBC, c[:block], **extra).decrypt(c[block:]), block)
        return enc, dec
    if cipher_name == "aes-gcm":
        from Cryptodome.Cipher import AES
        extra = {"use_aesni": False, "use_clmul": False} if no_aesni else {}

        def enc(m):
            nonce = urandom(12)
            c, tag = AES.new(KEY[:16], AES.MODE_GCM, nonce=nonce, **extra).encrypt_and_digest(m)
            return nonce + c + tag

        def dec(c):
            return AES.new(KEY[:16], AES.MODE_GCM, nonce=c[:12], **extra).decrypt_and_verify(c[12:-16], c[-16:])
        return enc, dec
    if cipher_name == "chacha20":
        from Cryptodome.Cipher import ChaCha20_Poly1305

        def enc(m):
            nonce = urandom(12)
            c, tag = ChaCha20_Poly1305.new(key=KEY32, nonce=nonce).encrypt_and_digest(m)
            return nonce + c + tag

        def dec(c):
            return ChaCha20_Poly1305.new(key=KEY32, nonce=c[:12]).decrypt_and_verify(c[12:-16], c[-16:])
        return enc, dec
    raise SystemExit("unknown cipher %r" % cipher_name)


encrypt, decrypt = make_cipher()
clock = time.perf_counter
stages = {"serialize_s": 0.0, "cipher_s": 0.0, "publish_s": 0.0, "deserialize_s": 0.0}
done_at = []  # wall time of every processed message
state = {"received": 0, "errors": 0, "in_bytes_msgs": 0}
rospy.init_node("%s_%s" % (role, sensor), disable_signals=True)

if role == "enc":
    pub = rospy.Publisher(topic + "_enc", UInt8MultiArray, queue_size=1)

    def on_plain(msg):
        t0 = clock()
        buf = io.BytesIO()
        msg.serialize(buf)
        plain = buf.getvalue()
        t1 = clock()
        ct = encrypt(plain)
        t2 = clock()
        pub.publish(UInt8MultiArray(data=ct))
        t3 = clock()
        stages["serialize_s"] += t1 - t0
        stages["cipher_s"] += t2 - t1
        stages["publish_s"] += t3 - t2
        state["received"] += 1
        done_at.append(time.time())

    sub = rospy.Subscriber(topic, msg_type, on_plain, queue_size=1, buff_size=1 << 24)
else:
    pub = None

    def on_cipher(msg):
        t0 = clock()
        try:
            plain = decrypt(msg.data)
        except ValueError:  # a padding or tag that does not verify
            state["errors"] += 1
            return
        t1 = clock()
        out = msg_type()
        out.deserialize(plain)
        t2 = clock()
        stages["cipher_s"] += t1 - t0
        stages["deserialize_s"] += t2 - t1
        state["received"] += 1
        done_at.append(time.time())

    sub = rospy.Subscriber(topic + "_enc", UInt8MultiArray, on_cipher, queue_size=1, buff_size=1 << 24)

samples = []
stop = threading.Event()


seen = {"in": {}, "out": {}}


def wire(impl, direction):
    """Bytes through this topic's connections as rospy's transports count them (a
    connection that closed keeps its last count)."""
    try:
        conns = impl.get_stats()[1] if direction == "in" else impl.get_stats()[2]
        for c in conns:
            seen[direction][c[0]] = max(seen[direction].get(c[0], 0), c[1])
    except Exception:  # noqa: BLE001 - a connection going away while read
        pass
    return sum(seen[direction].values())


def sample():
    # process_time: nanoseconds; os.times() counts 10 ms ticks, and a plain laser node's
    # few ms in the steady window read 0 there (a fresh-clone run of the quick bench)
    samples.append([time.time(), time.process_time(), wire(sub.impl, "in"),
                    wire(pub.impl, "out") if pub is not None else 0, state["received"]])


def sampler():
    while not stop.wait(0.25):
        sample()


def finish(*_):
    stop.set()
    sample()
    tmp = stats_path + ".tmp"
    with open(tmp, "w") as fh:
        json.dump({"role": role, "sensor": sensor, "cipher": cipher_name, "pid": os.getpid(), "samples": samples,
                   "done_at": done_at, "stages": stages, "errors": state["errors"], "no_aesni": no_aesni}, fh)
    os.replace(tmp, stats_path)
    os._exit(0)


signal.signal(signal.SIGTERM, finish)
signal.signal(signal.SIGINT, finish)
deadline = time.monotonic() + 60
while sub.get_num_connections() < 1 if role == "dec" else pub.get_num_connections() < 1:
    if time.monotonic() > deadline:
        print("NOPEER", flush=True)
        break
    time.sleep(0.02)
threading.Thread(target=sampler, daemon=True).start()
print("READY", flush=True)
while True:
    time.sleep(1)
