"""Counting what this process's access control refuses, from Zenoh's trace log."""

from __future__ import annotations

import os
import re
import sys
import threading
from collections import Counter
from typing import Any

__all__ = ["AccessRefusals"]

ACL_TARGET = "zenoh::net::routing::interceptor::access_control"
_ANSI = re.compile(r"\x1b\[[0-9;]*m")
_THREAD = re.compile(r"ThreadId\((\d+)\)")
_CACHING = re.compile(r"caching permissions for `([^`]*)`")
_REFUSAL = re.compile(
    r"on (?P<link>\S+) is unauthorized to (?P<message>\w+) \((?P<flow>ingress|egress)\) "
    r"on (?P<key>\S+)"
)
_CN = re.compile(r"CertCommonName\(([^)]*)\)")


class AccessRefusals:
    """Counts what this process's access control refuses, from Zenoh's trace log.

    Zenoh judges a message on a key expression its sender declared once, when it caches the
    permissions of that key for the link (a line "caching permissions for `KEY`", then one
    decision per kind of message, on the same thread), and then drops that key's messages
    without a word; it judges, and logs, every message on an undeclared key. So there are two
    counts: :attr:`counts`, refused messages, and :attr:`cached`, the (who, message, flow,
    key) refused in advance, whose messages go uncounted.

    :meth:`start` (before the session opens: Zenoh's log is set up once per process) turns on
    the access-control trace and puts a pipe under file descriptor 1 (where Zenoh writes); a
    thread reads it, counts, and passes every line that is not the access control's on to the
    real stdout. :meth:`stop` puts stdout back.
    """

    def __init__(self) -> None:
        self.counts: Counter[tuple[str, str, str, str]] = Counter()
        """Refused messages by (who, message, flow, key)."""
        self.cached: set[tuple[str, str, str, str]] = set()
        """Refused in advance for a declared key: its messages are dropped uncounted."""
        self._caching: dict[str, str] = {}
        """Per Zenoh thread, the key whose permissions it is caching."""
        self._lock = threading.Lock()
        self._saved: int | None = None
        self._thread: threading.Thread | None = None

    def feed(self, line: str) -> bool:
        """Count ``line`` if it is a refusal; whether it is an access-control line at all."""
        text = _ANSI.sub("", line)
        if ACL_TARGET not in text:
            return False
        thread_m = _THREAD.search(text)
        thread = thread_m.group(1) if thread_m else ""
        caching = _CACHING.search(text)
        if caching is not None:
            self._caching[thread] = caching.group(1)
            return True
        m = _REFUSAL.search(text)
        if m is None:
            if "is authorized to" not in text:
                self._caching.pop(thread, None)
            return True
        cn = _CN.search(m["link"])
        what = (cn.group(1) if cn else "unauthenticated", m["message"].lower(), m["flow"], m["key"])
        with self._lock:
            if self._caching.get(thread) == m["key"]:
                self.cached.add(what)
            else:
                self._caching.pop(thread, None)
                self.counts[what] += 1
        return True

    @property
    def total(self) -> int:
        with self._lock:
            return sum(self.counts.values())

    def as_dict(self) -> dict[str, Any]:
        """``messages``: ``"<who> <message> <flow> <key>" -> count``; ``in_advance``: those
        refused for a declared key (sorted)."""
        with self._lock:
            return {
                "messages": {" ".join(k): n for k, n in sorted(self.counts.items())},
                "in_advance": sorted(" ".join(k) for k in self.cached),
            }

    def start(self) -> None:
        import zenoh

        sys.stdout.flush()
        read_end, write_end = os.pipe()
        self._saved = os.dup(1)
        os.dup2(write_end, 1)
        os.close(write_end)
        self._thread = threading.Thread(
            target=self._pump, args=(read_end, self._saved), name="relloc-acl-log", daemon=True
        )
        self._thread.start()
        zenoh.init_log_from_env_or(f"error,{ACL_TARGET}=trace")

    def stop(self) -> None:
        if self._saved is None:
            return
        sys.stdout.flush()
        os.dup2(self._saved, 1)  # the pipe's last write end closes: the pump ends
        if self._thread is not None:
            self._thread.join(timeout=5)
        os.close(self._saved)
        self._saved = None

    def _pump(self, read_end: int, out: int) -> None:
        pending = b""
        with os.fdopen(read_end, "rb", buffering=0) as pipe:
            while chunk := pipe.read(65536):
                lines = (pending + chunk).split(b"\n")
                pending = lines.pop()
                passed = [ln for ln in lines if not self.feed(ln.decode(errors="replace"))]
                if passed:
                    os.write(out, b"".join(ln + b"\n" for ln in passed))
        if pending and not self.feed(pending.decode(errors="replace")):
            os.write(out, pending)

    def lines(self) -> list[str]:
        """The refusals for people: a total, then each refused message kind, most frequent
        first."""
        with self._lock:
            items = self.counts.most_common()
            cached = len(self.cached)
        head = (
            f"refused by access control: {sum(n for _, n in items)} messages judged one by one; "
            f"{cached} (sender, message, key) refused in advance (cached: their messages are "
            "dropped unreported)"
        )
        return [head] + [
            f"  {who} may not {msg} {key} ({flow}): {n}" for (who, msg, flow, key), n in items
        ]
