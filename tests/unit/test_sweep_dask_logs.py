"""The sweep's filter for distributed's interrupted-``sync`` traceback: that one record only."""

from __future__ import annotations

import logging
import sys

from groundstation.sweep import _InterruptedSyncFilter

_SOURCE = "def cancel():\n    return future\n"


def _record_raised_in(filename: str, name: str = "cancel") -> logging.LogRecord:
    namespace: dict[str, object] = {}
    exec(compile(_SOURCE.replace("cancel", name), filename, "exec"), namespace)
    try:
        namespace[name]()  # type: ignore[operator]
    except NameError:
        exc_info = sys.exc_info()
    return logging.LogRecord("tornado.application", logging.ERROR, __file__, 1,
                             "Exception in callback", None, exc_info)


def test_that_only_distributeds_interrupted_cancel_traceback_is_dropped() -> None:
    keep = _InterruptedSyncFilter().filter
    # Assert: distributed's cancel callback failing with a NameError is dropped
    assert not keep(_record_raised_in("/venv/site-packages/distributed/utils.py"))
    # ... the same error anywhere else, another function, or no exception at all passes
    assert keep(_record_raised_in("/venv/site-packages/tornado/ioloop.py"))
    assert keep(_record_raised_in("/venv/site-packages/distributed/utils.py", "wait"))
    assert keep(logging.LogRecord("tornado.application", logging.ERROR, __file__, 1,
                                  "Exception in callback", None, None))
