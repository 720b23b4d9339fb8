"""Structured logs: one JSON object per line on stderr, with the service name and extra fields.

Use `log.info("msg", extra={"fields": {...}})` or the `kv()` helper for key/values.
"""

from __future__ import annotations

import json
import logging
import sys
import threading
import time
from collections.abc import Callable
from typing import Any


class JsonFormatter(logging.Formatter):
    def __init__(self, service: str) -> None:
        super().__init__()
        self.service = service

    def format(self, record: logging.LogRecord) -> str:
        doc: dict[str, Any] = {
            "ts": round(record.created, 3),
            "level": record.levelname,
            "service": self.service,
            "logger": record.name,
            "msg": record.getMessage(),
        }
        fields = getattr(record, "fields", None)
        if fields:
            doc.update(fields)
        if record.exc_info:
            doc["exc"] = self.formatException(record.exc_info)
        return json.dumps(doc, default=str)


class TextFormatter(logging.Formatter):
    def __init__(self, service: str) -> None:
        super().__init__()
        self.service = service

    def format(self, record: logging.LogRecord) -> str:
        stamp = time.strftime("%H:%M:%S", time.localtime(record.created))
        fields = getattr(record, "fields", None) or {}
        tail = " ".join(f"{k}={v}" for k, v in fields.items())
        text = f"{stamp} {record.levelname:<7} {self.service}: {record.getMessage()} {tail}".rstrip()
        if record.exc_info:
            text += "\n" + self.formatException(record.exc_info)
        return text


def setup_logging(service: str, level: str = "INFO", json_lines: bool = True) -> None:
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(JsonFormatter(service) if json_lines else TextFormatter(service))
    root = logging.getLogger()
    root.handlers[:] = [handler]
    root.setLevel(level)
    # PyOpenGL (imported with MuJoCo's renderer) says at INFO that an optional speed-up is missing: noise that
    # would come before a start-up error's one line
    logging.getLogger("OpenGL").setLevel(logging.WARNING)


def kv(**fields: Any) -> dict[str, Any]:
    """`log.info("stored", extra=kv(steps=3))`"""
    return {"fields": fields}


ROUTINE_LOG_EVERY_S = 60.0


class RoutineLog:
    """A line that comes with every version (published, applied; a checkpoint saved) would be ~450 a minute at
    publish_every 20, ~110 MB a day per experiment. Per key (an experiment, a checkpoint directory): the first line
    and the first after reset(key) (an error, the key gone) go out at INFO, the others at DEBUG, but at most one a
    minute at INFO again with since_last_info, how many lines there were since the last INFO one, itself included."""

    def __init__(
        self, message: str, every_s: float = ROUTINE_LOG_EVERY_S, clock: Callable[[], float] = time.monotonic
    ) -> None:
        self.message, self.every_s, self.clock = message, every_s, clock
        self._lock = threading.Lock()
        self._last: dict[str, tuple[float, int]] = {}  # key -> (clock at its last INFO line, DEBUG lines since)

    def log(self, logger: logging.Logger, key: str, **fields: Any) -> None:
        now = self.clock()
        with self._lock:
            last = self._last.get(key)
            if last is not None and now - last[0] < self.every_s:
                self._last[key] = (last[0], last[1] + 1)
                level = logging.DEBUG
            else:
                self._last[key] = (now, 0)
                level = logging.INFO
                if last is not None:
                    fields["since_last_info"] = last[1] + 1
        logger.log(level, self.message, extra=kv(**fields))

    def reset(self, key: str) -> None:
        """The next line for `key` at INFO (after an error); and the key's state goes (an experiment removed)."""
        with self._lock:
            self._last.pop(key, None)
