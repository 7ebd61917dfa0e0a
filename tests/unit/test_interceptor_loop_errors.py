"""The interceptor's event-loop exception handler (:func:`interceptor.cli.quiet_closed_transport`)."""

from __future__ import annotations

import asyncio
import logging


def test_a_write_to_a_closed_transport_is_a_debug_line_and_anything_else_the_default(caplog):
    from interceptor.cli import quiet_closed_transport

    loop = asyncio.new_event_loop()
    try:
        closed = RuntimeError("unable to perform operation on <TCPTransport closed=True reading=False 0x5561>; "
                              "the handler is closed")
        with caplog.at_level(logging.DEBUG):
            quiet_closed_transport(loop, {"message": "Fatal error on SSL protocol", "exception": closed,
                                          "protocol": object(), "transport": object()})
        quiet = [r for r in caplog.records if "Fatal error on SSL protocol" in r.getMessage()]
        assert [r.levelno for r in quiet] == [logging.DEBUG] and not quiet[0].exc_info
        caplog.clear()
        with caplog.at_level(logging.DEBUG):
            quiet_closed_transport(loop, {"message": "Fatal error: protocol.data_received() call failed.",
                                          "exception": ValueError("a bug in a protocol"), "protocol": object()})
        loud = [r for r in caplog.records if "data_received" in r.getMessage()]
        assert [r.levelno for r in loud] == [logging.ERROR] and loud[0].exc_info  # the default handler's
    finally:
        loop.close()
