"""The DDS bridge child of the ``ros2`` role: its process, its local socket, and its
restarts.

:class:`DdsBridge` starts :mod:`cryptoros.ros2.bridge_node` with the ROS 2 python on a
socketpair, in this robot's domain and the bridge's Fast DDS profile (the localhost-only
one, its readers and writers capped at :data:`~cryptoros.ros2.profile.BRIDGE_MAX_SAMPLES`
samples), waits for its hello, and when it dies starts another (after removing what dead
DDS processes left in /dev/shm). What the bridge says goes to the role's callbacks; what
the role sends goes down :attr:`DdsBridge.link`. Streams are the role's: this module
knows nothing of peers, grants or topics.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import shutil
import socket
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cryptoros.ros2
from cryptoros.errors import CryptorosError
from cryptoros.ros2 import framing as fr
from cryptoros.ros2.profile import PROFILE_ENV, localhost_env, segments_cleaned, shm_clean_command, write_bridge_profile

log = logging.getLogger("cryptoros.interceptor.ros2")

BRIDGE_SCRIPT = Path(cryptoros.ros2.__file__).resolve().parent / "bridge_node.py"
BRIDGE_START_TIMEOUT = 30.0
#: a dead bridge's successor starts this long after (a bridge dying at once is not spun);
#: doubled after each start that failed, up to RESTART_PAUSE_MAX
RESTART_PAUSE = 1.0
RESTART_PAUSE_MAX = 8.0
#: eProsima's ``fastdds shm clean`` before a bridge starts (0.1 s on a clean host, 0.5 s
#: with 1,270 dead segments to remove)
SHM_CLEAN_TIMEOUT = 15.0
LOCAL_SOCKET_BUFFER = 4 * 1024 * 1024


class BridgeLink(asyncio.Protocol):
    """The local socket to the bridge child: frames in, frames out."""

    def __init__(self, on_frame: Callable[[int, int, bytes], None], max_size: int,
                 on_messages: Callable[[int, int, bytearray], None] | None = None) -> None:
        self._on_frame = on_frame
        self._on_messages = on_messages
        self._decoder = fr.FrameDecoder(max_size=max_size + fr.LINK_SLACK)
        self.transport: asyncio.Transport | None = None
        self.closed = asyncio.get_running_loop().create_future()

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self.transport = transport  # type: ignore[assignment]

    def data_received(self, data: bytes) -> None:
        try:
            self._decoder.feed(data)
            # consecutive MESSAGE frames of one channel go on as one batch, kept whole (one copy)
            for kind, chan, count, frames in self._decoder.runs():
                if kind == fr.MESSAGE and self._on_messages is not None:
                    self._on_messages(chan, count, frames)
                    continue
                for payload in fr.payloads(frames):
                    self._on_frame(kind, chan, payload)
        except fr.FrameError as exc:
            log.error("the DDS bridge sent garbage (%s); restarting it", exc)
            self.transport.abort()

    def connection_lost(self, exc: Exception | None) -> None:
        if not self.closed.done():
            self.closed.set_result(None)

    def send(self, data: bytes) -> None:
        if self.transport is not None and not self.transport.is_closing():
            self.transport.write(data)

    def control(self, **body: Any) -> None:
        self.send(fr.encode_control(body))


class DdsBridge:
    """One bridge child at a time: :meth:`start`, :meth:`supervise` (restarts it when it
    dies, calling ``on_lost`` first), :meth:`stop`. ``on_frame`` gets every frame but
    batched messages, which go to ``on_messages``; the bridge's hello makes it
    :attr:`ready`."""

    def __init__(self, settings: Any, on_frame: Callable[[int, int, bytes], None],
                 on_messages: Callable[[int, int, bytearray], None]) -> None:
        self.settings = settings
        self._on_frame = on_frame
        self._on_messages = on_messages
        self.link: BridgeLink | None = None
        self.hello: dict[str, Any] = {}
        self._proc: asyncio.subprocess.Process | None = None
        self._ready = asyncio.Event()
        self._profile_dir: str | None = None

    @property
    def ready(self) -> bool:
        """The bridge said hello and has not died since."""
        return self._ready.is_set()

    def said_hello(self, body: dict[str, Any]) -> None:
        """The bridge's hello (a control frame the role reads): it is up."""
        self.hello = body
        self._ready.set()

    def _env(self) -> dict[str, str]:
        settings = self.settings
        env = dict(os.environ)
        env.pop("_ROS_WHEELS_BOOTSTRAP_COMPLETE", None)  # the ROS 2 venv sets up its own libraries
        env.update(ROS_DOMAIN_ID=str(settings.domain_id), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
        env = localhost_env(env)  # DDS on 127.0.0.1 and shared memory only: private to this host
        try:  # the same, with the bridge's readers and writers holding fewer samples
            if self._profile_dir is None:
                self._profile_dir = tempfile.mkdtemp(prefix="cryptoros-dds-")
            env[PROFILE_ENV] = str(write_bridge_profile(Path(self._profile_dir)))
        except OSError as exc:
            raise CryptorosError(f"cannot write the DDS bridge's profile into {self._profile_dir or tempfile.gettempdir()}: "
                                 f"{exc.strerror or exc}") from None
        # glibc mmaps (and page-faults) every buffer of 128 KiB or more, and gives the top of
        # its heap back past 128 KiB free; images are read and joined in such buffers: keep
        # them on the heap, and the heap (measured: bridges 75 us less per 80 KB image)
        env.setdefault("GLIBC_TUNABLES", "glibc.malloc.mmap_threshold=16777216:glibc.malloc.trim_threshold=67108864")
        return env

    async def start(self) -> None:
        """Start a bridge and wait for its hello (CryptorosError past BRIDGE_START_TIMEOUT)."""
        settings = self.settings
        env = self._env()
        await self._clean_dead_segments(env)
        self._ready.clear()
        parent, child = socket.socketpair(socket.AF_UNIX, socket.SOCK_STREAM)
        for sock in (parent, child):
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, LOCAL_SOCKET_BUFFER)
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, LOCAL_SOCKET_BUFFER)
        try:
            self._proc = await asyncio.create_subprocess_exec(
                str(settings.python), str(BRIDGE_SCRIPT), "--fd", str(child.fileno()), "--name", settings.node_name,
                "--graph-interval", str(settings.graph_interval), "--max-size", str(settings.max_message_size),
                pass_fds=(child.fileno(),), env=env, stdin=asyncio.subprocess.DEVNULL,
            )
        except BaseException:
            parent.close()
            raise
        finally:
            child.close()
        loop = asyncio.get_running_loop()
        _, self.link = await loop.connect_accepted_socket(
            lambda: BridgeLink(self._on_frame, settings.max_message_size, self._on_messages), sock=parent
        )
        # its hello, or its end: a bridge that cannot start (its python or rclpy broken) exits
        # at once, and was waited for all of BRIDGE_START_TIMEOUT
        ready, exited = asyncio.ensure_future(self._ready.wait()), asyncio.ensure_future(self._proc.wait())
        try:
            await asyncio.wait([ready, exited], timeout=BRIDGE_START_TIMEOUT, return_when=asyncio.FIRST_COMPLETED)
        finally:
            for waiter in (ready, exited):
                waiter.cancel()
        if not self._ready.is_set():
            status = self._proc.returncode
            await self.stop()
            if status is not None:
                raise CryptorosError(f"the DDS bridge ({settings.python}) exited with status {status} before it was "
                                     "up (its output is above)")
            raise CryptorosError(f"the DDS bridge ({settings.python}) did not start within {BRIDGE_START_TIMEOUT:.0f} s")
        log.info("DDS bridge up: pid %s, %s, domain %s", self.hello.get("pid"), self.hello.get("rmw"),
                 self.hello.get("domain"))

    async def stop(self) -> None:
        """Close the link and end the child (SIGTERM, then SIGKILL after 3 s)."""
        self._ready.clear()
        if self.link is not None and self.link.transport is not None:
            self.link.transport.close()
        proc = self._proc
        if proc is not None and proc.returncode is None:
            with contextlib.suppress(ProcessLookupError):
                proc.terminate()
            try:
                await asyncio.wait_for(proc.wait(), 3)
            except asyncio.TimeoutError:
                with contextlib.suppress(ProcessLookupError):
                    proc.kill()
                await proc.wait()
        if self._profile_dir is not None:
            shutil.rmtree(self._profile_dir, ignore_errors=True)
            self._profile_dir = None

    async def supervise(self, on_lost: Callable[[], None], stopping: Callable[[], bool]) -> None:
        """Restart the bridge whenever it dies (its process or its link), unless
        ``stopping()``. Not :attr:`ready` from the moment it is found dead: a stream the
        role accepted meanwhile would go to the dead bridge and carry nothing, for good.
        ``on_lost`` drops what it carried; the role sets it up again from scratch."""
        pause = RESTART_PAUSE
        while True:
            proc, link = self._proc, self.link
            if proc is not None and link is not None:
                await asyncio.wait([asyncio.ensure_future(proc.wait()), link.closed],
                                   return_when=asyncio.FIRST_COMPLETED)
                if stopping():
                    return
                if proc.returncode is None:  # the link closed first: the exit (a signal?) is a moment behind
                    with contextlib.suppress(asyncio.TimeoutError):
                        await asyncio.wait_for(proc.wait(), 1.0)
                rc = proc.returncode
                log.error("the DDS bridge %s; restarting it", "closed its link" if rc is None else
                          f"was killed by signal {-rc}" if rc < 0 else f"exited with status {rc}")
                await self.stop()  # not ready from here on
                on_lost()
            await asyncio.sleep(pause)
            if stopping():
                return
            try:
                await self.start()
                pause = RESTART_PAUSE
            except (CryptorosError, OSError) as exc:
                log.error("cannot restart the DDS bridge: %s; trying again in %g s", exc, min(pause * 2, RESTART_PAUSE_MAX))
                self._proc, self.link = None, None
                pause = min(pause * 2, RESTART_PAUSE_MAX)

    async def _clean_dead_segments(self, env: dict[str, str]) -> None:
        """Before a bridge starts (the first, or one after its predecessor died): remove the
        shared-memory files DDS processes on this host left when they died unclosed, the
        dead bridge's among them. Each held RAM in /dev/shm for good (measured on a test
        host: 1,270 segments, 1.4 GiB, in a day of killed nodes). Best effort: a robot
        without eProsima's tool, or where it fails, starts its bridge all the same."""
        python = self.settings.python
        command = shm_clean_command(python, env)
        if command is None:
            log.debug("no `fastdds` tool beside %s or on PATH: shared memory of dead DDS processes is left", python)
            return
        proc = None
        try:
            proc = await asyncio.create_subprocess_exec(*command, env=env, stdin=asyncio.subprocess.DEVNULL,
                                                        stdout=asyncio.subprocess.PIPE,
                                                        stderr=asyncio.subprocess.STDOUT)
            report, _ = await asyncio.wait_for(proc.communicate(), SHM_CLEAN_TIMEOUT)
        except (OSError, asyncio.TimeoutError) as exc:
            if proc is not None and proc.returncode is None:
                with contextlib.suppress(ProcessLookupError):
                    proc.kill()
                await proc.wait()
            log.warning("`%s` failed (%s): shared memory of dead DDS processes is left",
                        " ".join(command), str(exc) or "timed out")
            return
        text = report.decode(errors="replace")
        if proc.returncode:
            log.warning("`%s` exited with %s: %s", " ".join(command), proc.returncode, text.strip()[-300:])
        elif cleaned := segments_cleaned(text):
            log.info("removed %d shared-memory segment(s) of DDS processes that died without closing them", cleaned)


__all__ = ["BRIDGE_SCRIPT", "BridgeLink", "DdsBridge"]
