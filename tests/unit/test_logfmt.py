"""cryptoros.logfmt: a record is one line whatever a peer put in its message."""

from __future__ import annotations

import io
import logging

from cryptoros.logfmt import MAX_MESSAGE, configure, one_line


def test_control_characters_are_escaped_and_a_long_message_cut():
    assert one_line("/nope\n2026 INFO ALLOW\r\x00\t\x7f\u2028") == "/nope\\n2026 INFO ALLOW\\r\\x00\\t\\x7f\\u2028"
    assert one_line("caf\u00e9 /robot_a") == "caf\u00e9 /robot_a"  # printable text is left as it is
    cut = one_line("x" * (MAX_MESSAGE + 10))
    assert cut.startswith("x" * MAX_MESSAGE) and cut.endswith("... (10 more characters)")


def test_the_daemons_handler_keeps_a_record_on_one_line_and_its_own_traceback_whole():
    root, stream = logging.getLogger(), io.StringIO()
    saved, level = root.handlers[:], root.level
    root.handlers.clear()
    try:
        configure("info", "%(levelname)s %(message)s", stream)
        log = logging.getLogger("test.logfmt")
        log.warning("DENY topic from %s: %s", "robot_b", "/nope\nINFO ALLOW topic from robot_c")
        try:
            raise ValueError("boom")
        except ValueError:
            log.exception("failed on %s", "/a\nb")
    finally:
        for handler in root.handlers:
            handler.close()
        root.handlers[:] = saved
        root.setLevel(level)
    lines = stream.getvalue().splitlines()
    assert lines[0] == "WARNING DENY topic from robot_b: /nope\\nINFO ALLOW topic from robot_c"
    assert lines[1] == "ERROR failed on /a\\nb"
    assert lines[2] == "Traceback (most recent call last):" and lines[-1] == "ValueError: boom"
